//! Partitioning and radius selection on a real scene: the snowmiku 3DGS means (120k Gaussians)
//! with its training cameras' up vectors; embeddings are synthetic (the encoder output is not part
//! of the shared data). The means and cameras are read here with a minimal reader of the INRIA
//! `.ply` (float properties, little-endian) and `cameras.json` (camera-to-world `rotation`
//! rows), so the test does not depend on the scene loaders being written in parallel.

use slag_common::embeddings::Embeddings;
use slag_common::shards::{Dtype, TileIndex, UpSource, decode_shard};
use slag_encoder::partition::{PartitionParams, UpChoice, partition};

#[test]
fn snowmiku_partition_and_radius_selection() {
    let dir = slag_common::paths::shared_dir().join("scenes/snowmiku");
    let means = read_means(&dir.join("point_cloud.ply"));
    let cams: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("cameras.json")).expect("cameras.json"))
            .expect("json");
    // Camera -y axis in world = -(column 1 of the camera-to-world rotation).
    let ups: Vec<[f64; 3]> = cams
        .as_array()
        .expect("list")
        .iter()
        .map(|c| {
            let r = &c["rotation"];
            let at = |i: usize| r[i][1].as_f64().expect("rotation entry");
            [-at(0), -at(1), -at(2)]
        })
        .collect();
    assert_eq!(ups.len(), 97);
    let n = means.len();
    assert_eq!(n, 120_000);
    let dim = 8;
    let mut vectors = vec![0.0f32; n * dim];
    for (i, row) in vectors.chunks_exact_mut(dim).enumerate() {
        row[i % dim] = 1.0;
    }
    let emb = Embeddings {
        ids: (0..n as u32).collect(),
        means: means.clone(),
        dim,
        vectors,
        total_weights: vec![1.0; n],
        model: "unit-basis".into(),
        scene_gaussians: n as u64,
        source_ply: "snowmiku".into(),
    };
    let params = PartitionParams {
        scene_id: "snowmiku".into(),
        max_per_shard: 4096,
        up: UpChoice::CameraUps(ups),
        dtype: Dtype::F16,
    };
    let (m, shards) = partition(&emb, &params).expect("partition");
    assert_eq!(m.ground.up_source, UpSource::Cameras);
    assert_eq!(m.total_gaussians, n as u64);
    assert!(m.tiles.iter().all(|t| t.count >= 1 && t.count <= 4096));
    assert_eq!(m.tiles.iter().map(|t| t.count).sum::<u64>(), n as u64);
    // Ground coordinates of every Gaussian, per tile.
    let decoded: Vec<_> = shards
        .iter()
        .map(|(_, b)| decode_shard(b).expect("decode"))
        .collect();
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for s in &decoded {
        for mean in &s.means {
            let p = m.ground.to_ground(*mean);
            for a in 0..2 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
    }
    let idx = TileIndex::new(&m.tiles);
    let extent = (hi[0] - lo[0]).max(hi[1] - lo[1]);
    let mut state = 99u64;
    let mut rnd = || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    for _ in 0..200 {
        let c = [
            lo[0] + (hi[0] - lo[0]) * rnd(),
            lo[1] + (hi[1] - lo[1]) * rnd(),
        ];
        let r = extent * 0.3 * rnd();
        let got = idx.select_tiles(c, r);
        let want: Vec<u64> = m
            .tiles
            .iter()
            .filter(|t| {
                let (a, b) = (t.footprint[0].map(f64::from), t.footprint[2].map(f64::from));
                let dx = (a[0] - c[0]).max(0.0).max(c[0] - b[0]);
                let dy = (a[1] - c[1]).max(0.0).max(c[1] - b[1]);
                (dx * dx + dy * dy).sqrt() <= r
            })
            .map(|t| t.id)
            .collect();
        assert_eq!(got, want);
        for (t, s) in m.tiles.iter().zip(&decoded) {
            let inside = s.means.iter().any(|mean| {
                let p = m.ground.to_ground(*mean);
                ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2)).sqrt() <= r
            });
            assert!(
                !inside || got.contains(&t.id),
                "tile {} has a Gaussian in the disc",
                t.id
            );
        }
    }
    let pca = slag_common::shards::GroundFrame::from_pca(&means).expect("pca");
    let cos: f32 = (0..3).map(|a| pca.up[a] * m.ground.up[a]).sum();
    eprintln!(
        "snowmiku: {} tiles, camera up {:?}, PCA up {:?} (|cos| {:.3}), ground extent {extent:.2}",
        m.tiles.len(),
        m.ground.up,
        pca.up,
        cos.abs()
    );
}

/// `x y z` of every vertex of a binary little-endian `.ply` whose properties are all `float`.
fn read_means(path: &std::path::Path) -> Vec<[f32; 3]> {
    let bytes = std::fs::read(path).expect("ply");
    let end = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .expect("header")
        + 11;
    let header = std::str::from_utf8(&bytes[..end]).expect("ascii header");
    assert!(header.contains("binary_little_endian"));
    let mut n = 0usize;
    let mut props = Vec::new();
    for line in header.lines() {
        let w: Vec<&str> = line.split_whitespace().collect();
        match w.as_slice() {
            ["element", "vertex", k] => n = k.parse().expect("count"),
            ["property", "float", name] => props.push(name.to_string()),
            ["property", ..] => panic!("non-float property {line}"),
            _ => {}
        }
    }
    let stride = 4 * props.len();
    let col = |name: &str| props.iter().position(|p| p == name).expect("x/y/z");
    let (x, y, z) = (col("x"), col("y"), col("z"));
    let body = &bytes[end..];
    assert_eq!(body.len(), n * stride);
    let f = |v: usize, c: usize| {
        let o = v * stride + 4 * c;
        f32::from_le_bytes([body[o], body[o + 1], body[o + 2], body[o + 3]])
    };
    (0..n).map(|v| [f(v, x), f(v, y), f(v, z)]).collect()
}
