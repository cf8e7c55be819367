//! Partitioning: coverage, tile size bound, adaptivity, shard contents, radius selection
//! completeness, up-axis choice.

use proptest::prelude::*;
use slag_common::shards::synthetic::SyntheticScene;
use slag_common::shards::{
    Dtype, GaussianSource, GroundFrame, TileIndex, UpSource, decode_shard, shard_checksum,
};
use slag_shards::partition::{PartitionParams, UpChoice, partition};

fn params(max: usize, up: UpChoice, dtype: Dtype) -> PartitionParams {
    PartitionParams {
        scene_id: "synthetic-1".into(),
        max_per_shard: max,
        up,
        dtype,
        to_map: None,
    }
}

fn z_up() -> UpChoice {
    UpChoice::Given(GroundFrame::from_axis_name("z").expect("axis"))
}

#[test]
fn every_gaussian_lands_in_exactly_one_bounded_tile_with_its_own_vector() {
    let scene = SyntheticScene::new(5000, 16, 6, 200.0, 7);
    let emb = scene.to_embeddings();
    let (m, shards) = partition(&emb, &params(300, z_up(), Dtype::F32)).expect("partition");
    assert_eq!(m.total_gaussians, 5000);
    assert_eq!(m.tiles.len(), shards.len());
    assert!(m.tiles.len() >= 5000 / 300);
    let mut seen = vec![false; emb.len()];
    for (t, (id, bytes)) in m.tiles.iter().zip(&shards) {
        assert_eq!(t.id, *id);
        assert_eq!(t.bytes, bytes.len() as u64);
        assert_eq!(t.checksum, format!("{:08x}", shard_checksum(bytes)));
        assert!(
            t.count >= 1 && t.count <= 300,
            "tile {} holds {}",
            t.id,
            t.count
        );
        let s = decode_shard(bytes).expect("decode");
        assert_eq!(s.header.count as u64, t.count);
        assert_eq!(s.header.aabb, t.aabb);
        let poly = t.footprint_polygon();
        use geo::{BoundingRect, Contains, Intersects};
        let rect = poly.bounding_rect().expect("rect");
        for (k, &gid) in s.ids.iter().enumerate() {
            let row = (gid / 2) as usize; // synthetic ids are 2*row
            assert_eq!(emb.ids[row], gid);
            assert!(!seen[row], "Gaussian {gid} in two tiles");
            seen[row] = true;
            assert_eq!(s.means[k], emb.means[row]);
            assert_eq!(s.vector(k), emb.vector(row));
            let g = m.ground.to_ground(s.means[k]);
            let p = geo::Point::new(g[0], g[1]);
            assert!(
                rect.contains(&p) || rect.intersects(&p),
                "mean outside its footprint"
            );
        }
    }
    assert!(seen.iter().all(|&s| s), "some Gaussian is in no tile");
}

#[test]
fn display_attributes_travel_with_their_gaussians() {
    let scene = SyntheticScene::new(700, 4, 2, 30.0, 5);
    // .ply has 2N Gaussians (synthetic ids are 2*row); attributes encode the id.
    let scales: Vec<[f32; 3]> = (0..1400).map(|i| [i as f32, -(i as f32), 0.5]).collect();
    let opac: Vec<f32> = (0..1400).map(|i| i as f32 * 0.01).collect();
    let src = slag_common::shards::WithDisplay::new(&scene, &scales, &opac).expect("ids in range");
    let (_, shards) = partition(&src, &params(100, z_up(), Dtype::F16)).expect("partition");
    for (_, b) in &shards {
        let s = decode_shard(b).expect("decode");
        let (sc, op) = (s.scales.expect("scales"), s.opacities.expect("opacities"));
        for (k, &id) in s.ids.iter().enumerate() {
            assert_eq!(sc[k], scales[id as usize]);
            assert_eq!(op[k], opac[id as usize]);
        }
    }
    assert!(slag_common::shards::WithDisplay::new(&scene, &scales[..10], &opac).is_err());
}

#[test]
fn dense_areas_get_small_tiles_and_sparse_areas_large_ones() {
    // 20k Gaussians in a 2 m square, 2k spread over 400 m: max 500 per tile.
    let mut scene = SyntheticScene::new(22_000, 4, 1, 1.0, 3);
    for (i, m) in scene.means.iter_mut().enumerate() {
        let u = ((i * 7919) % 1000) as f32 / 1000.0;
        let v = ((i * 104_729) % 997) as f32 / 997.0;
        *m = if i < 20_000 {
            [100.0 + 2.0 * u, 100.0 + 2.0 * v, 0.0]
        } else {
            [400.0 * u, 400.0 * v, 0.0]
        };
    }
    let (m, _) = partition(&scene, &params(500, z_up(), Dtype::I8)).expect("partition");
    let area = |t: &slag_common::shards::TileInfo| {
        let f = &t.footprint;
        ((f[2][0] - f[0][0]) * (f[2][1] - f[0][1])) as f64
    };
    let dense: Vec<f64> = m
        .tiles
        .iter()
        .filter(|t| {
            t.footprint
                .iter()
                .all(|p| (99.0..=103.0f32).contains(&p[0]) && (99.0..=103.0f32).contains(&p[1]))
        })
        .map(area)
        .collect();
    let sparse_max = m.tiles.iter().map(area).fold(0.0, f64::max);
    assert!(dense.len() >= 40, "{} dense tiles", dense.len());
    assert!(dense.iter().all(|&a| a <= 4.0));
    assert!(
        sparse_max > 100.0 * dense.iter().fold(0.0, |a: f64, &b| a.max(b)),
        "sparse {sparse_max}"
    );
    assert!(m.tiles.iter().all(|t| t.count >= 1 && t.count <= 500));
}

#[test]
fn up_axis_is_estimated_or_taken_from_user_and_cameras() {
    let scene = SyntheticScene::new(3000, 4, 5, 100.0, 11);
    let (m, _) = partition(&scene, &params(1000, UpChoice::Pca, Dtype::F16)).expect("pca");
    assert_eq!(m.ground.up_source, UpSource::Pca);
    assert!(
        m.ground.up[2].abs() > 0.999,
        "synthetic scenes are z-up, PCA gave {:?}",
        m.ground.up
    );
    let (m, _) = partition(
        &scene,
        &params(
            1000,
            UpChoice::Given(GroundFrame::from_axis_name("-y").expect("y")),
            Dtype::F16,
        ),
    )
    .expect("user");
    assert_eq!(m.ground.up, [0.0, -1.0, 0.0]);
    assert_eq!(m.ground.up_source, UpSource::User);
    let ups = vec![[0.05, 0.0, 1.0], [-0.05, 0.0, 1.0], [0.0, 0.02, 0.9]];
    let (m, _) =
        partition(&scene, &params(1000, UpChoice::CameraUps(ups), Dtype::F16)).expect("cams");
    assert_eq!(m.ground.up_source, UpSource::Cameras);
    assert!(m.ground.up[2] > 0.999);
}

#[test]
fn bad_parameters_are_typed_errors() {
    let scene = SyntheticScene::new(10, 4, 1, 10.0, 1);
    assert!(partition(&scene, &params(0, z_up(), Dtype::F16)).is_err());
    let mut p = params(5, z_up(), Dtype::F16);
    p.scene_id = "../etc".into();
    assert!(matches!(
        partition(&scene, &p),
        Err(slag_common::Error::Param {
            name: "scene_id",
            ..
        })
    ));
    let mut bad = scene.to_embeddings();
    bad.means[3][1] = f32::NAN;
    assert!(matches!(
        partition(&bad, &params(5, z_up(), Dtype::F16)),
        Err(slag_common::Error::Invalid(_))
    ));
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]
    /// On random partitioned scenes the R-tree returns exactly the tiles whose footprint meets the
    /// disc (brute force over all tiles), and every Gaussian within the radius is in one of them.
    #[test]
    fn radius_selection_on_partitioned_scenes(seed in 0u64..1000, n in 1usize..3000, max in 1usize..400,
            cx in -20f64..220.0, cy in -20f64..220.0, r in 0f64..80.0) {
        let scene = SyntheticScene::new(n, 2, 4, 200.0, seed);
        let (m, shards) = partition(&scene, &params(max, z_up(), Dtype::F16)).expect("partition");
        let idx = TileIndex::new(&m.tiles);
        let got = idx.select_tiles([cx, cy], r);
        let want: Vec<u64> = m.tiles.iter().filter(|t| {
            let (lo, hi) = (t.footprint[0].map(f64::from), t.footprint[2].map(f64::from));
            let dx = (lo[0] - cx).max(0.0).max(cx - hi[0]);
            let dy = (lo[1] - cy).max(0.0).max(cy - hi[1]);
            (dx * dx + dy * dy).sqrt() <= r
        }).map(|t| t.id).collect();
        prop_assert_eq!(&got, &want);
        for (id, bytes) in &shards {
            let s = decode_shard(bytes).expect("decode");
            for mean in &s.means {
                let g = m.ground.to_ground(*mean);
                if ((g[0] - cx).powi(2) + (g[1] - cy).powi(2)).sqrt() <= r {
                    prop_assert!(got.contains(id), "Gaussian within radius in unselected tile {}", id);
                }
            }
        }
        prop_assert_eq!(scene.ids().len(), n);
    }
}

// ---- Byte-sized shards (`--max-shard-mb`) and the stored-vs-dense report ----

use slag_common::shards::{ShardInput, encode_shard};
use slag_shards::partition::{MIB, ShardCap, resolve_max_per_shard, shard_layout, storage_report};

/// Shard header length written by `encode_shard`, from the format's module doc (72 fixed bytes
/// + scene id + model id + CRC, padded to 8), computed here independently of `ShardLayout`.
fn header_len(scene: &str, model: &str) -> u64 {
    ((72 + scene.len() + model.len() + 4) as u64).div_ceil(8) * 8
}

/// Payload bytes per dim-`d` row (id + mean + vector) per the format's module doc.
fn row_bytes(dtype: Dtype, d: u64) -> u64 {
    16 + match dtype {
        Dtype::F32 => 4 * d,
        Dtype::F16 => 2 * d,
        Dtype::I8 => 4 + d,
    }
}

#[test]
fn a_byte_budget_caps_shards_of_every_dtype_and_f16_fills_it() {
    let budget_mib = 0.25;
    let ShardCap::Bytes(budget) = ShardCap::from_mib(budget_mib).expect("cap") else {
        panic!("--max-shard-mb must give a byte cap");
    };
    assert_eq!(budget, 262_144);
    let scene = SyntheticScene::new(1004, 512, 5, 100.0, 11);
    let emb = scene.to_embeddings();
    let h = header_len("synthetic-1", &emb.model);
    let mut caps = Vec::new();
    for dtype in [Dtype::F32, Dtype::F16, Dtype::I8] {
        let row = row_bytes(dtype, 512);
        let layout = shard_layout(&emb, "synthetic-1", dtype);
        let cap = resolve_max_per_shard(&layout, ShardCap::Bytes(budget)).expect("resolves");
        // dim 512 rows keep every section 4-aligned: no padding, so the cap is plain division.
        assert_eq!(cap as u64, (budget - h) / row, "{dtype:?}");
        caps.push(cap);
        let (m, shards) = partition(&emb, &params(cap, z_up(), dtype)).expect("partition");
        assert_eq!(m.max_per_shard, cap as u64);
        assert_eq!(m.total_gaussians, 1004);
        let largest = shards
            .iter()
            .map(|(_, b)| b.len() as u64)
            .max()
            .expect("shards");
        for (t, (_, bytes)) in m.tiles.iter().zip(&shards) {
            assert!(
                bytes.len() as u64 <= budget,
                "{dtype:?} tile {} is {} bytes > {budget}",
                t.id,
                bytes.len()
            );
            assert_eq!(
                bytes.len() as u64,
                h + t.count * row,
                "{dtype:?} size model"
            );
        }
        // The cap is tight: one more row, actually encoded, no longer fits.
        let k = cap + 1;
        let big = encode_shard(&ShardInput {
            scene_id: "synthetic-1",
            model: &emb.model,
            tile_id: 0,
            dim: 512,
            dtype,
            ids: &emb.ids[..k],
            means: &emb.means[..k],
            vectors: &emb.vectors[..k * 512],
            scales: None,
            opacities: None,
            rotations: None,
            sh_dc: None,
            segments: None,
        })
        .expect("encode");
        assert!(big.len() as u64 > budget, "{dtype:?}: {} rows fit", k);
        if dtype == Dtype::F16 {
            // 1004 = 4 × 251: median splits make four full tiles, each within one row of the
            // budget.
            assert_eq!(shards.len(), 4);
            assert!(
                budget - largest < row,
                "f16 shard {largest} bytes, budget {budget}"
            );
            assert!(largest as f64 >= 0.99 * budget as f64);
        }
    }
    // The download unit is the same; the Gaussians per shard follow the bytes per row.
    assert_eq!(caps, vec![126, 251, 492]);
}

#[test]
fn byte_budgets_too_small_for_one_gaussian_are_typed_errors_with_a_remedy() {
    let emb = SyntheticScene::new(10, 512, 1, 10.0, 1).to_embeddings();
    let layout = shard_layout(&emb, "s", Dtype::F32);
    let one = header_len("s", &emb.model) + row_bytes(Dtype::F32, 512);
    // The library names the parameter; the command line adds the flag.
    for (cap, name, flag) in [
        (ShardCap::Bytes(0), "max_shard_mib", "--max-shard-mb"),
        (ShardCap::Gaussians(0), "max_per_shard", "--max-per-shard"),
    ] {
        let e = resolve_max_per_shard(&layout, cap).expect_err("refused");
        assert!(
            matches!(&e, slag_common::Error::Param { name: n, .. } if *n == name),
            "{e}"
        );
        assert!(!e.to_string().contains("--"), "{e}");
        let hint = slag_shards::cli::hint_for(&e).unwrap_or_default();
        assert!(hint.contains(flag), "{hint}");
    }
    for bad in [0.0, -1.0, f64::NAN, f64::INFINITY, 1e-9] {
        assert!(
            matches!(
                ShardCap::from_mib(bad),
                Err(slag_common::Error::Param {
                    name: "max_shard_mib",
                    ..
                })
            ),
            "{bad}"
        );
    }
    assert_eq!(
        resolve_max_per_shard(&layout, ShardCap::Bytes(one)).expect("one row fits"),
        1
    );
    let Err(e @ slag_common::Error::Param { .. }) =
        resolve_max_per_shard(&layout, ShardCap::Bytes(one - 1))
    else {
        panic!("a budget one byte short of one row must be rejected");
    };
    let msg = e.to_string();
    assert!(msg.contains(&format!("{one} bytes")), "{msg}");
    // The suggested budget works.
    let suggested: f64 = msg
        .rsplit("at least ")
        .next()
        .and_then(|t| t.split_whitespace().next())
        .and_then(|t| t.parse().ok())
        .unwrap_or_else(|| panic!("no suggestion in {msg:?}"));
    let cap = ShardCap::from_mib(suggested).expect("suggested cap");
    assert_eq!(resolve_max_per_shard(&layout, cap).expect("fits"), 1);
    // A count is taken as is.
    assert_eq!(
        resolve_max_per_shard(&layout, ShardCap::Gaussians(7)).expect("count"),
        7
    );
}

#[test]
fn storage_report_compares_stored_shards_with_a_dense_f32_scene() {
    let dir = tempfile::tempdir().expect("tmp");
    let store = slag_shards::store::ShardStore::open(&dir.path().join("s")).expect("store");
    let emb = SyntheticScene::new(600, 512, 3, 50.0, 5).to_embeddings();
    assert_eq!(emb.scene_gaussians, 1200); // every other .ply Gaussian observed
    let p = PartitionParams {
        scene_id: "tiny".into(),
        ..params(250, z_up(), Dtype::F16)
    };
    let m = slag_shards::store::partition_into_store(&store, &emb, &p).expect("partition");
    let stored = store.scene_bytes("tiny").expect("read").expect("scene");
    // Independently: each shard is its header plus 1040 bytes per f16 row.
    let expected = m.tiles.len() as u64 * header_len("tiny", &emb.model) + 600 * 1040;
    assert_eq!(stored, expected);
    let r = storage_report(&m, Some(emb.scene_gaussians), stored);
    assert_eq!(r.scene_gaussians, Some(1200));
    assert_eq!(r.rows_stored, 600);
    assert_eq!(r.dropped, Some(600));
    assert_eq!(r.dtype, Dtype::F16);
    assert_eq!(r.shards, m.tiles.len() as u64);
    assert_eq!(r.bytes_stored, expected);
    assert_eq!(r.dense_rows, 1200);
    assert_eq!(r.dense_f32_bytes, 1200 * 512 * 4);
    assert!((r.ratio - expected as f64 / 2_457_600.0).abs() < 1e-12);
    assert!(r.ratio < 0.26); // half the rows dropped, half the bytes per value, + 16 B/row
    let line = r.to_string();
    assert!(
        line.contains("600 of 1200") && line.contains(&expected.to_string()),
        "{line}"
    );
    // Without a recorded scene count the baseline is the stored rows.
    let r = storage_report(&m, None, stored);
    assert_eq!(
        (r.scene_gaussians, r.dropped, r.dense_rows),
        (None, None, 600)
    );
    assert_eq!(r.dense_f32_bytes, 600 * 2048);
    assert!(r.to_string().contains("not recorded"));
    assert_eq!(storage_report(&m, Some(0), stored).dense_rows, 600);
    // More bytes than the dense baseline is reported as such, never as "smaller".
    let line = storage_report(&m, None, 2 * 600 * 2048).to_string();
    assert!(
        line.contains("200.00 % of dense") && !line.contains("smaller"),
        "{line}"
    );
}

#[derive(clap::Parser)]
struct PartitionCli {
    #[command(flatten)]
    args: slag_shards::cli::PartitionArgs,
}

fn parse(extra: &[&str]) -> Result<PartitionCli, clap::Error> {
    use clap::Parser;
    let base = [
        "partition",
        "--synthetic",
        "10",
        "--shard-store",
        "S",
        "--scene",
        "x",
    ];
    PartitionCli::try_parse_from(base.iter().chain(extra))
}

#[test]
fn partition_cli_sizes_shards_in_mib_by_default_and_counts_on_request() {
    let a = parse(&[]).expect("parse").args;
    assert_eq!(a.shard_cap().expect("cap"), ShardCap::Bytes(16 * MIB));
    let a = parse(&["--max-shard-mb", "0.5"]).expect("parse").args;
    assert_eq!(a.shard_cap().expect("cap"), ShardCap::Bytes(MIB / 2));
    let a = parse(&["--max-per-shard", "100"]).expect("parse").args;
    assert_eq!(a.shard_cap().expect("cap"), ShardCap::Gaussians(100));
    let e = parse(&["--max-per-shard", "100", "--max-shard-mb", "4"])
        .err()
        .expect("both flags conflict");
    assert_eq!(e.kind(), clap::error::ErrorKind::ArgumentConflict);
    let a = parse(&["--max-shard-mb", "0"]).expect("parse").args;
    assert!(matches!(
        a.shard_cap(),
        Err(slag_common::Error::Param { .. })
    ));
}

#[test]
fn synthetic_partition_honours_the_byte_budget_and_writes_the_report() {
    let dir = tempfile::tempdir().expect("tmp");
    let store = dir.path().join("store");
    let report = dir.path().join("report.json");
    let budget = MIB / 8; // 131072 bytes
    let mut a = parse(&["--max-shard-mb", "0.125", "--dtype", "int8"])
        .expect("parse")
        .args;
    a.scene = "syn".into();
    a.synthetic = Some("1000:512".into());
    a.store = store.clone();
    a.report = Some(report.clone());
    slag_shards::cli::run_partition(&a).expect("partition");
    let s = slag_shards::store::ShardStore::open(&store).expect("store");
    let m = s.manifest("syn").expect("read").expect("scene");
    let h = header_len("syn", "synthetic");
    let row = row_bytes(Dtype::I8, 512);
    assert_eq!(m.max_per_shard, (budget - h) / row);
    let mut total = 0;
    for t in &m.tiles {
        let b = s.shard("syn", t.id).expect("read").expect("shard");
        assert!(b.len() as u64 <= budget, "tile {} {} bytes", t.id, b.len());
        total += b.len() as u64;
    }
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&report).expect("report written")).expect("json");
    assert_eq!(json["rows_stored"], 1000);
    assert_eq!(json["bytes_stored"], total);
    assert_eq!(json["dtype"], "i8");
    assert_eq!(json["scene_gaussians"], serde_json::Value::Null);
    assert_eq!(json["dense_f32_bytes"], 1000 * 512 * 4);
    // The budget is refused when it cannot hold one Gaussian, before the store is touched.
    a.max_shard_mb = 0.0004; // 419 bytes < 88 + 532
    a.report = None;
    a.store = dir.path().join("never-created");
    let e = slag_shards::cli::run_partition(&a).expect_err("too small");
    // The library names the parameter and what fits; the command line's hint names the flag.
    assert!(format!("{e:#}").contains("max_shard_mib"), "{e:#}");
    assert!(
        slag_shards::cli::hint(&e).is_some_and(|h| h.contains("--max-shard-mb")),
        "{e:#}"
    );
    assert!(!a.store.exists());
}

#[test]
fn partition_records_the_scene_to_map_transform_from_a_file_or_surveyed_points() {
    use slag_common::shards::{MapSource, SceneToMap};
    let dir = tempfile::tempdir().expect("tmp");
    // A known transform: yaw 90° about z after a tilt, scale 4, UTM-like offset.
    let h = std::f64::consts::FRAC_PI_4;
    let truth = SceneToMap::new(
        4.0,
        slag_common::shards::frame::quaternion_to_matrix([h.cos(), 0.0, 0.0, h.sin()]),
        [350_000.0, 5_600_000.0, 12.0],
        MapSource::File,
    )
    .expect("transform");
    let file = dir.path().join("to-map.json");
    std::fs::write(
        &file,
        serde_json::json!({"scale": 4.0, "quaternion_wxyz": truth.quaternion_wxyz(),
                           "translation": truth.translation})
        .to_string(),
    )
    .expect("write");
    let scene_pts = [
        [0.0, 0.0, 0.0],
        [10.0, 0.0, 0.5],
        [0.0, 7.0, 0.2],
        [5.0, 5.0, 3.0],
    ];
    let pairs: Vec<serde_json::Value> = scene_pts
        .iter()
        .map(|&p| serde_json::json!({"scene": p, "map": truth.to_map(p)}))
        .collect();
    let points = dir.path().join("points.json");
    std::fs::write(&points, serde_json::json!({ "pairs": pairs }).to_string()).expect("write");
    for (flag, path, source) in [
        ("--to-map", &file, MapSource::File),
        ("--to-map-points", &points, MapSource::Points),
    ] {
        let store = dir.path().join(format!("store{flag}"));
        let mut a = parse(&[flag, path.to_str().expect("utf-8")])
            .expect("parse")
            .args;
        a.scene = "syn".into();
        a.synthetic = Some("500:8".into());
        a.store = store.clone();
        slag_shards::cli::run_partition(&a).expect("partition");
        let s = slag_shards::store::ShardStore::open(&store).expect("store");
        let m = s.manifest("syn").expect("read").expect("scene");
        assert_eq!(m.frames.data, "scene");
        let t = m.frames.scene_to_map.clone().expect("transform stored");
        assert_eq!(t.source, source);
        assert!((t.scale - 4.0).abs() < 1e-9, "{}", t.scale);
        let p = [3.0, -2.0, 1.0];
        let (x, y) = (t.to_map(p), truth.to_map(p));
        assert!((0..3).all(|i| (x[i] - y[i]).abs() < 1e-6), "{x:?} {y:?}");
        if source == MapSource::Points {
            assert!(t.rms_residual.expect("rms") < 1e-6);
            assert_eq!(t.points, Some(4));
        }
        // Without --up, tiles lie on the map's ground: up = the map's z seen from the scene.
        assert_eq!(m.ground.up_source, UpSource::Map);
        let u = t.map_up_in_scene();
        assert!((0..3).all(|i| (m.ground.up[i] as f64 - u[i]).abs() < 1e-6));
        // The manifest JSON round-trips with the transform (serde_json parses f64 to within an
        // ulp, not always bit-exactly, without its float_roundtrip feature).
        let mut back = slag_common::shards::Manifest::from_json(&m.to_json(), "m").expect("json");
        let bt = back.frames.scene_to_map.take().expect("transform");
        for i in 0..3 {
            for k in 0..3 {
                assert!((bt.rotation[i][k] - t.rotation[i][k]).abs() <= 1e-15);
            }
        }
        assert_eq!((bt.scale, bt.translation), (t.scale, t.translation));
        let mut m2 = m.clone();
        m2.frames.scene_to_map = None;
        assert_eq!(back, m2);
    }
    // Too few or collinear points are typed errors before anything is stored.
    std::fs::write(
        &points,
        serde_json::json!({ "pairs": &pairs[..2] }).to_string(),
    )
    .expect("write");
    let mut a = parse(&["--to-map-points", points.to_str().expect("utf-8")])
        .expect("parse")
        .args;
    a.store = dir.path().join("never-created");
    let e = slag_shards::cli::run_partition(&a).expect_err("2 points");
    assert!(format!("{e:#}").contains("at least 3"), "{e:#}");
    assert!(!a.store.exists());
    // Both sources at once are refused by the parser.
    assert!(parse(&["--to-map", "identity", "--to-map-points", "p.json"]).is_err());
}

#[test]
fn manifests_without_frames_read_as_the_scene_frame() {
    let scene = SyntheticScene::new(200, 8, 3, 50.0, 3);
    let emb = scene.to_embeddings();
    let (m, _) = partition(&emb, &params(100, z_up(), Dtype::F16)).expect("partition");
    let mut v: serde_json::Value = serde_json::from_slice(&m.to_json()).expect("json");
    v.as_object_mut().expect("object").remove("frames");
    let old = slag_common::shards::Manifest::from_json(v.to_string().as_bytes(), "old")
        .expect("an old manifest parses");
    assert_eq!(old.frames.data, "scene");
    assert!(old.frames.scene_to_map.is_none());
    assert_eq!(old, m);
}
