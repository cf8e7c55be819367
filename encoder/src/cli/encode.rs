//! `slag-encoder encode` (and `bench`, which times the same run): arguments → pipeline.

use std::path::PathBuf;

use anyhow::Context;
use clap::{Args, ValueEnum};
use slag_common::embeddings::StoredPrecision;
use slag_common::onnx::Placement;

use crate::aggregate::{ImageStageParams, ReduceParams};
use crate::masks::MaskGenerator;
use crate::pipeline::{self, EncodeParams, SceneInput};
use crate::raster::WeightRasterizer;
use crate::report::{Inputs, ModelPlacement, Models, Parameters, Report};

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
    /// Crops per CLIP batch (default: 64 on a GPU provider, where the batched service ran
    /// ViT-B/16 fp16 1.45x faster than at 32 on an H100 (docs/device/gpu-models); 32 on the CPU).
    #[arg(long)]
    pub clip_batch: Option<usize>,
    /// Keep every N-th image (1 = all; the paper uses 1:20 on large scenes).
    #[arg(long, default_value_t = 1)]
    pub every: usize,
    /// Raster resolution relative to the images (weights are computed at this resolution).
    #[arg(long, default_value_t = 0.5)]
    pub raster_scale: f64,
    /// Weight rasterizer.
    #[arg(long, value_enum, default_value_t = RasterBackend::Gpu)]
    pub rasterizer: RasterBackend,
    /// ONNX Runtime execution provider for SAM and CLIP: `auto` = CUDA where the loaded ONNX
    /// Runtime has it and a GPU answers, else the CPU (one line says why).
    #[arg(long, value_enum, default_value_t = EpArg::Auto)]
    pub ep: EpArg,
    /// Cap of each model session's CUDA memory arena, GiB (default: no cap beyond the card).
    #[arg(long, value_name = "GIB")]
    pub gpu_mem_limit_gb: Option<f64>,
    /// Worker threads (ONNX Runtime intra-op and CPU stages); default: all cores.
    #[arg(long)]
    pub threads: Option<usize>,
    /// GPUs to rasterize on: a count or `all` (every discrete GPU; one wgpu device and one back
    /// worker each, images balanced dynamically). Default 1. Ignored with `--rasterizer cpu`.
    #[arg(long, default_value = "1")]
    pub gpus: GpuCount,
    /// Front workers (decode → masks → CLIP crops). With the models on the CPU each has its own
    /// ONNX Runtime sessions sharing `--threads` (default: 1 per GPU plus 1); with the models on
    /// GPUs they share each GPU's one SAM session pair and one CLIP service, spread round-robin
    /// over the GPUs (default: 4 per GPU). At most the cores.
    #[arg(long)]
    pub front_workers: Option<usize>,
    /// Keep only the K largest contributors per pixel (default: all, as in the paper).
    #[arg(long)]
    pub top_k_per_pixel: Option<usize>,
    /// Specificity weighting of each mask's a_kj: none (the default, as in the paper), area
    /// (image pixels / mask area: small masks count more), sam-score (SAM predicted IoU ×
    /// stability). Measured held-out in docs/tradeoffs.md: area adds +0.004 over --overlap
    /// finest with SAM masks but costs 0.032 with graph masks, so it is not the default.
    #[arg(long, value_enum, default_value_t = crate::aggregate::MaskWeighting::None)]
    pub mask_weighting: crate::aggregate::MaskWeighting,
    /// Which masks a pixel covered by several gives its blend weights to: finest (the default:
    /// only the smallest covering mask, so each Gaussian mixes only its most specific segments)
    /// or all (the paper's a_kj). `--overlap all --mask-weighting none` is the paper's mean.
    #[arg(long, value_enum, default_value_t = crate::levels::MaskOverlap::Finest)]
    pub overlap: crate::levels::MaskOverlap,
    /// Also write OUT/embeddings-level{0,1,2}.safetensors: one embedding per SAM granularity
    /// level (subpart, part, whole; SAM's three multimask outputs), each reduced over that
    /// level's masks only (LangSplat's levels; needs --masks sam).
    #[arg(long)]
    pub levels: bool,
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

/// `--gpus`: a positive count or `all`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GpuCount {
    /// Exactly this many GPUs (error if fewer are visible).
    Count(usize),
    /// Every discrete GPU visible.
    All,
}

impl std::str::FromStr for GpuCount {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        if s.eq_ignore_ascii_case("all") {
            return Ok(GpuCount::All);
        }
        match s.parse::<usize>() {
            Ok(n) if n >= 1 => Ok(GpuCount::Count(n)),
            _ => Err(format!("--gpus {s:?}: give a count >= 1 or `all`")),
        }
    }
}

/// `--mixture-keep`: a positive slot count.
fn parse_keep(s: &str) -> Result<usize, String> {
    match s.parse::<usize>() {
        Ok(0) => Err("keep at least 1 mask embedding per Gaussian".into()),
        Ok(k) => Ok(k),
        Err(e) => Err(format!("{e}; pass a positive integer")),
    }
}

/// Where `a`'s models run on GPU `device` with `threads` intra-op threads (`--ep`,
/// `--gpu-mem-limit-gb`).
pub(crate) fn placement(a: &EncodeArgs, device: u32, threads: usize) -> Placement {
    Placement {
        ep: a.ep,
        device,
        intra_threads: threads,
        gpu_mem_limit: a
            .gpu_mem_limit_gb
            .filter(|g| *g > 0.0)
            .map(|g| (g * f64::from(1u32 << 30)) as usize),
    }
}

/// SAM parameters from `a`.
fn sam_params(a: &EncodeArgs) -> crate::masks::sam::SamParams {
    crate::masks::sam::SamParams {
        points_per_side: a.sam_points_per_side,
        points_per_batch: a.sam_points_per_batch,
        pred_iou_thresh: a.sam_pred_iou_thresh,
        stability_score_thresh: a.sam_stability_score_thresh,
        box_nms_thresh: a.sam_box_nms_thresh,
        ..Default::default()
    }
}

/// `--sam-encoder` and `--sam-decoder`, required with `--masks sam`.
fn sam_paths(a: &EncodeArgs) -> anyhow::Result<(&std::path::Path, &std::path::Path)> {
    Ok((
        a.sam_encoder
            .as_deref()
            .context("--masks sam needs --sam-encoder")?,
        a.sam_decoder
            .as_deref()
            .context("--masks sam needs --sam-decoder")?,
    ))
}

/// The mask generator `a` asks for (`--masks`), with `threads` ONNX Runtime intra-op threads.
pub(crate) fn build_masks(
    a: &EncodeArgs,
    threads: usize,
) -> anyhow::Result<Box<dyn MaskGenerator>> {
    Ok(match a.masks {
        MaskSource::Sam => {
            let (enc, dec) = sam_paths(a)?;
            let params = sam_params(a);
            Box::new(
                crate::masks::sam::SamAutomaticMaskGenerator::with_placement(
                    enc,
                    dec,
                    &placement(a, 0, threads),
                    params,
                )?,
            )
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

/// The report's inputs, models and parameters sections for `a`.
pub(crate) fn report_header(a: &EncodeArgs, scene: &SceneInput, threads: usize) -> Report {
    Report {
        slag_version: env!("CARGO_PKG_VERSION").to_string(),
        inputs: Inputs {
            every: scene.every,
            ply: scene.ply.clone(),
            scene: scene.dir.clone(),
        },
        models: Models {
            clip_visual: a.clip_visual.clone(),
            execution_provider_requested: a.ep,
            sam_decoder: a.sam_decoder.clone(),
            sam_encoder: a.sam_encoder.clone(),
            ..Default::default()
        },
        parameters: Parameters {
            clip_batch: a.clip_batch,
            cluster_addresses: None,
            cluster_processes: None,
            front_workers: a.front_workers,
            gpus: format!("{:?}", a.gpus),
            graph_k: a.graph_k.map(f64::from),
            graph_min_size: a.graph_min_size,
            levels: a.levels,
            mask_weighting: a.mask_weighting,
            min_weight: a.min_weight,
            mixture_keep: a.mixture_keep,
            overlap: a.overlap,
            raster_scale: a.raster_scale,
            sam_box_nms_thresh: f64::from(a.sam_box_nms_thresh),
            sam_points_per_batch: a.sam_points_per_batch,
            sam_points_per_side: a.sam_points_per_side,
            sam_pred_iou_thresh: f64::from(a.sam_pred_iou_thresh),
            sam_stability_score_thresh: f64::from(a.sam_stability_score_thresh),
            threads,
            top_k_per_pixel: a.top_k_per_pixel,
        },
        ..Default::default()
    }
}

/// Worker threads for `a` (`--threads`, default all cores); sets rayon's global pool to that
/// size unless it already exists (tests, bench repeats).
pub(crate) fn setup_threads(a: &EncodeArgs) -> usize {
    let threads = a.threads.unwrap_or_else(|| {
        std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(1)
    });
    let _ = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build_global();
    threads
}

/// The pipeline parameters `a` asks for.
pub(crate) fn encode_params(a: &EncodeArgs) -> EncodeParams {
    EncodeParams {
        raster_scale: a.raster_scale,
        image_stage: ImageStageParams {
            top_k_per_pixel: a.top_k_per_pixel,
            mask_weighting: a.mask_weighting,
            overlap: a.overlap,
        },
        reduce: ReduceParams {
            min_total_weight: a.min_weight,
            accumulator_budget_bytes: a.accumulator_memory_mb << 20,
            ..Default::default()
        },
        contribution_budget_bytes: a.contribution_memory_mb << 20,
        precision: match a.precision {
            PrecisionArg::F16 => StoredPrecision::F16,
            PrecisionArg::F32 => StoredPrecision::F32,
        },
        out_dir: a.out.clone(),
        progress: !a.quiet,
        mixture_keep: a.mixture_keep,
        levels: a.levels,
    }
}

/// The weight rasterizer `backend` names, over the Gaussians `g`.
pub(crate) fn make_rasterizer(
    backend: RasterBackend,
    g: &slag_common::scene::Gaussians,
) -> slag_common::Result<Box<dyn WeightRasterizer>> {
    Ok(match backend {
        RasterBackend::Gpu => Box::new(crate::raster::gpu::GpuRasterizer::new(g)?),
        RasterBackend::Cpu => Box::new(crate::raster::cpu::CpuRasterizer::new(g)),
    })
}

/// The front workers of a run and what keeps their shared models alive.
pub(crate) struct Fronts {
    /// One entry per front worker.
    pub stages: Vec<pipeline::FrontStages>,
    /// The CLIP services of the GPUs (empty on the CPU); dropped after the encode.
    pub services: Vec<crate::clip::ClipService>,
    /// Per GPU (or one entry for the CPU): where each model actually runs.
    pub providers: Vec<ModelPlacement>,
    /// The provider that actually runs CLIP (and SAM): `cpu`, `cuda`, `tensorrt`.
    pub provider: slag_common::onnx::ExecutionProvider,
}

/// Builds the front workers of `a` over `gpus` GPUs with `threads` cores.
///
/// CLIP is loaded on GPU 0 first with `--ep`: if it runs on the CPU (`--ep cpu`, or `auto`
/// without a usable GPU provider) every front worker gets its own sessions with a share of the
/// cores (as ONNX Runtime's CPU provider scales best); otherwise each GPU gets one SAM session
/// pair and one [`crate::clip::ClipService`], and the workers are bound round-robin to the GPUs.
/// `--clip-batch` default on a GPU provider (measured: docs/device/gpu-models, "CLIP batch").
pub const CLIP_BATCH_GPU: usize = 64;
/// `--clip-batch` default on the CPU provider.
pub const CLIP_BATCH_CPU: usize = 32;

pub(crate) fn build_fronts(
    a: &EncodeArgs,
    gpus: usize,
    front_workers: Option<usize>,
    threads: usize,
) -> anyhow::Result<Fronts> {
    use slag_common::onnx::ExecutionProvider;
    let gpu_threads = (threads / gpus.max(1)).max(1);
    let gpu_batch = a.clip_batch.unwrap_or(CLIP_BATCH_GPU);
    let clip0 = crate::clip::ClipVisual::with_placement(
        &a.clip_visual,
        &placement(a, 0, gpu_threads),
        gpu_batch,
    )?;
    if clip0.provider() == ExecutionProvider::Cpu {
        drop(clip0);
        let n = front_workers.unwrap_or(gpus + 1).clamp(1, threads.max(1));
        let per_front = (threads / n).max(1);
        let mut cpu = a.clone();
        cpu.ep = EpArg::Cpu;
        let mut stages = Vec::with_capacity(n);
        for _ in 0..n {
            let masks = build_masks(&cpu, per_front)?;
            let clip = crate::clip::ClipVisual::with_threads(
                &a.clip_visual,
                ExecutionProvider::Cpu,
                a.clip_batch.unwrap_or(CLIP_BATCH_CPU),
                per_front,
            )?;
            stages.push(pipeline::FrontStages::new(masks, Box::new(clip)));
        }
        let sam = (a.masks == MaskSource::Sam).then_some(ExecutionProvider::Cpu);
        return Ok(Fronts {
            stages,
            services: Vec::new(),
            providers: vec![ModelPlacement {
                clip_batch: a.clip_batch.unwrap_or(CLIP_BATCH_CPU),
                clip_visual: ExecutionProvider::Cpu,
                device: "cpu".into(),
                gpu: None,
                sam_decoder: sam,
                sam_encoder: sam,
            }],
            provider: ExecutionProvider::Cpu,
        });
    }
    let provider = clip0.provider();
    let mut services = vec![clip0.into_service()];
    let mut sams = Vec::new();
    let mut providers = Vec::new();
    for g in 0..gpus {
        if g > 0 {
            let clip = crate::clip::ClipVisual::with_placement(
                &a.clip_visual,
                &placement(a, g as u32, gpu_threads),
                gpu_batch,
            )?;
            services.push(clip.into_service());
        }
        let sam = match a.masks {
            MaskSource::Sam => {
                let (enc, dec) = sam_paths(a)?;
                Some(
                    crate::masks::sam::SamAutomaticMaskGenerator::with_placement(
                        enc,
                        dec,
                        &placement(a, g as u32, gpu_threads),
                        sam_params(a),
                    )?,
                )
            }
            MaskSource::Graph => None,
        };
        let (enc_p, dec_p) = sam.as_ref().map_or((None, None), |s| {
            let (e, d) = s.models().providers();
            (Some(e), Some(d))
        });
        providers.push(ModelPlacement {
            clip_batch: gpu_batch,
            clip_visual: services[g].provider(),
            device: services[g].device_label().to_string(),
            gpu: Some(g),
            sam_decoder: dec_p,
            sam_encoder: enc_p,
        });
        sams.push(sam);
    }
    let n = front_workers.unwrap_or(4 * gpus).clamp(1, threads.max(1));
    let mut stages = Vec::with_capacity(n);
    for w in 0..n {
        let g = w % gpus;
        let masks: Box<dyn MaskGenerator> = match &sams[g] {
            Some(sam) => Box::new(sam.share()),
            None => build_masks(a, 1)?,
        };
        stages.push(pipeline::FrontStages {
            masks,
            crops: Box::new(services[g].handle()),
            gpu: Some(g),
        });
    }
    Ok(Fronts {
        stages,
        services,
        providers,
        provider,
    })
}

/// Runs `encode` and returns the report it wrote: front workers (masks + CLIP; see
/// [`build_fronts`]) and one rasterizer per GPU (`--gpus`).
pub fn run(a: &EncodeArgs) -> anyhow::Result<Report> {
    if a.levels && a.masks != MaskSource::Sam {
        anyhow::bail!(
            "--levels needs masks with granularity levels (SAM's three multimask outputs): use \
             --masks sam, or drop --levels"
        );
    }
    let threads = setup_threads(a);
    let scene = SceneInput::new(&a.scene, a.ply.as_deref(), a.every);
    let gpus = match (a.rasterizer, a.gpus) {
        (RasterBackend::Cpu, _) => 1,
        (_, GpuCount::Count(n)) => n,
        (_, GpuCount::All) => crate::raster::gpu::adapter_names()
            .map(|v| v.len())
            .unwrap_or(1),
    };
    let fronts = build_fronts(a, gpus, a.front_workers, threads)?;
    let params = encode_params(a);
    let mut header = report_header(a, &scene, threads);
    header.models.execution_provider = Some(fronts.provider);
    header.models.execution_providers = Some(fronts.providers.clone());
    let backend = a.rasterizer;
    let want = match a.gpus {
        GpuCount::Count(n) => Some(n),
        GpuCount::All => None,
    };
    let make =
        |g: &slag_common::scene::Gaussians| -> slag_common::Result<Vec<Box<dyn WeightRasterizer>>> {
            Ok(match backend {
                RasterBackend::Gpu => crate::raster::gpu::GpuRasterizer::new_many(g, want)?
                    .into_iter()
                    .map(|r| Box::new(r) as Box<dyn WeightRasterizer>)
                    .collect(),
                RasterBackend::Cpu => vec![make_rasterizer(backend, g)?],
            })
        };
    let Fronts {
        stages, services, ..
    } = fronts;
    let report = pipeline::encode_pool(&scene, stages, make, &params, header)?;
    for s in &services {
        let st = s.stats();
        tracing::info!(
            device = s.device_label(),
            runs = st.runs,
            crops = st.crops,
            run_s = st.run_s,
            "CLIP service"
        );
    }
    Ok(report)
}
