//! Partitioning: coverage, tile size bound, adaptivity, shard contents, radius selection
//! completeness, up-axis choice.

use proptest::prelude::*;
use slag_common::shards::synthetic::SyntheticScene;
use slag_common::shards::{
    Dtype, GaussianSource, GroundFrame, TileIndex, UpSource, decode_shard, shard_checksum,
};
use slag_encoder::partition::{PartitionParams, UpChoice, partition};

fn params(max: usize, up: UpChoice, dtype: Dtype) -> PartitionParams {
    PartitionParams {
        scene_id: "synthetic-1".into(),
        max_per_shard: max,
        up,
        dtype,
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
        Err(slag_common::Error::Invalid(_))
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
