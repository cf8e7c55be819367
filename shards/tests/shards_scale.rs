//! Scale measurement (not a pass/fail timing test; run explicitly):
//! `SLAG_SHARDS_SCALE="1000000:512:f32,f16,i8" cargo test --workspace --test shards_scale -- --ignored --nocapture`
//!
//! Generates a synthetic scene in-process (means in memory, vectors generated per tile and never
//! materialised for the whole scene), partitions it with a counting sink, checks coverage and
//! decodes a sample of shards, and prints shard count, count/size distribution, time and bytes
//! per Gaussian for each dtype.

use std::time::Instant;

use slag_common::shards::synthetic::SyntheticScene;
use slag_common::shards::{Dtype, GroundFrame, decode_shard};
use slag_shards::partition::{PartitionParams, UpChoice, partition_with};

fn pct(v: &mut [u64], p: f64) -> u64 {
    v.sort_unstable();
    v[((v.len() - 1) as f64 * p).round() as usize]
}

#[test]
#[ignore = "measurement; run explicitly with --ignored --nocapture"]
fn measure_partition_at_scale() {
    let spec =
        std::env::var("SLAG_SHARDS_SCALE").unwrap_or_else(|_| "1000000:512:f32,f16,i8".into());
    let max: usize = std::env::var("SLAG_SHARDS_MAX")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(65536);
    let mut parts = spec.split(':');
    let n: usize = parts.next().and_then(|s| s.parse().ok()).expect("N");
    let dim: usize = parts.next().and_then(|s| s.parse().ok()).expect("dim");
    let dtypes: Vec<Dtype> = parts
        .next()
        .unwrap_or("f16")
        .split(',')
        .map(|s| s.parse().expect("dtype"))
        .collect();
    let t = Instant::now();
    let scene = SyntheticScene::new(n, dim, 64, 2000.0, 42);
    println!(
        "scene: {n} Gaussians, dim {dim}, 64 clusters over 2 km x 2 km; means generated in {:.1}s",
        t.elapsed().as_secs_f64()
    );
    for dtype in dtypes {
        let params = PartitionParams {
            scene_id: "synthetic-scale".into(),
            max_per_shard: max,
            up: UpChoice::Given(GroundFrame::from_axis_name("z").expect("z")),
            dtype,
            to_map: None,
        };
        let mut checked = 0;
        let t = Instant::now();
        let m = partition_with(&scene, &params, |info, bytes| {
            if info.id % 16 == 0 {
                let s = decode_shard(&bytes).expect("decodes");
                assert_eq!(s.header.count as u64, info.count);
                checked += 1;
            }
            Ok(())
        })
        .expect("partition");
        let secs = t.elapsed().as_secs_f64();
        let total_bytes: u64 = m.tiles.iter().map(|t| t.bytes).sum();
        assert_eq!(m.tiles.iter().map(|t| t.count).sum::<u64>(), n as u64);
        assert!(m.tiles.iter().all(|t| t.count as usize <= max));
        let mut counts: Vec<u64> = m.tiles.iter().map(|t| t.count).collect();
        let mut sizes: Vec<u64> = m.tiles.iter().map(|t| t.bytes).collect();
        println!(
            "{dtype:?}: {} shards (max {max}/shard); count min/p50/max {}/{}/{}; bytes min/p50/max {}/{}/{}; total {:.3} GB, {:.1} B/Gaussian; partition+encode {:.1}s ({checked} shards decoded)",
            m.tiles.len(),
            pct(&mut counts, 0.0),
            pct(&mut counts, 0.5),
            pct(&mut counts, 1.0),
            pct(&mut sizes, 0.0),
            pct(&mut sizes, 0.5),
            pct(&mut sizes, 1.0),
            total_bytes as f64 / 1e9,
            total_bytes as f64 / n as f64,
            secs
        );
        // Optionally the same partition into a sled store (SLAG_SHARDS_STORE=1): commit time and
        // on-disk size.
        if std::env::var("SLAG_SHARDS_STORE").is_ok() {
            let dir = tempfile::tempdir().expect("tmp");
            let store = slag_shards::store::ShardStore::open(dir.path()).expect("open");
            let t = Instant::now();
            let m =
                slag_shards::store::partition_into_store(&store, &scene, &params).expect("store");
            let secs = t.elapsed().as_secs_f64();
            let disk: u64 = walk_size(dir.path());
            println!(
                "{dtype:?} into sled: generation {} committed in {secs:.1}s; store on disk {:.3} GB",
                m.generation,
                disk as f64 / 1e9
            );
        }
    }
}

fn walk_size(p: &std::path::Path) -> u64 {
    std::fs::read_dir(p)
        .map(|rd| {
            rd.filter_map(|e| e.ok())
                .map(|e| match e.metadata() {
                    Ok(m) if m.is_dir() => walk_size(&e.path()),
                    Ok(m) => m.len(),
                    Err(_) => 0,
                })
                .sum()
        })
        .unwrap_or(0)
}
