//! Memory of loading an edge store: builds a store of synthetic f16 shards, then loads it
//! the way `slag-edge serve` does and prints the process's resident memory (`VmRSS`, Linux
//! `/proc/self/status`) and its large anonymous mappings (`/proc/self/smaps`) after each stage.
//!
//! ```sh
//! cargo run --example store_rss -- build DIR [TILES=16] [PER_TILE=65536] [DIM=512]
//! cargo run --example store_rss -- load DIR      # a fresh process, like `serve`
//! ```
//!
//! Each tile of the synthetic scene is one shard of `PER_TILE` Gaussians with `DIM`-d f16 vectors
//! (the load test's 1M × 512 scene is 16 tiles of 62,500; the defaults give 67 MB shards).
#![allow(clippy::unwrap_used)]

use std::path::Path;

use slag_common::shards::{
    Aabb, Dtype, GroundFrame, MANIFEST_FORMAT, MANIFEST_VERSION, Manifest, SHARD_FORMAT_VERSION,
    ShardInput, TileInfo, encode_shard, shard_checksum,
};
use slag_edge::store::{EdgeStore, FetchRecord};

fn status(key: &str) -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with(key))
                .and_then(|l| l.split_whitespace().nth(1).and_then(|v| v.parse().ok()))
        })
        .unwrap_or(0)
}

/// Prints VmRSS/VmHWM and every anonymous mapping of at least 16 MiB (its resident size).
fn report(stage: &str) {
    let mut big = Vec::new();
    if let Ok(s) = std::fs::read_to_string("/proc/self/smaps") {
        let mut anon_map = false;
        let mut size = 0u64;
        for l in s.lines() {
            let f: Vec<&str> = l.split_whitespace().collect();
            if f.first()
                .is_some_and(|a| a.contains('-') && !a.ends_with(':'))
            {
                // Mapping header: address perms offset dev inode [path].
                anon_map = f.len() == 5;
            } else if f.first() == Some(&"Size:") {
                size = f[1].parse().unwrap_or(0);
            } else if f.first() == Some(&"Rss:") && anon_map {
                let rss: u64 = f[1].parse().unwrap_or(0);
                if rss >= 16 * 1024 {
                    big.push(format!("{}/{} MiB", rss / 1024, size / 1024));
                }
            }
        }
    }
    println!(
        "{stage:<48} VmRSS {:>6} MiB  VmHWM {:>6} MiB  anon ≥16 MiB (rss/size): [{}]",
        status("VmRSS:") / 1024,
        status("VmHWM:") / 1024,
        big.join(", ")
    );
}

fn build(dir: &Path, tiles: usize, per_tile: usize, dim: usize) {
    let store = EdgeStore::open(dir).unwrap();
    let mut seed = 0x9E37_79B9_7F4A_7C15u64;
    let mut next = move || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        (seed >> 40) as f32 / (1u64 << 24) as f32 - 0.5
    };
    let mut infos = Vec::new();
    let mut shards = Vec::new();
    for t in 0..tiles {
        let ids: Vec<u32> = (0..per_tile).map(|k| (t * per_tile + k) as u32).collect();
        let means: Vec<[f32; 3]> = (0..per_tile)
            .map(|_| [t as f32 * 10.0 + 9.0 * (next() + 0.5), 0.0, 0.0])
            .collect();
        let mut vectors: Vec<f32> = (0..per_tile * dim).map(|_| next()).collect();
        for row in vectors.chunks_mut(dim) {
            let n = row.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-6);
            row.iter_mut().for_each(|x| *x /= n);
        }
        let bytes = encode_shard(&ShardInput {
            scene_id: "synth",
            model: "synthetic",
            tile_id: t as u64,
            dim,
            dtype: Dtype::F16,
            ids: &ids,
            means: &means,
            vectors: &vectors,
            ..Default::default()
        })
        .unwrap();
        infos.push(TileInfo {
            id: t as u64,
            footprint: TileInfo::rect_ring([t as f64 * 10.0, 0.0], [t as f64 * 10.0 + 9.0, 9.0]),
            aabb: Aabb::of_points(means.iter().copied()).unwrap(),
            count: per_tile as u64,
            bytes: bytes.len() as u64,
            checksum: format!("{:08x}", shard_checksum(&bytes)),
            sha256: None,
        });
        shards.push(bytes);
    }
    let manifest = Manifest {
        format: MANIFEST_FORMAT.into(),
        manifest_version: MANIFEST_VERSION,
        shard_format_version: SHARD_FORMAT_VERSION,
        scene_id: "synth".into(),
        generation: 1,
        model: "synthetic".into(),
        dim: dim as u32,
        dtype: Dtype::F16,
        ground: GroundFrame::from_axis_name("z").unwrap(),
        frames: Default::default(),
        mixture: None,
        max_per_shard: per_tile as u64,
        total_gaussians: (tiles * per_tile) as u64,
        tiles: infos,
    };
    for (t, b) in manifest.tiles.iter().zip(&shards) {
        store.commit_shard(&manifest, t, b).unwrap();
    }
    let record = FetchRecord {
        server: "synthetic".into(),
        center: [0.0, 0.0],
        radius: 1e9,
        completed_unix_s: 0,
        tiles: None,
        kept: None,
    };
    store.commit_fetch(&manifest, &record).unwrap();
    println!(
        "built {tiles} shards of {per_tile} × {dim} f16 ({:.1} MB) in {}",
        shards.iter().map(|b| b.len()).sum::<usize>() as f64 / 1e6,
        dir.display()
    );
}

fn load(dir: &Path) {
    report("start");
    let store = EdgeStore::open(dir).unwrap();
    report("store open");
    let engine = slag_edge::engine::Engine::load(&store, "synth", false).unwrap();
    report(&format!(
        "scene loaded ({} Gaussians, {} MiB vectors)",
        engine.store.len(),
        engine.store.memory_bytes() >> 20
    ));
    drop(store);
    report("store closed (engine kept)");
    drop(engine);
    report("engine dropped");
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let num = |i: usize, d: usize| args.get(i).and_then(|v| v.parse().ok()).unwrap_or(d);
    match (args.first().map(String::as_str), args.get(1)) {
        (Some("build"), Some(dir)) => build(Path::new(dir), num(2, 16), num(3, 65536), num(4, 512)),
        (Some("load"), Some(dir)) => load(Path::new(dir)),
        _ => eprintln!("usage: store_rss build DIR [TILES PER_TILE DIM] | store_rss load DIR"),
    }
}
