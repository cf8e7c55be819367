//! The stage instances and parameters of a run, built from an [`EncodeConfig`]: mask
//! generators, the front workers with their shared GPU models, rasterizers, the pipeline's
//! [`EncodeParams`] and the report's header.

use slag_common::onnx::ExecutionProvider;
use slag_common::scene::Gaussians;
use slag_common::{Error, Result};

use super::{EncodeParams, FrontStages, SceneInput};
use crate::aggregate::{ImageStageParams, ReduceParams};
use crate::config::{
    CLIP_BATCH_CPU, CLIP_BATCH_GPU, ConfigError, EncodeConfig, Field, GpuCount, MaskSource,
    RasterBackend,
};
use crate::masks::MaskGenerator;
use crate::raster::WeightRasterizer;
use crate::report::{Inputs, ModelPlacement, Models, Parameters, Report};

/// The scene input of `c`.
pub(crate) fn scene_input(c: &EncodeConfig) -> SceneInput {
    let mut s = SceneInput::new(&c.scene.dir, c.scene.ply.as_deref(), c.scene.every);
    s.hold_out_every = c.scene.hold_out_every;
    s.selection = c.scene.views;
    s
}

/// SAM's two model files, required with SAM masks.
fn sam_paths(c: &EncodeConfig) -> Result<(&std::path::Path, &std::path::Path)> {
    let missing = |field| Error::from(ConfigError::Missing { field });
    Ok((
        c.masks
            .sam
            .encoder
            .as_deref()
            .ok_or_else(|| missing(Field::SamEncoder))?,
        c.masks
            .sam
            .decoder
            .as_deref()
            .ok_or_else(|| missing(Field::SamDecoder))?,
    ))
}

/// The SAM timing model of `c` ([`crate::config::SamConfig::timing_encoder`]) placed at
/// `placement`, if one is set.
///
/// Errors: its models unloadable or of the wrong signature.
fn sam_timing(
    c: &EncodeConfig,
    placement: &slag_common::onnx::Placement,
    params: &crate::masks::sam::SamParams,
) -> Result<Option<crate::masks::sam::SamAutomaticMaskGenerator>> {
    let s = &c.masks.sam;
    match (&s.timing_encoder, &s.timing_decoder) {
        (Some(enc), Some(dec)) => Ok(Some(
            crate::masks::sam::SamAutomaticMaskGenerator::with_placement(
                enc,
                dec,
                placement,
                params.clone(),
            )?,
        )),
        _ => Ok(None),
    }
}

/// Host memory that the SAM decoder calls of all CPU front workers together may take, bytes
/// (2 GiB): each CPU front holds its own sessions, and ONNX Runtime's arena keeps a session's
/// largest call, so without a shared budget this term grows with the fronts (8 fronts at 64
/// prompts per call on 990 × 742 images: about 8 × 3.6 GiB). Each front's SAM model gets
/// `SAM_CPU_DECODER_BYTES / fronts` ([`crate::masks::sam::SamParams::decoder_batch_bytes`]).
pub const SAM_CPU_DECODER_BYTES: usize = 2 << 30;

/// `masks`, or, with a SAM timing model, the [`crate::masks::timed::TimedMasks`] pair of `timing`
/// and `masks` (named `sam timing=<timing encoder> masks=<mask encoder>` after the files' stems).
fn with_timing(
    c: &EncodeConfig,
    masks: crate::masks::sam::SamAutomaticMaskGenerator,
    timing: Option<crate::masks::sam::SamAutomaticMaskGenerator>,
) -> Box<dyn MaskGenerator> {
    let stem = |p: Option<&std::path::Path>| {
        p.and_then(|p| p.file_stem())
            .map_or_else(String::new, |s| s.to_string_lossy().into_owned())
    };
    match timing {
        Some(t) => {
            let name = format!(
                "sam timing={} masks={}",
                stem(c.masks.sam.timing_encoder.as_deref()),
                stem(c.masks.sam.encoder.as_deref())
            );
            Box::new(crate::masks::timed::TimedMasks::new(
                Box::new(t),
                Box::new(masks),
                name,
            ))
        }
        None => Box::new(masks),
    }
}

/// The mask generator `c` asks for, with `threads` ONNX Runtime intra-op threads (SAM on GPU 0
/// with `c`'s execution provider; with a SAM timing model, the pair
/// [`crate::masks::timed::TimedMasks`]).
///
/// Errors: SAM's models missing or unloadable.
pub fn build_masks(c: &EncodeConfig, threads: usize) -> Result<Box<dyn MaskGenerator>> {
    build_masks_within(c, threads, None)
}

/// [`build_masks`] with SAM's decoder calls capped at `decoder_batch_bytes` of host memory
/// ([`crate::masks::sam::SamParams::decoder_batch_bytes`]; `None`: no cap).
fn build_masks_within(
    c: &EncodeConfig,
    threads: usize,
    decoder_batch_bytes: Option<usize>,
) -> Result<Box<dyn MaskGenerator>> {
    Ok(match c.masks.source {
        MaskSource::Sam => {
            let (enc, dec) = sam_paths(c)?;
            let placement = c.placement(0, threads);
            let params = crate::masks::sam::SamParams {
                decoder_batch_bytes,
                ..c.masks.sam.params()
            };
            let masks = crate::masks::sam::SamAutomaticMaskGenerator::with_placement(
                enc,
                dec,
                &placement,
                params.clone(),
            )?;
            with_timing(c, masks, sam_timing(c, &placement, &params)?)
        }
        MaskSource::Graph => Box::new(crate::masks::graph::GraphSegmenter::new(
            c.masks.graph.params(),
        )),
    })
}

/// The report's inputs, models and parameters sections for `c` run with `threads` threads
/// (the rest is filled by the run).
pub fn report_header(c: &EncodeConfig, threads: usize) -> Report {
    let scene = scene_input(c);
    let (sam, a, e) = (&c.masks.sam, &c.aggregate, &c.execution);
    Report {
        slag_version: env!("CARGO_PKG_VERSION").to_string(),
        inputs: Inputs {
            every: scene.every,
            hold_out_every: scene.hold_out_every,
            ply: scene.ply,
            scene: scene.dir,
        },
        models: Models {
            clip_visual: c.clip.visual.clone(),
            execution_provider_requested: e.ep,
            sam_decoder: sam.decoder.clone(),
            sam_encoder: sam.encoder.clone(),
            ..Default::default()
        },
        parameters: Parameters {
            clip_batch: c.clip.batch,
            crop_fill: c.clip.crop_fill,
            device_reduce_budget: Some(super::budget::of(c)),
            cluster_addresses: None,
            cluster_processes: None,
            front_workers: e.front_workers,
            gpus: format!("{:?}", e.gpus),
            graph_k: c.masks.graph.k.map(f64::from),
            graph_min_size: c.masks.graph.min_size,
            levels: a.levels,
            mask_weighting: a.mask_weighting,
            min_weight: a.min_weight,
            mixture_keep: a.mixture_keep,
            overlap: a.overlap,
            mask_erode: a.mask_erode,
            raster_scale: c.raster.scale,
            sam_box_nms_thresh: f64::from(sam.box_nms_thresh),
            sam_points_per_batch: sam.points_per_batch,
            sam_points_per_side: sam.points_per_side,
            sam_pred_iou_thresh: f64::from(sam.pred_iou_thresh),
            sam_stability_score_thresh: f64::from(sam.stability_score_thresh),
            threads,
            top_k_per_pixel: a.top_k_per_pixel,
        },
        ..Default::default()
    }
}

/// Worker threads of `c` ([`crate::config::ExecutionConfig::resolved_threads`]); sets rayon's
/// global pool to that size unless it already exists (tests, bench repeats).
pub fn setup_threads(c: &EncodeConfig) -> usize {
    let threads = c.execution.resolved_threads();
    let _ = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build_global();
    threads
}

/// The pipeline parameters `c` asks for.
pub fn encode_params(c: &EncodeConfig) -> EncodeParams {
    let a = &c.aggregate;
    EncodeParams {
        raster_scale: c.raster.scale,
        image_stage: ImageStageParams {
            top_k_per_pixel: a.top_k_per_pixel,
            mask_weighting: a.mask_weighting,
            overlap: a.overlap,
            mask_erode: a.mask_erode,
        },
        reduce: ReduceParams {
            min_total_weight: a.min_weight,
            accumulator_budget_bytes: a.accumulator_memory_mb << 20,
            ..Default::default()
        },
        contribution_budget_bytes: a.contribution_memory_mb << 20,
        precision: c.output.precision,
        out_dir: c.output.dir.clone(),
        dense: c.output.dense,
        progress: c.output.progress,
        mixture_keep: a.mixture_keep,
        levels: a.levels,
        mask_record_slots: c
            .segments
            .enabled
            .then_some(slag_common::mask_record::DEFAULT_SLOTS),
        reduce_on: a.reduce_on,
        device_reduce_budget_bytes: super::budget::of(c).bytes,
    }
}

/// The weight rasterizer `backend` names, over the Gaussians `g`.
///
/// Errors: no GPU adapter (GPU backend), the scene too large for it.
pub fn make_rasterizer(backend: RasterBackend, g: &Gaussians) -> Result<Box<dyn WeightRasterizer>> {
    Ok(match backend {
        RasterBackend::Gpu => Box::new(crate::raster::gpu::GpuRasterizer::new(g)?),
        RasterBackend::Cpu => Box::new(crate::raster::cpu::CpuRasterizer::new(g)),
    })
}

/// The rasterizers of a run of `c`: one per GPU ([`crate::config::ExecutionConfig::gpus`]), or
/// the one CPU reference.
///
/// Errors: as [`make_rasterizer`]; fewer GPUs than a [`GpuCount::Count`] asks for.
pub fn make_rasterizers(c: &EncodeConfig, g: &Gaussians) -> Result<Vec<Box<dyn WeightRasterizer>>> {
    let want = match c.execution.gpus {
        GpuCount::Count(n) => Some(n),
        GpuCount::All => None,
    };
    Ok(match c.raster.backend {
        RasterBackend::Gpu => crate::raster::gpu::GpuRasterizer::new_many(g, want)?
            .into_iter()
            .map(|r| Box::new(r) as Box<dyn WeightRasterizer>)
            .collect(),
        RasterBackend::Cpu => vec![make_rasterizer(RasterBackend::Cpu, g)?],
    })
}

/// The GPUs a run of `c` rasterizes on: 1 with the CPU rasterizer, the count asked for, or
/// every discrete GPU wgpu sees (1 when it sees none).
pub fn gpu_count(c: &EncodeConfig) -> usize {
    match (c.raster.backend, c.execution.gpus) {
        (RasterBackend::Cpu, _) => 1,
        (_, GpuCount::Count(n)) => n,
        (_, GpuCount::All) => crate::raster::gpu::adapter_names()
            .map(|v| v.len())
            .unwrap_or(1),
    }
}

/// The front workers of a run and what keeps their shared models alive.
pub struct Fronts {
    /// One entry per front worker.
    pub stages: Vec<FrontStages>,
    /// The CLIP services of the GPUs (empty on the CPU); dropped after the encode.
    pub services: Vec<crate::clip::ClipService>,
    /// Per GPU (or one entry for the CPU): where each model actually runs.
    pub providers: Vec<ModelPlacement>,
    /// The provider that actually runs CLIP (and SAM): `cpu`, `cuda`, `tensorrt`.
    pub provider: ExecutionProvider,
}

/// Builds the front workers of `c` over `gpus` GPUs with `threads` cores.
///
/// With provider `cpu`, or `auto` without a usable GPU provider (CLIP is loaded on GPU 0 first
/// to find out), every front worker gets its own sessions with a share of the cores (as ONNX
/// Runtime's CPU provider scales best) and a share of [`SAM_CPU_DECODER_BYTES`] for its SAM
/// decoder calls. Otherwise each GPU gets one SAM session pair and one
/// [`crate::clip::ClipService`], all set up side by side ([`gpu_models`]), and the workers are
/// bound round-robin to the GPUs. The CLIP batch defaults to [`CLIP_BATCH_GPU`] on a GPU
/// provider, [`CLIP_BATCH_CPU`] on the CPU.
///
/// Errors: models missing or unloadable.
pub fn build_fronts(c: &EncodeConfig, gpus: usize, threads: usize) -> Result<Fronts> {
    let gpu_threads = (threads / gpus.max(1)).max(1);
    let gpu_batch = c.clip.batch.unwrap_or(CLIP_BATCH_GPU);
    let clip0 = match c.execution.ep {
        ExecutionProvider::Cpu => return cpu_fronts(c, gpus, threads),
        // Only a built session tells whether `auto` found a GPU.
        ExecutionProvider::Auto => {
            let clip0 = gpu_clip(c, 0, gpu_threads, gpu_batch)?;
            if clip0.provider() == ExecutionProvider::Cpu {
                drop(clip0);
                return cpu_fronts(c, gpus, threads);
            }
            Some(clip0)
        }
        ExecutionProvider::Cuda | ExecutionProvider::TensorRt => None,
    };
    // Each GPU's models are set up on a thread of their own (sessions, warm-up runs: seconds
    // per GPU); the first error in GPU order is the one returned.
    let per_gpu: Vec<Result<(crate::clip::ClipService, Option<GpuSam>)>> =
        std::thread::scope(|s| {
            let others: Vec<_> = (1..gpus)
                .map(|g| s.spawn(move || gpu_models(c, g, gpu_threads, gpu_batch, None)))
                .collect();
            let first = gpu_models(c, 0, gpu_threads, gpu_batch, clip0);
            let joined = others.into_iter().map(|h| {
                h.join()
                    .unwrap_or_else(|_| Err(Error::internal("a GPU's model setup panicked")))
            });
            std::iter::once(first).chain(joined).collect()
        });
    let (mut services, mut sams, mut providers) = (Vec::new(), Vec::new(), Vec::new());
    for (g, models) in per_gpu.into_iter().enumerate() {
        let (service, sam) = models?;
        let (enc_p, dec_p) = sam.as_ref().map_or((None, None), |(s, _)| {
            let (e, d) = s.models().providers();
            (Some(e), Some(d))
        });
        providers.push(ModelPlacement {
            clip_batch: gpu_batch,
            clip_visual: service.provider(),
            device: service.device_label().to_string(),
            gpu: Some(g),
            sam_decoder: dec_p,
            sam_encoder: enc_p,
        });
        services.push(service);
        sams.push(sam);
    }
    let n = c
        .execution
        .front_workers
        .unwrap_or(4 * gpus)
        .clamp(1, threads.max(1));
    let mut stages = Vec::with_capacity(n);
    for w in 0..n {
        let g = w % gpus;
        let masks: Box<dyn MaskGenerator> = match &sams[g] {
            Some((sam, timing)) => with_timing(c, sam.share(), timing.as_ref().map(|t| t.share())),
            None => build_masks(c, 1)?,
        };
        stages.push(FrontStages {
            masks,
            crops: Box::new(services[g].handle()),
            gpu: Some(g),
        });
    }
    let provider = services.first().map_or(c.execution.ep, |s| s.provider());
    Ok(Fronts {
        stages,
        services,
        providers,
        provider,
    })
}

/// CLIP's visual tower on GPU `g` (`gpu_threads` host threads, batches of `gpu_batch` crops),
/// with the encode's crop fill.
///
/// Errors: the model missing or unloadable; the provider not registering.
fn gpu_clip(
    c: &EncodeConfig,
    g: usize,
    gpu_threads: usize,
    gpu_batch: usize,
) -> Result<crate::clip::ClipVisual> {
    let mut clip = crate::clip::ClipVisual::with_placement(
        &c.clip.visual,
        &c.placement(g as u32, gpu_threads),
        gpu_batch,
    )?;
    clip.set_crop_fill(c.clip.crop_fill);
    Ok(clip)
}

/// GPU `g`'s CLIP service (from `clip`, or a new session with `gpu_batch`) and SAM
/// ([`gpu_sam`]). CLIP, SAM and SAM's timing copy are set up side by side, each on a thread of
/// its own: each is seconds of session building (graph optimisation, weights to the device)
/// and warm-up, and none needs another.
///
/// Errors: the models missing or unloadable; CLIP's warm-up run failing (CLIP's error first,
/// then SAM's).
fn gpu_models(
    c: &EncodeConfig,
    g: usize,
    gpu_threads: usize,
    gpu_batch: usize,
    clip: Option<crate::clip::ClipVisual>,
) -> Result<(crate::clip::ClipService, Option<GpuSam>)> {
    let service = move || {
        timed("CLIP", g, || match clip {
            Some(clip) => clip.into_service(),
            None => gpu_clip(c, g, gpu_threads, gpu_batch)?.into_service(),
        })
    };
    let (service, sam) = slag_common::onnx::side_by_side("a CLIP model setup", service, || {
        gpu_sam(c, g, gpu_threads)
    });
    Ok((service?, sam?))
}

/// `set_up()`, with a debug line naming `model`, GPU `g` and the seconds it took (where the
/// encode's start goes: the report's `timings.models` is the longest of them).
fn timed<T>(model: &str, g: usize, set_up: impl FnOnce() -> Result<T>) -> Result<T> {
    let t0 = std::time::Instant::now();
    let out = set_up();
    tracing::debug!(
        target: "slag_encoder::pipeline",
        model,
        gpu = g,
        seconds = t0.elapsed().as_secs_f64(),
        ok = out.is_ok(),
        "model set up"
    );
    out
}

/// One GPU's SAM and the copy that times its stages (with the encode's SAM timing setting).
type GpuSam = (
    crate::masks::sam::SamAutomaticMaskGenerator,
    Option<crate::masks::sam::SamAutomaticMaskGenerator>,
);

/// SAM with its timing copy on GPU `g` (`gpu_threads` host threads) when `c` asks for SAM
/// masks; `None` for graph masks ([`build_fronts`]).
///
/// Errors: the SAM models missing or unloadable.
fn gpu_sam(c: &EncodeConfig, g: usize, gpu_threads: usize) -> Result<Option<GpuSam>> {
    if c.masks.source != MaskSource::Sam {
        return Ok(None);
    }
    let (enc, dec) = sam_paths(c)?;
    let placement = c.placement(g as u32, gpu_threads);
    let params = c.masks.sam.params();
    let (timing, sam) = slag_common::onnx::side_by_side(
        "a SAM timing model setup",
        || timed("SAM timing copy", g, || sam_timing(c, &placement, &params)),
        || {
            timed("SAM", g, || {
                crate::masks::sam::SamAutomaticMaskGenerator::with_placement(
                    enc,
                    dec,
                    &placement,
                    params.clone(),
                )
            })
        },
    );
    Ok(Some((sam?, timing?)))
}

/// The fronts when CLIP runs on the CPU ([`build_fronts`]): every worker its own SAM and CLIP
/// sessions with a share of the `threads` cores and of [`SAM_CPU_DECODER_BYTES`].
///
/// Errors: models missing or unloadable.
fn cpu_fronts(c: &EncodeConfig, gpus: usize, threads: usize) -> Result<Fronts> {
    let n = c
        .execution
        .front_workers
        .unwrap_or(gpus + 1)
        .clamp(1, threads.max(1));
    let per_front = (threads / n).max(1);
    let batch = c.clip.batch.unwrap_or(CLIP_BATCH_CPU);
    let mut cpu = c.clone();
    cpu.execution.ep = ExecutionProvider::Cpu;
    let mut stages = Vec::with_capacity(n);
    for _ in 0..n {
        let masks = build_masks_within(&cpu, per_front, Some(SAM_CPU_DECODER_BYTES / n))?;
        let mut clip = crate::clip::ClipVisual::with_threads(
            &c.clip.visual,
            ExecutionProvider::Cpu,
            batch,
            per_front,
        )?;
        clip.set_crop_fill(c.clip.crop_fill);
        stages.push(FrontStages::new(masks, Box::new(clip)));
    }
    let sam = (c.masks.source == MaskSource::Sam).then_some(ExecutionProvider::Cpu);
    Ok(Fronts {
        stages,
        services: Vec::new(),
        providers: vec![ModelPlacement {
            clip_batch: batch,
            clip_visual: ExecutionProvider::Cpu,
            device: "cpu".into(),
            gpu: None,
            sam_decoder: sam,
            sam_encoder: sam,
        }],
        provider: ExecutionProvider::Cpu,
    })
}
