//! `slag-encoder encode` (and `bench`, which times the same run): arguments → pipeline.

use std::path::PathBuf;

use anyhow::Context;
use clap::{Args, ValueEnum};
use slag_common::embeddings::StoredPrecision;

use crate::aggregate::{ImageStageParams, ReduceParams};
use crate::masks::MaskGenerator;
use crate::pipeline::{self, CropEmbedder, EncodeParams, SceneInput};
use crate::raster::WeightRasterizer;
use crate::report::Report;

use super::EpArg;

/// `--masks`: where the masks come from.
#[derive(Debug, Clone, Copy, ValueEnum, PartialEq, Eq)]
pub enum MaskSource {
    /// SAM automatic mask generation over `--sam-encoder` / `--sam-decoder`.
    Sam,
    /// Felzenszwalb-Huttenlocher graph segmentation (no model, fast, CPU).
    Graph,
}

/// `--rasterizer`: which weight rasterizer runs.
#[derive(Debug, Clone, Copy, ValueEnum, PartialEq, Eq)]
pub enum RasterBackend {
    /// wgpu compute (Vulkan: a GPU, or Mesa lavapipe on CPU-only machines).
    Gpu,
    /// The slow f64 CPU reference (for checking).
    Cpu,
}

/// `--precision`: stored precision of the embeddings.
#[derive(Debug, Clone, Copy, ValueEnum, PartialEq, Eq)]
pub enum PrecisionArg {
    /// 2 bytes per component.
    F16,
    /// 4 bytes per component.
    F32,
}

/// Arguments of `encode` (the CLI contract of the encoder issue).
#[derive(Debug, Clone, Args)]
pub struct EncodeArgs {
    /// Scene folder: point_cloud.ply (or --ply), images/, and sparse/0 (COLMAP) or transforms.json.
    #[arg(long)]
    pub scene: PathBuf,
    /// The trained 3DGS .ply (INRIA layout); default <scene>/point_cloud.ply.
    #[arg(long)]
    pub ply: Option<PathBuf>,
    /// Mask source.
    #[arg(long, value_enum, default_value_t = MaskSource::Sam)]
    pub masks: MaskSource,
    /// SAM image encoder ONNX (pixel_values f32[1,3,1024,1024] -> image_embeddings).
    #[arg(long, required_if_eq("masks", "sam"))]
    pub sam_encoder: Option<PathBuf>,
    /// SAM prompt decoder ONNX (segment_anything SamOnnxModel signature).
    #[arg(long, required_if_eq("masks", "sam"))]
    pub sam_decoder: Option<PathBuf>,
    /// SAM point grid: points per image side (segment_anything's default 32).
    #[arg(long, default_value_t = 32)]
    pub sam_points_per_side: u32,
    /// SAM prompts per decoder call.
    #[arg(long, default_value_t = 64)]
    pub sam_points_per_batch: usize,
    /// SAM filter: minimum predicted IoU (segment_anything's default 0.88).
    #[arg(long, default_value_t = 0.88)]
    pub sam_pred_iou_thresh: f32,
    /// SAM filter: minimum stability score (segment_anything's default 0.95).
    #[arg(long, default_value_t = 0.95)]
    pub sam_stability_score_thresh: f32,
    /// SAM box NMS IoU threshold.
    #[arg(long, default_value_t = 0.7)]
    pub sam_box_nms_thresh: f32,
    /// Graph segmenter: scale parameter k (larger = larger segments).
    #[arg(long)]
    pub graph_k: Option<f32>,
    /// Graph segmenter: minimum segment size, pixels.
    #[arg(long)]
    pub graph_min_size: Option<u32>,
    /// CLIP visual tower ONNX (pixel_values f32[B,3,224,224] -> [B,D]).
    #[arg(long)]
    pub clip_visual: PathBuf,
    /// Crops per CLIP batch.
    #[arg(long, default_value_t = 32)]
    pub clip_batch: usize,
    /// Keep every N-th image (1 = all; the paper uses 1:20 on large scenes).
    #[arg(long, default_value_t = 1)]
    pub every: usize,
    /// Raster resolution relative to the images (weights are computed at this resolution).
    #[arg(long, default_value_t = 0.5)]
    pub raster_scale: f64,
    /// Weight rasterizer.
    #[arg(long, value_enum, default_value_t = RasterBackend::Gpu)]
    pub rasterizer: RasterBackend,
    /// ONNX Runtime execution provider for SAM and CLIP.
    #[arg(long, value_enum, default_value_t = EpArg::Cpu)]
    pub ep: EpArg,
    /// Worker threads (ONNX Runtime intra-op and CPU stages); default: all cores.
    #[arg(long)]
    pub threads: Option<usize>,
    /// Keep only the K largest contributors per pixel (default: all, as in the paper).
    #[arg(long)]
    pub top_k_per_pixel: Option<usize>,
    /// Σa below which a Gaussian is unobserved (gets no embedding).
    #[arg(long, default_value_t = 1e-6)]
    pub min_weight: f64,
    /// Memory for per-image contributions before spilling to disk, MiB.
    #[arg(long, default_value_t = 4096)]
    pub contribution_memory_mb: usize,
    /// Memory for the reduction's f64 accumulator, MiB (larger scenes are reduced in chunks).
    #[arg(long, default_value_t = 2048)]
    pub accumulator_memory_mb: usize,
    /// Stored precision of the embeddings.
    #[arg(long, value_enum, default_value_t = PrecisionArg::F16)]
    pub precision: PrecisionArg,
    /// Also write OUT/mixture.safetensors: a shared codebook of the mask embeddings plus each
    /// Gaussian's S largest a_kj (compressed embeddings; S >= 1).
    #[arg(long, value_name = "S", value_parser = parse_keep)]
    pub mixture_keep: Option<usize>,
    /// Output folder (embeddings.safetensors, report.json).
    #[arg(long)]
    pub out: PathBuf,
    /// No progress bars.
    #[arg(long)]
    pub quiet: bool,
}

/// `--mixture-keep`: a positive slot count.
fn parse_keep(s: &str) -> Result<usize, String> {
    match s.parse::<usize>() {
        Ok(0) => Err("keep at least 1 mask embedding per Gaussian".into()),
        Ok(k) => Ok(k),
        Err(e) => Err(format!("{e}; pass a positive integer")),
    }
}

fn build_masks(a: &EncodeArgs, threads: usize) -> anyhow::Result<Box<dyn MaskGenerator>> {
    Ok(match a.masks {
        MaskSource::Sam => {
            let (enc, dec) = (
                a.sam_encoder
                    .as_ref()
                    .context("--masks sam needs --sam-encoder")?,
                a.sam_decoder
                    .as_ref()
                    .context("--masks sam needs --sam-decoder")?,
            );
            let params = crate::masks::sam::SamParams {
                points_per_side: a.sam_points_per_side,
                points_per_batch: a.sam_points_per_batch,
                pred_iou_thresh: a.sam_pred_iou_thresh,
                stability_score_thresh: a.sam_stability_score_thresh,
                box_nms_thresh: a.sam_box_nms_thresh,
                ..Default::default()
            };
            Box::new(crate::masks::sam::SamAutomaticMaskGenerator::new(
                enc,
                dec,
                a.ep.into(),
                threads,
                params,
            )?)
        }
        MaskSource::Graph => {
            let mut p = crate::masks::graph::GraphParams::default();
            if let Some(k) = a.graph_k {
                p.k = k;
            }
            if let Some(m) = a.graph_min_size {
                p.min_size = m;
            }
            Box::new(crate::masks::graph::GraphSegmenter::new(p))
        }
    })
}

fn report_header(a: &EncodeArgs, scene: &SceneInput, threads: usize) -> Report {
    Report {
        slag_version: env!("CARGO_PKG_VERSION").to_string(),
        inputs: serde_json::json!({
            "scene": scene.dir, "ply": scene.ply, "every": scene.every,
        }),
        models: serde_json::json!({
            "sam_encoder": a.sam_encoder, "sam_decoder": a.sam_decoder,
            "clip_visual": a.clip_visual,
            "execution_provider": format!("{:?}", a.ep).to_lowercase(),
        }),
        parameters: serde_json::json!({
            "raster_scale": a.raster_scale,
            "sam_points_per_side": a.sam_points_per_side,
            "sam_points_per_batch": a.sam_points_per_batch,
            "sam_pred_iou_thresh": a.sam_pred_iou_thresh,
            "sam_stability_score_thresh": a.sam_stability_score_thresh,
            "sam_box_nms_thresh": a.sam_box_nms_thresh,
            "graph_k": a.graph_k, "graph_min_size": a.graph_min_size,
            "clip_batch": a.clip_batch,
            "top_k_per_pixel": a.top_k_per_pixel,
            "min_weight": a.min_weight,
            "mixture_keep": a.mixture_keep,
            "threads": threads,
        }),
        ..Default::default()
    }
}

/// Runs `encode` and returns the report it wrote.
pub fn run(a: &EncodeArgs) -> anyhow::Result<Report> {
    let threads = a.threads.unwrap_or_else(|| {
        std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(1)
    });
    // The global pool may already exist (tests, bench repeats): then keep it.
    let _ = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build_global();
    let scene = SceneInput::new(&a.scene, a.ply.as_deref(), a.every);
    let masks = build_masks(a, threads)?;
    let clip =
        crate::clip::ClipVisual::with_threads(&a.clip_visual, a.ep.into(), a.clip_batch, threads)?;
    let crops: Box<dyn CropEmbedder> = Box::new(clip);
    let params = EncodeParams {
        raster_scale: a.raster_scale,
        image_stage: ImageStageParams {
            top_k_per_pixel: a.top_k_per_pixel,
        },
        reduce: ReduceParams {
            min_total_weight: a.min_weight,
            accumulator_budget_bytes: a.accumulator_memory_mb << 20,
        },
        contribution_budget_bytes: a.contribution_memory_mb << 20,
        precision: match a.precision {
            PrecisionArg::F16 => StoredPrecision::F16,
            PrecisionArg::F32 => StoredPrecision::F32,
        },
        out_dir: a.out.clone(),
        progress: !a.quiet,
        mixture_keep: a.mixture_keep,
    };
    let header = report_header(a, &scene, threads);
    let backend = a.rasterizer;
    let make =
        |g: &slag_common::scene::Gaussians| -> slag_common::Result<Box<dyn WeightRasterizer>> {
            Ok(match backend {
                RasterBackend::Gpu => Box::new(crate::raster::gpu::GpuRasterizer::new(g)?),
                RasterBackend::Cpu => Box::new(crate::raster::cpu::CpuRasterizer::new(g)),
            })
        };
    let report = pipeline::encode(&scene, masks, crops, make, &params, header)?;
    Ok(report)
}

/// A markdown table of per-stage times from a run report (the `bench` output).
pub fn timing_table(r: &Report) -> String {
    let t = &r.timings;
    let n = r.counts.views_used.max(1) as f64;
    let rows = [
        ("load scene", t.load_scene, false),
        ("decode", t.decode, true),
        ("masks", t.masks, true),
        ("CLIP crops", t.clip, true),
        ("raster", t.raster, true),
        ("a_kj (image stage)", t.image_aggregate, true),
        ("reduce (E_k)", t.reduce, false),
        ("write", t.write, false),
        ("total (wall)", t.total, false),
    ];
    let mut s = String::from("| stage | seconds | ms / image |\n|---|---:|---:|\n");
    for (name, secs, per_image) in rows {
        let per = if per_image {
            format!("{:.1}", 1000.0 * secs / n)
        } else {
            "".into()
        };
        s += &format!("| {name} | {secs:.3} | {per} |\n");
    }
    s += &format!(
        "\nviews {} | Gaussians {} | observed {} ({:.1}%) | masks {} | a_kj entries {} | contributors/pixel {:.1} | rasterizer {} | masks {}\n",
        r.counts.views_used,
        r.counts.gaussians,
        r.counts.observed,
        100.0 * r.counts.observed_fraction,
        r.counts.masks,
        r.counts.entries,
        r.counts.contributors_per_pixel,
        r.models["rasterizer"].as_str().unwrap_or("?"),
        r.models["masks"].as_str().unwrap_or("?"),
    );
    s
}
