//! Loads a scene folder (views + `point_cloud.ply`) and prints what it found and how long it took.
//!
//! ```text
//! cargo run --example load_scene -- ../shared/scenes/snowmiku [--colours]
//! ```

use std::error::Error;
use std::path::PathBuf;
use std::time::Instant;

use slag_common::camera::load_views;
use slag_common::scene::{PlyLoadOptions, load_ply};

fn main() -> Result<(), Box<dyn Error>> {
    let mut args = std::env::args().skip(1);
    let dir = PathBuf::from(
        args.next()
            .ok_or("usage: load_scene <scene dir> [--colours]")?,
    );
    let colours = args.any(|a| a == "--colours");
    let t = Instant::now();
    let views = load_views(&dir)?;
    let tv = t.elapsed();
    let t = Instant::now();
    let g = load_ply(&dir.join("point_cloud.ply"), PlyLoadOptions { colours })?;
    let tg = t.elapsed();
    let k = views.first().ok_or("no views")?.intrinsics;
    println!(
        "{} views ({}x{}, fx {:.2}) in {:.1} ms; {} Gaussians (SH degree {}) in {:.1} ms",
        views.len(),
        k.width,
        k.height,
        k.fx,
        tv.as_secs_f64() * 1e3,
        g.len(),
        g.sh.as_ref()
            .map_or("not loaded".to_string(), |s| s.degree.to_string()),
        tg.as_secs_f64() * 1e3
    );
    Ok(())
}
