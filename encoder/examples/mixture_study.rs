//! Size/accuracy of the mixture storage (`slag_common::mixture`) against the exact f32 `E_k`.
//!
//! `keep` `all` keeps every non-zero `a_kj` (the default list ends with it).
//!
//! `cargo build --workspace --example mixture_study && target/debug/examples/mixture_study [--scene DIR] [--masks graph|sam] [--every N]
//!  [--raster-scale S] [--keep 1,2,4,8,16,32,all]` (defaults: `data/snowmiku-mini`, graph masks,
//! every view, raster scale 0.5, color-clip from `shared/fixtures/clip`).
//!
//! Runs the encode stages once (masks → color-clip crops → weight raster → `a_kj`), then the exact
//! reduction and one mixture reduction per `keep`, and prints a markdown table: slots S, codebook
//! rows M, bytes per Gaussian, mean / 1st-percentile cosine between `E_k` and its reconstruction,
//! and for the 12 colour prompts of color-clip the IoU of the Gaussians matched at the paper's 0.28
//! threshold against the exact f32 answer (dense f16 storage as a baseline row).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use slag_common::onnx::ExecutionProvider;
use slag_common::similarity::{PAPER_THRESHOLD, cosine_scores};
use slag_encoder::aggregate::{self, ContributionStore, ImageStageParams, ReduceParams};
use slag_encoder::masks::MaskGenerator;
use slag_encoder::pipeline::{SceneInput, read_image};
use slag_encoder::raster::WeightRasterizer;

/// Sets matched at the threshold, and their IoU (`None` when both are empty).
fn iou(a: &[f32], b: &[f32]) -> (usize, usize, Option<f64>) {
    let (mut inter, mut union, mut na, mut nb) = (0, 0, 0, 0);
    for (&x, &y) in a.iter().zip(b) {
        let (p, q) = (x >= PAPER_THRESHOLD, y >= PAPER_THRESHOLD);
        na += p as usize;
        nb += q as usize;
        inter += (p && q) as usize;
        union += (p || q) as usize;
    }
    (na, nb, (union > 0).then(|| inter as f64 / union as f64))
}

fn main() -> anyhow::Result<()> {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    let fixtures = slag_common::paths::source_tree_shared_dir().join("fixtures");
    let (mut scene_dir, mut masks_kind, mut every, mut scale) = (
        root.join("data/snowmiku-mini"),
        "graph".to_string(),
        1usize,
        0.5f64,
    );
    let mut keeps = vec![1usize, 2, 4, 8, 16, 32, usize::MAX];
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        let v = args.next().with_context(|| format!("{a} needs a value"))?;
        match a.as_str() {
            "--scene" => scene_dir = v.into(),
            "--masks" => masks_kind = v,
            "--every" => every = v.parse()?,
            "--raster-scale" => scale = v.parse()?,
            "--keep" => {
                keeps = v
                    .split(',')
                    .map(|k| {
                        if k == "all" {
                            Ok(usize::MAX)
                        } else {
                            k.parse()
                        }
                    })
                    .collect::<Result<_, _>>()?
            }
            _ => anyhow::bail!("unknown argument {a}"),
        }
    }
    let t_all = Instant::now();
    let scene = SceneInput::new(&scene_dir, None, every);
    let (gaussians, views, _) = scene.load()?;
    let mut masks: Box<dyn MaskGenerator> = match masks_kind.as_str() {
        "graph" => Box::new(slag_encoder::masks::graph::GraphSegmenter::new(
            Default::default(),
        )),
        "sam" => Box::new(slag_encoder::masks::sam::SamAutomaticMaskGenerator::new(
            &fixtures.join("sam-amg/color-sam-encoder.onnx"),
            &fixtures.join("sam-amg/color-sam-decoder.onnx"),
            ExecutionProvider::Cpu,
            0,
            slag_encoder::masks::sam::SamParams {
                points_per_side: 16,
                pred_iou_thresh: 0.8,
                stability_score_thresh: 0.5,
                ..Default::default()
            },
        )?),
        other => anyhow::bail!("--masks {other}: graph or sam"),
    };
    let mut clip = slag_encoder::clip::ClipVisual::new(
        &fixtures.join("clip/color-clip-visual.onnx"),
        ExecutionProvider::Cpu,
        32,
    )?;
    let dim = clip.dim();
    let mut raster = slag_encoder::raster::gpu::GpuRasterizer::new(&gaussians)?;
    let mut store = ContributionStore::new(usize::MAX, std::env::temp_dir().join("mixture-study"));
    let mut n_masks = 0;
    for view in &views {
        let img = read_image(view)?;
        let m = masks.generate(&img)?;
        let e = clip.embed_masks(&img, &m)?.concat();
        let intr = slag_encoder::raster::raster_intrinsics(&view.intrinsics, scale)?;
        let w = raster.rasterize(&intr, &view.world_to_camera)?;
        n_masks += m.len();
        store.push(aggregate::image_contribution(
            &w,
            &m,
            e,
            dim,
            ImageStageParams::default(),
        )?)?;
    }
    let encode_s = t_all.elapsed().as_secs_f64();
    let p = ReduceParams::default();
    let t0 = Instant::now();
    let exact = aggregate::reduce(&store, gaussians.len(), dim, p)?;
    let reduce_s = t0.elapsed().as_secs_f64();
    let n = exact.ids.len();
    // Non-zero a_kj per observed Gaussian (the slots a keep-all mixture uses).
    let all = aggregate::reduce_mixture(
        &store,
        gaussians.len(),
        dim,
        p,
        usize::MAX,
        "",
        &gaussians.means,
    )?;
    let counts: Vec<usize> = all
        .atoms
        .chunks_exact(all.keep)
        .map(|r| {
            r.iter()
                .filter(|&&a| a != slag_common::mixture::UNUSED)
                .count()
        })
        .collect();
    drop(all);
    let mut sorted_counts = counts.clone();
    sorted_counts.sort_unstable();
    println!(
        "non-zero a_kj per observed Gaussian: mean {:.2}, median {}, p90 {}, p99 {}, max {}",
        counts.iter().sum::<usize>() as f64 / n.max(1) as f64,
        sorted_counts.get(n / 2).copied().unwrap_or(0),
        sorted_counts.get(n * 9 / 10).copied().unwrap_or(0),
        sorted_counts.get(n * 99 / 100).copied().unwrap_or(0),
        sorted_counts.last().copied().unwrap_or(0),
    );

    let classes = [
        "red", "orange", "yellow", "green", "teal", "blue", "purple", "pink", "brown", "white",
        "gray", "black",
    ];
    let mut text = slag_common::text::TextEncoder::new(
        &fixtures.join("clip/color-clip-textual.onnx"),
        &fixtures.join("clip/clip-tokenizer.json"),
        ExecutionProvider::Cpu,
    )?;
    let prompts = text.encode(&classes)?;
    let truth: Vec<Vec<f32>> = prompts
        .iter()
        .map(|q| cosine_scores(&exact.vectors, dim, q))
        .collect::<Result<_, _>>()?;
    println!(
        "scene {} | views {} | masks {n_masks} | Gaussians {} | observed {n} | D {dim} | \
         encode stages {encode_s:.1} s | exact reduce {reduce_s:.2} s\n",
        scene_dir.display(),
        views.len(),
        gaussians.len(),
    );
    let mut header = String::from(
        "| storage | S | M | bytes/Gaussian | all atoms kept | reduce s | mean cos | p1 cos | min cos | mean IoU@0.28 |",
    );
    for c in classes {
        header += &format!(" {c} |");
    }
    println!("{header}");
    println!("|{}", "---|".repeat(10 + classes.len()));
    let row = |name: String,
               s: usize,
               m: String,
               bpg: f64,
               secs: String,
               cos: &[f64],
               scores: &[Vec<f32>]| {
        let mut sorted = cos.to_vec();
        sorted.sort_by(f64::total_cmp);
        let mean = sorted.iter().sum::<f64>() / sorted.len().max(1) as f64;
        let p1 = sorted.get(sorted.len() / 100).copied().unwrap_or(f64::NAN);
        let min = sorted.first().copied().unwrap_or(f64::NAN);
        let mut cells = String::new();
        let mut ious = Vec::new();
        for (t, s) in truth.iter().zip(scores) {
            let (na, nb, i) = iou(t, s);
            match i {
                Some(v) => {
                    ious.push(v);
                    cells += &format!(" {v:.4} ({na}/{nb}) |");
                }
                None => cells += " – (0/0) |",
            }
        }
        let miou = ious.iter().sum::<f64>() / ious.len().max(1) as f64;
        println!(
            "| {name} | {} | {m} | {bpg:.1} | {:.2}% | {secs} | {mean:.6} | {p1:.6} | {min:.6} | {miou:.4} |{cells}",
            if s == usize::MAX {
                "–".to_string()
            } else {
                s.to_string()
            },
            100.0 * counts.iter().filter(|&&c| c <= s).count() as f64 / n.max(1) as f64,
        );
    };
    // Baseline: the dense f16 file.
    let f16v: Vec<f32> = exact
        .vectors
        .iter()
        .map(|&v| half::f16::from_f32(v).to_f32())
        .collect();
    let cos_of = |a: &[f32], b: &[f32]| -> f64 {
        let (mut ab, mut aa, mut bb) = (0f64, 0f64, 0f64);
        for (&x, &y) in a.iter().zip(b) {
            ab += x as f64 * y as f64;
            aa += x as f64 * x as f64;
            bb += y as f64 * y as f64;
        }
        ab / (aa.sqrt() * bb.sqrt())
    };
    // Per Gaussian: the cosine of its exact row with the same row of `other` (n rows of `dim`).
    let row_cosines = |other: &[f32]| -> Vec<f64> {
        let rows = exact.vectors.chunks_exact(dim).zip(other.chunks_exact(dim));
        rows.take(n).map(|(a, b)| cos_of(a, b)).collect()
    };
    let cos = row_cosines(&f16v);
    let scores: Vec<Vec<f32>> = prompts
        .iter()
        .map(|q| cosine_scores(&f16v, dim, q))
        .collect::<Result<_, _>>()?;
    row(
        "dense f16".into(),
        usize::MAX,
        "–".into(),
        (dim * 2 + 16) as f64,
        "–".into(),
        &cos,
        &scores,
    );
    for &keep in &keeps {
        let t0 = Instant::now();
        let mix = aggregate::reduce_mixture(
            &store,
            gaussians.len(),
            dim,
            p,
            keep,
            "color-clip-visual",
            &gaussians.means,
        )?;
        let secs = t0.elapsed().as_secs_f64();
        anyhow::ensure!(mix.gaussian_ids == exact.ids, "observed sets differ");
        let dense = mix.to_dense();
        let cos = row_cosines(&dense);
        let refs: Vec<&[f32]> = prompts.iter().map(Vec::as_slice).collect();
        let scores = mix.scores_many(&refs)?;
        row(
            if keep == usize::MAX {
                "mixture keep all".into()
            } else {
                format!("mixture keep {keep}")
            },
            mix.keep,
            mix.codebook_len().to_string(),
            mix.bytes_per_gaussian(),
            format!("{secs:.2}"),
            &cos,
            &scores,
        );
    }
    Ok(())
}
