//! Weight-rasterizer timing on the shared snowmiku scene (120k Gaussians, 990×742 photos).
//!
//! `cargo bench --workspace --bench raster` (release) or, without rebuilding dependencies in
//! release, `cargo test --workspace --bench raster` (dev profile; slower CPU code). Prints, per
//! raster scale: GPU-path and CPU-reference milliseconds per view, mean contributors per pixel and
//! total entries. Environment: `SLAG_BENCH_SCALES` (default `1.0,0.5`), `SLAG_BENCH_VIEWS`
//! (default 3), `SLAG_BENCH_CPU=0` to skip the CPU reference.

#[path = "../src/raster/testdata.rs"]
mod testdata;

use std::time::Instant;

use slag_encoder::raster::{CpuRasterizer, GpuRasterizer, WeightRasterizer, raster_intrinsics};

fn main() {
    let dir = testdata::snowmiku_dir();
    let g = testdata::load_ply_for_test(&dir.join("point_cloud.ply"), false);
    let views = testdata::load_views_for_test(&dir);
    let scales: Vec<f64> = std::env::var("SLAG_BENCH_SCALES")
        .unwrap_or_else(|_| "1.0,0.5".into())
        .split(',')
        .filter_map(|s| s.trim().parse().ok())
        .collect();
    let n_views: usize = std::env::var("SLAG_BENCH_VIEWS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(3);
    let run_cpu = std::env::var("SLAG_BENCH_CPU").map_or(true, |v| v != "0");
    let t = Instant::now();
    let mut gpu = match GpuRasterizer::new(&g) {
        Ok(r) => r,
        Err(e) => {
            eprintln!("GPU rasterizer unavailable: {e}");
            std::process::exit(1);
        }
    };
    println!(
        "{} Gaussians; GPU setup {:.0} ms on {}",
        g.len(),
        ms(t),
        gpu.name()
    );
    let mut cpu = CpuRasterizer::new(&g);
    let picks: Vec<usize> = (0..n_views)
        .map(|i| 1 + i * views.len() / n_views.max(1))
        .collect();
    for &scale in &scales {
        // Warm-up (pipeline caches, allocator).
        let (_, k0, p0) = &views[picks[0]];
        let k = raster_intrinsics(k0, scale).expect("scale");
        gpu.rasterize(&k, p0).expect("gpu");
        let (mut gpu_ms, mut cpu_ms, mut entries, mut contrib) = (0.0, 0.0, 0usize, 0.0);
        for &i in &picks {
            let (_, k, pose) = &views[i % views.len()];
            let k = raster_intrinsics(k, scale).expect("scale");
            let t = Instant::now();
            let w = gpu.rasterize(&k, pose).expect("gpu");
            gpu_ms += ms(t);
            println!("  view {i}: GPU phases {:?}", gpu.last_timings());
            entries += w.len();
            contrib += w.mean_contributors();
            if run_cpu {
                let t = Instant::now();
                let c = cpu.rasterize(&k, pose).expect("cpu");
                cpu_ms += ms(t);
                assert_eq!(c.width, w.width);
            }
        }
        let n = picks.len() as f64;
        println!(
            "scale {scale}: {}x{} px, GPU {:.0} ms/view, CPU reference {} ms/view, {:.1} contributors/pixel, {:.0} entries/view",
            k.width,
            k.height,
            gpu_ms / n,
            if run_cpu {
                format!("{:.0}", cpu_ms / n)
            } else {
                "-".into()
            },
            contrib / n,
            entries as f64 / n
        );
    }
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}
