//! The flags of `slag-encoder encode` ([`EncodeArgs`]) and their conversion into the library's
//! [`EncodeConfig`], one flag to one field. `slag-bench stages` and `slag-bench scaling` take
//! the same flags.

use std::path::PathBuf;

use clap::{Args, ValueEnum};
use slag_common::cli::EpArg;
use slag_common::embeddings::StoredPrecision;

use super::values::{
    CropFillArg, MaskSourceArg, MaskWeightingArg, OverlapArg, RasterArg, ViewsArg,
};
use crate::config::{
    AggregateConfig, ClipConfig, EncodeConfig, ExecutionConfig, GpuCount, GraphConfig, MasksConfig,
    OutputConfig, RasterConfig, SamConfig, SceneConfig, SegmentsConfig,
};
use crate::segments::SegmentParams;
use crate::views::{CoverageRule, ViewSelection};

/// `--precision`: stored precision of the embeddings.
#[derive(Debug, Clone, Copy, ValueEnum, PartialEq, Eq)]
pub enum PrecisionArg {
    /// 2 bytes per component.
    F16,
    /// 4 bytes per component.
    F32,
}

/// `--write-segments`: write the geometric segments or not.
#[derive(Debug, Clone, Copy, ValueEnum, PartialEq, Eq)]
pub enum OnOff {
    /// Write them.
    On,
    /// Do not.
    Off,
}

/// The settings of the geometric segmentation (`encode` and `segment`), one flag to one field
/// of [`SegmentParams`]; defaults are its defaults.
#[derive(Debug, Clone, Args)]
pub struct SegmentArgs {
    /// Segmentation: nearest neighbours per Gaussian in the graph.
    #[arg(long, default_value_t = SegmentParams::default().neighbours)]
    pub segment_neighbours: usize,
    /// Segmentation: Felzenszwalb–Huttenlocher scale τ (larger = larger segments).
    #[arg(long, default_value_t = SegmentParams::default().threshold)]
    pub segment_threshold: f32,
    /// Segmentation: segments below this many Gaussians merge into a neighbour.
    #[arg(long, default_value_t = SegmentParams::default().min_size)]
    pub segment_min_size: usize,
    /// Segmentation: longest graph edge, scene units; default 10 × the
    /// median of the Gaussians' largest standard deviation.
    #[arg(long, value_name = "LENGTH")]
    pub segment_max_edge: Option<f32>,
    /// Segmentation: most Gaussians per tile (bounds the graph's memory; smaller tiles run faster
    /// and their segments differ more from one tile's across tile borders).
    #[arg(long, default_value_t = SegmentParams::default().tile_gaussians)]
    pub segment_tile_gaussians: usize,
    /// Segmentation: weight of the mask term (an edge whose ends fall in different SAM masks in
    /// the views that see both gets this much added; 0 = geometry only).
    #[arg(long, default_value_t = SegmentParams::default().mask_weight)]
    pub segment_mask_weight: f32,
    /// Segmentation: mask disagreement assumed for neighbours that share no recorded view.
    #[arg(long, default_value_t = SegmentParams::default().mask_unknown)]
    pub segment_mask_unknown: f32,
    /// Segmentation: small segments do not merge across an edge whose mask disagreement exceeds
    /// this (1 = they merge across anything).
    #[arg(long, default_value_t = SegmentParams::default().mask_veto)]
    pub segment_mask_veto: f32,
    /// Segmentation: two segments never join when their regions' mask disagreement (their
    /// Gaussians' recorded masks pooled per view) exceeds this (1 = no region veto).
    #[arg(long, default_value_t = SegmentParams::default().region_veto)]
    pub segment_region_veto: f32,
    /// Segmentation: weight of the normal term (splats' shortest axes).
    #[arg(long, default_value_t = SegmentParams::default().normal_weight)]
    pub segment_normal_weight: f32,
    /// Segmentation: weight of the gap term (distance beyond the splats' 2σ overlap).
    #[arg(long, default_value_t = SegmentParams::default().distance_weight)]
    pub segment_distance_weight: f32,
    /// Segmentation: weight of the shape term (ratio of the splats' sizes).
    #[arg(long, default_value_t = SegmentParams::default().shape_weight)]
    pub segment_shape_weight: f32,
}

impl From<&SegmentArgs> for SegmentParams {
    fn from(a: &SegmentArgs) -> Self {
        SegmentParams {
            neighbours: a.segment_neighbours,
            threshold: a.segment_threshold,
            min_size: a.segment_min_size,
            max_edge: a.segment_max_edge,
            tile_gaussians: a.segment_tile_gaussians,
            mask_weight: a.segment_mask_weight,
            mask_unknown: a.segment_mask_unknown,
            mask_veto: a.segment_mask_veto,
            region_veto: a.segment_region_veto,
            normal_weight: a.segment_normal_weight,
            distance_weight: a.segment_distance_weight,
            shape_weight: a.segment_shape_weight,
        }
    }
}

/// Arguments of `encode`.
#[derive(Debug, Clone, Args)]
pub struct EncodeArgs {
    /// Scene folder: point_cloud.ply (or --ply), images/, and sparse/0 (COLMAP) or transforms.json.
    #[arg(long = "scene-dir", value_name = "DIR")]
    pub scene: PathBuf,
    /// The trained 3DGS .ply (INRIA layout); default <scene>/point_cloud.ply.
    #[arg(long)]
    pub ply: Option<PathBuf>,
    /// Mask source.
    #[arg(long, value_enum, default_value_t = MaskSourceArg::Sam)]
    pub masks: MaskSourceArg,
    /// SAM image encoder ONNX (pixel_values f32[1,3,1024,1024] -> image_embeddings).
    #[arg(long, required_if_eq("masks", "sam"))]
    pub sam_encoder: Option<PathBuf>,
    /// SAM prompt decoder ONNX (segment_anything SamOnnxModel signature).
    #[arg(long, required_if_eq("masks", "sam"))]
    pub sam_decoder: Option<PathBuf>,
    /// Benchmarks: a second SAM image encoder (e.g. ViT-H) run on every image for its cost only,
    /// with the same SAM settings; its masks are dropped and --sam-encoder/--sam-decoder's
    /// masks go downstream (a timing model + mask model pair; the report names both).
    #[arg(long, requires = "sam_timing_decoder")]
    pub sam_timing_encoder: Option<PathBuf>,
    /// The timing model's SAM prompt decoder (see --sam-timing-encoder).
    #[arg(long, requires = "sam_timing_encoder")]
    pub sam_timing_decoder: Option<PathBuf>,
    /// SAM point grid: points per image side (segment_anything's default 32).
    #[arg(long, default_value_t = 32)]
    pub sam_points_per_side: u32,
    /// SAM prompts per decoder call [default: 128 when the decoder runs on a GPU, 64 on the
    /// CPU].
    #[arg(long)]
    pub sam_points_per_batch: Option<usize>,
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
    /// CLIP visual tower ONNX (pixel_values f32[B,3,224,224], or pixels u8[B,3,224,224] from
    /// scripts/clip-u8-pixels.py, -> [B,D]).
    #[arg(long)]
    pub clip_visual: PathBuf,
    /// Crops per CLIP batch (default: 64 on a GPU provider, where the batched service ran
    /// ViT-B/16 fp16 1.45x faster than at 32 on an H100 (docs/results/gpu-models.md); 32 on the CPU).
    #[arg(long)]
    pub clip_batch: Option<usize>,
    /// Where each mask crop's white fill is applied: before-resize (the default, the paper's
    /// order: white outside the mask, then the resize to CLIP's 224 × 224, which blends the
    /// mask's border with white) or after-resize (the box of the image, the mask's colours
    /// extended past its border, and the box of the mask resized alike, then white outside the
    /// resized mask: the border keeps its colour). after-resize helped the labelled-object room
    /// with heavy texture but cost snowmiku's held-out mIoU (docs/results/prediction-filtering.md).
    #[arg(long, value_enum, value_name = "ORDER", default_value_t = CropFillArg::BeforeResize)]
    pub crop_fill: CropFillArg,
    /// Keep every N-th image (1 = all; the paper uses 1:20 on large scenes).
    #[arg(long, value_name = "N", default_value_t = 1)]
    pub every: usize,
    /// Hold out the views with name-sorted index ≡ N/2 (mod N) for `eval-colors --held-out`
    /// and train on all the others (N >= 2; e.g. 4 trains on 3 views of 4).
    #[arg(long, value_name = "N")]
    pub hold_out_every: Option<usize>,
    /// Which training views are encoded: coverage (the default: a cheap weight-raster pass, then
    /// a greedy choice that stops where views add little; see --view-coverage-*), all, or uniform
    /// (--view-count of them, evenly spaced). `encode-cluster` takes all views unless asked.
    #[arg(long, value_enum, value_name = "RULE")]
    pub views: Option<ViewsArg>,
    /// With --views uniform: exactly this many views. With --views coverage: at most this many
    /// (the first of the greedy order).
    #[arg(long, value_name = "N")]
    pub view_count: Option<usize>,
    /// --views coverage: blend weight a view must give a Gaussian to count as seeing it, in
    /// pixels of the full-resolution image (Σ_p α·T over the view). Default: the scene's own,
    /// 1 pixel or, in a scene denser in Gaussians than pixels, the median of the Gaussians'
    /// largest weights in 16 evenly spaced views.
    #[arg(long, value_name = "PIXELS")]
    pub view_coverage_weight: Option<f64>,
    /// --views coverage: distinct viewpoints that must see each observed Gaussian (fewer where
    /// the training views have fewer).
    #[arg(long, value_name = "K", default_value_t = CoverageRule::default().min_views)]
    pub view_coverage_min_views: usize,
    /// --views coverage: angle between two views' directions to a Gaussian from which they are
    /// distinct viewpoints of it, degrees (0: any two views).
    #[arg(long, value_name = "DEGREES", default_value_t = CoverageRule::default().min_angle_deg)]
    pub view_coverage_angle: f64,
    /// --views coverage: stop once the chosen views give this fraction of the (Gaussian,
    /// viewpoint) pairs the rule asks for, each weighted by the Gaussian's footprint in pixels
    /// (1: no bound; 0.95 drops the views that add the last 5 %).
    #[arg(long, value_name = "FRACTION", default_value_t = CoverageRule::default().target)]
    pub view_coverage_target: f64,
    /// --views coverage: the stopping rule; keep the views of the greedy order while a view adds
    /// at least this fraction of what the first view added (new distinct viewpoints, weighted by
    /// the Gaussians' footprints in pixels; 0: every view that adds one).
    #[arg(long, value_name = "FRACTION", default_value_t = CoverageRule::default().min_gain)]
    pub view_coverage_min_gain: f64,
    /// --views coverage: raster resolution of the coverage pass relative to the images.
    #[arg(long, value_name = "SCALE", default_value_t = CoverageRule::default().raster_scale)]
    pub view_coverage_raster_scale: f64,
    /// Raster resolution relative to the images (weights are computed at this resolution).
    #[arg(long, default_value_t = 0.5)]
    pub raster_scale: f64,
    /// Weight rasterizer.
    #[arg(long, value_enum, default_value_t = RasterArg::Gpu)]
    pub rasterizer: RasterArg,
    /// ONNX Runtime execution provider for SAM and CLIP: `auto` = CUDA where the loaded ONNX
    /// Runtime has it and a GPU answers, else the CPU (one line says why).
    #[arg(long, value_enum, default_value_t = EpArg::Auto)]
    pub ep: EpArg,
    /// Cap of each model session's CUDA memory arena, GiB (default: no cap beyond the card).
    #[arg(long, value_name = "GIB")]
    pub gpu_mem_limit_gb: Option<f64>,
    /// Worker threads (ONNX Runtime intra-op and CPU stages; a quarter of them segment the
    /// Gaussians beside the encode, see --write-segments); default: all cores.
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
    /// stability). Measured held-out in docs/results/tradeoffs.md: area adds +0.004 over --overlap
    /// finest with SAM masks but costs 0.032 with graph masks, so it is not the default.
    #[arg(long, value_enum, default_value_t = MaskWeightingArg::None)]
    pub mask_weighting: MaskWeightingArg,
    /// Which masks a pixel covered by several gives its blend weights to: finest (the default:
    /// only the smallest covering mask, so each Gaussian mixes only its most specific segments)
    /// or all (the paper's a_kj). `--overlap all --mask-weighting none` is the paper's mean.
    #[arg(long, value_enum, default_value_t = OverlapArg::Finest)]
    pub overlap: OverlapArg,
    /// Erode every mask by PIXELS image pixels (a square of that radius) before its pixels
    /// credit it in the a_kj, so that the border pixels of a mask, where its assignment is least
    /// certain, credit only the masks that still hold them (or none). The CLIP crop keeps the
    /// whole mask; the image's edge is not a border; a mask erosion would empty is kept whole.
    /// Default 0: whole masks (the paper's a_kj).
    #[arg(long, value_name = "PIXELS", default_value_t = 0)]
    pub mask_erode: u32,
    /// Also write OUT/embeddings-level{0,1,2}.safetensors: one embedding per SAM granularity
    /// level (subpart, part, whole; SAM's three multimask outputs), each reduced over that
    /// level's masks only (LangSplat's levels; needs --masks sam).
    #[arg(long)]
    pub levels: bool,
    /// Σa below which a Gaussian is unobserved (gets no embedding).
    #[arg(long, default_value_t = 1e-6)]
    pub min_weight: f64,
    /// Memory for per-image contributions before spilling to disk, MiB; with --dense, the
    /// views batched for one sweep over the dense accumulators' spilled tiles.
    #[arg(long, default_value_t = 4096)]
    pub contribution_memory_mb: usize,
    /// Memory for the reduction's f64 accumulator, MiB (larger scenes are reduced in chunks;
    /// with --dense, the tiles of (D + 1) × 8 B a Gaussian past it spill to disk under OUT).
    #[arg(long, default_value_t = 2048)]
    pub accumulator_memory_mb: usize,
    /// Where E_k is reduced: host (the CPU, in f64), device (on the GPU: the label sums stay on
    /// the device; also lavapipe; an error where it cannot, and with --dense), or auto (the GPU
    /// where it can and --dense is not asked for; past --device-reduce-memory-mb it goes on on
    /// the host). --dense is always reduced on the host, each view folded as it comes.
    #[arg(long, value_enum, default_value_t = crate::config::ReduceOn::Auto)]
    pub reduce: crate::config::ReduceOn,
    /// Device memory for the label sums kept for the GPU reduction, MiB (16 B per Gaussian and
    /// pixel label of each view). Default: half the least free memory of the GPUs nvidia-smi
    /// lists at the start, or 16384 where it cannot be read.
    #[arg(long)]
    pub device_reduce_memory_mb: Option<usize>,
    /// Stored precision of the embeddings.
    #[arg(long, value_enum, default_value_t = PrecisionArg::F16)]
    pub precision: PrecisionArg,
    /// Write OUT/mixture.safetensors (an output by default): a shared codebook of the mask
    /// embeddings plus each Gaussian's S largest a_kj (the compressed form the shards carry by
    /// default; the mean of a Gaussian's 4 strongest masks was the best held-out point,
    /// docs/results/tradeoffs.md). Default 4 for `encode`; 0 writes no mixture and then implies
    /// --dense; `encode-cluster` writes none unless asked (and then refuses: one-process encodes
    /// only).
    #[arg(long, value_name = "S", value_parser = parse_keep)]
    pub mixture_keep: Option<usize>,
    /// Also write the dense embeddings OUT/embeddings.safetensors: one E_k row of D values per
    /// observed Gaussian at --precision (about 1 KiB a Gaussian at f16 and D = 512, 31 GB at 30M
    /// Gaussians). Off by default: the mixture, the segments and the report are enough for
    /// `partition`, `serve` and `query`; `eval-colors`, `eval-objects` and an upload to Qdrant
    /// without expansion read the dense file.
    #[arg(long)]
    pub dense: bool,
    /// Output folder (mixture.safetensors, segments.safetensors, report.json; with --dense
    /// embeddings.safetensors).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// No progress bars.
    #[arg(long)]
    pub quiet: bool,
    /// Also write the Gaussians' geometric segments (`segments.safetensors`, for prediction
    /// filtering, the shards and `&smooth=segment`): computed beside the encode, written after it
    /// succeeded.
    #[arg(
        long = "write-segments",
        value_enum,
        value_name = "on|off",
        default_value_t = OnOff::On
    )]
    pub segments: OnOff,
    /// The segmentation's settings (`--segment-*`).
    #[command(flatten)]
    pub segment: SegmentArgs,
}

/// `--mixture-keep`: a slot count (0: no mixture file, dense embeddings only).
fn parse_keep(s: &str) -> Result<usize, String> {
    s.parse::<usize>()
        .map_err(|e| format!("{e}; pass a slot count (0: dense embeddings only)"))
}

/// `--mixture-keep` as the one-process encode reads it: unset → the library's default
/// ([`crate::config::DEFAULT_MIXTURE_KEEP`]), 0 → none.
fn mixture_keep(flag: Option<usize>) -> Option<usize> {
    match flag {
        None => Some(crate::config::DEFAULT_MIXTURE_KEEP),
        Some(0) => None,
        Some(k) => Some(k),
    }
}

impl From<&EncodeArgs> for EncodeConfig {
    fn from(a: &EncodeArgs) -> Self {
        EncodeConfig {
            scene: scene_config(a),
            masks: masks_config(a),
            clip: ClipConfig {
                visual: a.clip_visual.clone(),
                batch: a.clip_batch,
                crop_fill: a.crop_fill.into(),
            },
            raster: RasterConfig {
                scale: a.raster_scale,
                backend: a.rasterizer.into(),
            },
            aggregate: AggregateConfig {
                top_k_per_pixel: a.top_k_per_pixel,
                mask_weighting: a.mask_weighting.into(),
                overlap: a.overlap.into(),
                mask_erode: a.mask_erode,
                levels: a.levels,
                min_weight: a.min_weight,
                contribution_memory_mb: a.contribution_memory_mb,
                accumulator_memory_mb: a.accumulator_memory_mb,
                mixture_keep: mixture_keep(a.mixture_keep),
                reduce_on: a.reduce,
                device_reduce_memory_mb: a.device_reduce_memory_mb,
            },
            output: OutputConfig {
                dir: a.out.clone(),
                precision: match a.precision {
                    PrecisionArg::F16 => StoredPrecision::F16,
                    PrecisionArg::F32 => StoredPrecision::F32,
                },
                progress: !a.quiet,
                // `--mixture-keep 0` keeps its meaning "dense embeddings only".
                dense: a.dense || a.mixture_keep == Some(0),
            },
            execution: ExecutionConfig {
                ep: a.ep.into(),
                gpu_mem_limit_gb: a.gpu_mem_limit_gb,
                threads: a.threads,
                gpus: a.gpus,
                front_workers: a.front_workers,
            },
            segments: SegmentsConfig {
                enabled: a.segments == OnOff::On,
                params: SegmentParams::from(&a.segment),
            },
        }
    }
}

/// The scene and its views of `a` (`--scene-dir`, `--ply`, `--every`, `--hold-out-every`,
/// `--views` and the coverage rule's flags).
fn scene_config(a: &EncodeArgs) -> SceneConfig {
    SceneConfig {
        dir: a.scene.clone(),
        ply: a.ply.clone(),
        every: a.every,
        hold_out_every: a.hold_out_every,
        views: ViewSelection {
            mode: a.views.unwrap_or_default().into(),
            count: a.view_count,
            coverage: CoverageRule {
                min_weight: a.view_coverage_weight,
                min_views: a.view_coverage_min_views,
                min_angle_deg: a.view_coverage_angle,
                target: a.view_coverage_target,
                min_gain: a.view_coverage_min_gain,
                raster_scale: a.view_coverage_raster_scale,
            },
        },
    }
}

/// The mask source of `a` and the settings of each (`--masks`, `--sam-*`, `--graph-*`).
fn masks_config(a: &EncodeArgs) -> MasksConfig {
    MasksConfig {
        source: a.masks.into(),
        sam: SamConfig {
            encoder: a.sam_encoder.clone(),
            decoder: a.sam_decoder.clone(),
            points_per_side: a.sam_points_per_side,
            points_per_batch: a.sam_points_per_batch,
            pred_iou_thresh: a.sam_pred_iou_thresh,
            stability_score_thresh: a.sam_stability_score_thresh,
            box_nms_thresh: a.sam_box_nms_thresh,
            timing_encoder: a.sam_timing_encoder.clone(),
            timing_decoder: a.sam_timing_decoder.clone(),
        },
        graph: GraphConfig {
            k: a.graph_k,
            min_size: a.graph_min_size,
        },
    }
}
