//! Times the graph segmenter on real photos and prints segment counts.
//!
//! `cargo run --workspace --example graph_snowmiku -- [IMAGE...] [--k K] [--min-size N] [--max-side S]`
//! (defaults: the first three snowmiku photos from `shared/`, [`GraphParams::default`]).

use std::time::Instant;

use slag_encoder::masks::MaskGenerator;
use slag_encoder::masks::graph::{GraphParams, GraphSegmenter, segment_labels};

fn main() -> anyhow::Result<()> {
    let mut params = GraphParams::default();
    let mut images = Vec::new();
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        let mut value = || {
            args.next()
                .ok_or_else(|| anyhow::anyhow!("{a} needs a value"))
        };
        match a.as_str() {
            "--k" => params.k = value()?.parse()?,
            "--min-size" => params.min_size = value()?.parse()?,
            "--max-side" => params.max_side = Some(value()?.parse()?),
            "--sigma" => params.sigma = value()?.parse()?,
            _ => images.push(std::path::PathBuf::from(a)),
        }
    }
    if images.is_empty() {
        let dir = slag_common::paths::source_tree_shared_dir().join("scenes/snowmiku/images");
        let mut all: Vec<_> = std::fs::read_dir(&dir)?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .collect();
        all.sort();
        images = all.into_iter().take(3).collect();
    }
    println!("{params:?}");
    let reps = 5;
    // CPU time (user + system) of this process so far, seconds (Linux only, else 0).
    let cpu_seconds = || slag_common::util::cpu_seconds().unwrap_or(0.0);
    for path in images {
        let img = image::open(&path)?.to_rgb8();
        let (t, c) = (Instant::now(), cpu_seconds());
        let mut count = 0;
        for _ in 0..reps {
            count = segment_labels(&img, &params)?.1;
        }
        let (t_seg, c_seg) = (
            t.elapsed().as_secs_f64() / reps as f64,
            (cpu_seconds() - c) / reps as f64,
        );
        let (t, c) = (Instant::now(), cpu_seconds());
        let mut masks = Vec::new();
        for _ in 0..reps {
            masks = GraphSegmenter::new(params).generate(&img)?;
        }
        let (t_all, c_all) = (
            t.elapsed().as_secs_f64() / reps as f64,
            (cpu_seconds() - c) / reps as f64,
        );
        println!(
            "{}: {}x{} segments {count} ({} masks, largest {} px, smallest {} px) \
             segment_labels {:.0} ms wall / {:.0} ms cpu; generate (segments + masks) {:.0} ms wall / {:.0} ms cpu",
            path.file_name().unwrap_or_default().to_string_lossy(),
            img.width(),
            img.height(),
            masks.len(),
            masks.first().map_or(0, |m| m.area),
            masks.last().map_or(0, |m| m.area),
            t_seg * 1e3,
            c_seg * 1e3,
            t_all * 1e3,
            c_all * 1e3,
        );
    }
    Ok(())
}
