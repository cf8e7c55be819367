//! Host tile binning + depth sort, the reference of the GPU rasterizer's step 2 (`raster::gpu`): the chunked
//! counting sort (`bin_and_sort`) against one global sort of 128-bit keys
//! (`bin_and_sort_reference`), on synthetic tile rects shaped like the 2M-Gaussian, 250-view scene
//! of docs/results/gpu-models.md (raster 495 × 371 at scale 0.5: 31 × 24 tiles, 1–4 × 1–3 tiles per
//! Gaussian, 10 % culled).
//!
//! `cargo bench -p slag-encoder --bench binsort` (release). Environment: `SLAG_BENCH_GAUSSIANS`
//! (default 2000000), `SLAG_BENCH_REPEATS` (default 5; the best of each is reported). Prints both
//! times, their ratio (measured in this one run) and checks that both give the same order.

use std::time::Instant;

use glam::{DMat3, DVec3};
use slag_common::camera::WorldToCamera;
use slag_common::rng::SplitMix64;
use slag_encoder::raster::gpu::project::{bin_and_sort, bin_and_sort_reference};

fn main() {
    let n: usize = std::env::var("SLAG_BENCH_GAUSSIANS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(2_000_000);
    let repeats: usize = std::env::var("SLAG_BENCH_REPEATS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(5);
    let (tiles_x, tiles_y) = (31u32, 24u32);
    let mut rng = SplitMix64::new(7);
    let mut isect = Vec::with_capacity(n);
    let mut means = Vec::with_capacity(n);
    for _ in 0..n {
        let r = rng.next_u64();
        let (x0, y0) = (
            (r % tiles_x as u64) as u32,
            ((r >> 8) % tiles_y as u64) as u32,
        );
        let (w, h) = (1 + ((r >> 16) % 4) as u32, 1 + ((r >> 20) % 3) as u32);
        let culled = (r >> 24).is_multiple_of(10);
        let (x1, y1) = if culled {
            (x0, y0)
        } else {
            ((x0 + w).min(tiles_x), (y0 + h).min(tiles_y))
        };
        isect.push([x0 | y0 << 16, x1 | y1 << 16]);
        let z = 1.0 + ((r >> 32) % 100_000) as f32 * 1e-3;
        means.push([0.0, 0.0, z]);
    }
    let w2c = WorldToCamera {
        rotation: DMat3::IDENTITY,
        translation: DVec3::ZERO,
    };
    let n_tiles = tiles_x * tiles_y;
    let time = |f: &dyn Fn() -> (Vec<[u32; 2]>, Vec<u32>)| {
        let mut best = f64::INFINITY;
        let mut out = None;
        for _ in 0..repeats.max(1) {
            let t = Instant::now();
            let o = f();
            best = best.min(t.elapsed().as_secs_f64() * 1e3);
            out = Some(o);
        }
        (best, out.unwrap_or_default())
    };
    // Alternate the two a first time (warm caches and allocator), then time each.
    let (ref_ms, ref_out) = time(&|| {
        bin_and_sort_reference(&isect, &means, &w2c, tiles_x, n_tiles).expect("reference")
    });
    let (new_ms, new_out) =
        time(&|| bin_and_sort(&isect, &means, &w2c, tiles_x, n_tiles).expect("counting sort"));
    assert!(new_out == ref_out, "the two binnings disagree");
    println!(
        "{n} Gaussians, {} intersections, {} threads: global sort {ref_ms:.1} ms, counting sort {new_ms:.1} ms ({:.2}x)",
        ref_out.1.len(),
        rayon::current_num_threads(),
        ref_ms / new_ms
    );
}
