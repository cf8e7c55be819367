//! Partitioning and radius selection on a real scene: the snowmiku 3DGS means (120k Gaussians)
//! with its training cameras' up vectors; embeddings are synthetic (the encoder output is not part
//! of the shared data). Means and cameras come from the real loaders (`load_ply`, `load_views`).

use slag_common::embeddings::Embeddings;
use slag_common::shards::{Dtype, TileIndex, UpSource, decode_shard};
use slag_shards::partition::{PartitionParams, UpChoice, partition};

#[test]
fn snowmiku_partition_and_radius_selection() {
    let dir = slag_common::paths::source_tree_shared_dir().join("scenes/snowmiku");
    let means = slag_common::scene::load_ply(&dir.join("point_cloud.ply"), Default::default())
        .expect("ply")
        .means;
    // Camera -y axis in world = -(row 1 of the world-to-camera rotation).
    let ups: Vec<[f64; 3]> = slag_common::camera::load_views(&dir)
        .expect("views")
        .iter()
        .map(|v| {
            let up = -v.world_to_camera.rotation.row(1);
            [up.x, up.y, up.z]
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
        to_map: None,
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
