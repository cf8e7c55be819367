//! The typed configuration of one encode run ([`EncodeConfig`]), grouped by the paper's stages:
//! scene and views, masks `M_j`, CLIP crops `E_j`, the weight raster `w_kp`, the aggregation
//! `a_kj` → `E_k`, the output files and where the work runs. [`crate::pipeline::Encoder`] runs it
//! (one process, one or more GPUs), [`crate::distributed::ClusterEncoder`] runs it over several
//! processes; `slag-encoder encode`'s flags convert into it one to one.
//!
//! Every default here is the command line's default. A config serialises to JSON (`serde`) and
//! back, so it can be stored beside a run or used as a cache key; unknown fields are refused,
//! missing ones take their defaults.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};
use slag_common::embeddings::StoredPrecision;
use slag_common::onnx::{ExecutionProvider, Placement};

use crate::aggregate::MaskOverlap;
use crate::aggregate::MaskWeighting;

/// Everything one encode run needs besides the models' and scene's files themselves.
///
/// [`EncodeConfig::new`] fills the command line's defaults (SAM masks, raster scale 0.5, one GPU,
/// execution provider `auto`, f16 output); set [`MasksConfig::sam`]'s model paths, or switch to
/// [`MasksConfig::graph`], before running.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EncodeConfig {
    /// The scene and which of its views are encoded (stage: load).
    pub scene: SceneConfig,
    /// Where the masks `M_j` come from (stage: masks).
    pub masks: MasksConfig,
    /// The CLIP visual tower embedding each mask's crop, `E_j` (stage: clip).
    pub clip: ClipConfig,
    /// The weight rasterizer giving `w_kp = α_kp T_kp` (stage: raster).
    pub raster: RasterConfig,
    /// How `a_kj` and `E_k` are formed and which reductions are written (stage: aggregate).
    pub aggregate: AggregateConfig,
    /// Output folder and format.
    pub output: OutputConfig,
    /// Threads, GPUs and the ONNX Runtime execution provider (no effect on the result).
    pub execution: ExecutionConfig,
    /// Geometric segments of the Gaussians, written beside the embeddings as
    /// `segments.safetensors` (on by default; [`crate::segments`]).
    pub segments: SegmentsConfig,
}

/// Whether and how `encode` segments the scene's Gaussians (Felzenszwalb–Huttenlocher over a
/// k-NN graph of the means, its edges weighed by geometry and the encode's masks:
/// [`crate::segments`]). The segments are used by
/// prediction filtering (`eval-colors --prediction-filtering`), carried in the shards, and
/// smooth query scores (`&smooth=segment`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SegmentsConfig {
    /// Write `segments.safetensors` (default on).
    pub enabled: bool,
    /// The segmentation's settings ([`crate::segments::SegmentParams::default`]).
    pub params: crate::segments::SegmentParams,
}

impl Default for SegmentsConfig {
    fn default() -> Self {
        SegmentsConfig {
            enabled: true,
            params: crate::segments::SegmentParams::default(),
        }
    }
}

impl EncodeConfig {
    /// The command line's defaults for the scene folder `scene_dir`, the CLIP visual tower
    /// `clip_visual` and the output folder `out_dir`. Masks default to SAM, whose two models
    /// still have to be set ([`MasksConfig::sam`]), or use [`MasksConfig::graph`].
    pub fn new(
        scene_dir: impl Into<PathBuf>,
        clip_visual: impl Into<PathBuf>,
        out_dir: impl Into<PathBuf>,
    ) -> Self {
        EncodeConfig {
            scene: SceneConfig {
                dir: scene_dir.into(),
                ..Default::default()
            },
            clip: ClipConfig {
                visual: clip_visual.into(),
                ..Default::default()
            },
            output: OutputConfig {
                dir: out_dir.into(),
                ..Default::default()
            },
            ..Default::default()
        }
    }

    /// Checks what a run would otherwise refuse only after loading models: required paths set,
    /// SAM's models with SAM masks, levels only with SAM masks, counts that must be positive.
    /// Files are not opened here.
    ///
    /// Errors: the first [`ConfigError`] found.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let missing = |field| Err(ConfigError::Missing { field });
        if self.scene.dir.as_os_str().is_empty() {
            return missing(Field::SceneDir);
        }
        if self.clip.visual.as_os_str().is_empty() {
            return missing(Field::ClipVisual);
        }
        if self.output.dir.as_os_str().is_empty() {
            return missing(Field::OutputDir);
        }
        if self.masks.source == MaskSource::Sam {
            if self.masks.sam.encoder.is_none() {
                return missing(Field::SamEncoder);
            }
            if self.masks.sam.decoder.is_none() {
                return missing(Field::SamDecoder);
            }
            match (
                &self.masks.sam.timing_encoder,
                &self.masks.sam.timing_decoder,
            ) {
                (Some(_), None) => return missing(Field::SamTimingDecoder),
                (None, Some(_)) => return missing(Field::SamTimingEncoder),
                _ => {}
            }
        }
        if self.aggregate.levels && self.masks.source != MaskSource::Sam {
            return Err(ConfigError::LevelsNeedSam);
        }
        if self.aggregate.mixture_keep == Some(0) {
            return Err(ConfigError::NotPositive {
                field: Field::MixtureKeep,
            });
        }
        if self.execution.gpus == GpuCount::Count(0) {
            return Err(ConfigError::NotPositive { field: Field::Gpus });
        }
        if !self.output.dense && self.aggregate.mixture_keep.is_none() {
            return Err(ConfigError::NoEmbeddingsOutput);
        }
        Ok(())
    }

    /// Refuses what a cluster encode cannot honour (instead of ignoring it): per-level files
    /// (written by the one-process encode only). The mixture, the dense file, the view
    /// selection, the segments, and each process's GPUs and front workers
    /// ([`ExecutionConfig::gpus`], [`ExecutionConfig::front_workers`], for that process alone)
    /// run as in a one-process encode.
    ///
    /// Errors: [`ConfigError::ClusterUnsupported`] naming what.
    pub fn check_cluster(&self) -> Result<(), ConfigError> {
        let unsupported = |what| Err(ConfigError::ClusterUnsupported(what));
        if self.aggregate.levels {
            return unsupported(ClusterUnsupported::Levels);
        }
        Ok(())
    }

    /// The `.ply` the run reads: [`SceneConfig::ply`] or `<scene>/point_cloud.ply`.
    pub fn ply(&self) -> PathBuf {
        self.scene
            .ply
            .clone()
            .unwrap_or_else(|| self.scene.dir.join("point_cloud.ply"))
    }

    /// Where the models run on GPU `device` with `threads` intra-op threads
    /// ([`ExecutionConfig::ep`], [`ExecutionConfig::gpu_mem_limit_gb`]).
    pub fn placement(&self, device: u32, threads: usize) -> Placement {
        Placement {
            ep: self.execution.ep,
            device,
            intra_threads: threads,
            gpu_mem_limit: self
                .execution
                .gpu_mem_limit_gb
                .filter(|g| *g > 0.0)
                .map(|g| (g * f64::from(1u32 << 30)) as usize),
        }
    }
}

/// The scene and its views (stage: load).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SceneConfig {
    /// Scene folder: `point_cloud.ply` (or [`SceneConfig::ply`]), `images/`, and `sparse/0`
    /// (COLMAP) or `transforms.json`. Required.
    pub dir: PathBuf,
    /// The trained 3DGS `.ply` (INRIA layout); `None` (default): `<dir>/point_cloud.ply`.
    pub ply: Option<PathBuf>,
    /// Keep every N-th view in name order (default 1 = all; the paper uses 1:20 on large
    /// scenes; 0 counts as 1).
    pub every: usize,
    /// Hold out the views with name-sorted index ≡ ⌊N/2⌋ (mod N), the views
    /// `eval-colors --held-out` scores, and train on all others (N ≥ 2; default `None`: none
    /// held out beyond what [`SceneConfig::every`] skips). [`crate::views`] has the split.
    pub hold_out_every: Option<usize>,
    /// Which of the training views are encoded (default: coverage selection with its own
    /// stopping rule; [`crate::views::ViewSelection`]).
    pub views: crate::views::ViewSelection,
}

impl Default for SceneConfig {
    fn default() -> Self {
        SceneConfig {
            dir: PathBuf::new(),
            ply: None,
            every: 1,
            hold_out_every: None,
            views: crate::views::ViewSelection::default(),
        }
    }
}

/// Where the masks come from (stage: masks).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MaskSource {
    /// SAM automatic mask generation over [`SamConfig::encoder`] / [`SamConfig::decoder`]
    /// (the default, as in the paper).
    #[default]
    Sam,
    /// Felzenszwalb-Huttenlocher graph segmentation (no model, fast, CPU).
    Graph,
}

/// The masks `M_j` of each image (stage: masks). Both generators' settings are kept whichever
/// runs; the report records them all.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MasksConfig {
    /// Which generator runs (default: SAM).
    pub source: MaskSource,
    /// SAM automatic mask generation.
    pub sam: SamConfig,
    /// The graph segmenter.
    pub graph: GraphConfig,
}

impl MasksConfig {
    /// SAM masks from the image encoder `encoder` and prompt decoder `decoder` (ONNX), with the
    /// default filters.
    pub fn sam(encoder: impl Into<PathBuf>, decoder: impl Into<PathBuf>) -> Self {
        MasksConfig {
            source: MaskSource::Sam,
            sam: SamConfig {
                encoder: Some(encoder.into()),
                decoder: Some(decoder.into()),
                ..Default::default()
            },
            graph: GraphConfig::default(),
        }
    }

    /// Graph-segmenter masks with its defaults.
    pub fn graph() -> Self {
        MasksConfig {
            source: MaskSource::Graph,
            ..Default::default()
        }
    }
}

/// SAM automatic mask generation (segment_anything's `SamAutomaticMaskGenerator`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SamConfig {
    /// SAM image encoder ONNX (`pixel_values f32[1,3,1024,1024] -> image_embeddings`); required
    /// with [`MaskSource::Sam`].
    pub encoder: Option<PathBuf>,
    /// SAM prompt decoder ONNX (segment_anything `SamOnnxModel` signature); required with
    /// [`MaskSource::Sam`].
    pub decoder: Option<PathBuf>,
    /// Point grid: points per image side (default 32, segment_anything's).
    pub points_per_side: u32,
    /// Prompts per decoder call (memory and speed, not the result); `None` (the default): 128
    /// on a GPU, 64 on the CPU ([`crate::masks::sam::SamParams::batch_for`]).
    pub points_per_batch: Option<usize>,
    /// Filter: minimum predicted IoU (default 0.88, segment_anything's).
    pub pred_iou_thresh: f32,
    /// Filter: minimum stability score (default 0.95, segment_anything's).
    pub stability_score_thresh: f32,
    /// Box NMS IoU threshold (default 0.7).
    pub box_nms_thresh: f32,
    /// Benchmarks only: a second SAM encoder ONNX (e.g. ViT-H) run on every image for its cost
    /// alone, with the same parameters; its masks are dropped and [`SamConfig::encoder`] /
    /// [`SamConfig::decoder`]'s go downstream ([`crate::masks::timed::TimedMasks`]). Set with
    /// [`SamConfig::timing_decoder`], or neither.
    pub timing_encoder: Option<PathBuf>,
    /// The timing model's prompt decoder ONNX (see [`SamConfig::timing_encoder`]).
    pub timing_decoder: Option<PathBuf>,
}

impl Default for SamConfig {
    fn default() -> Self {
        SamConfig {
            encoder: None,
            decoder: None,
            points_per_side: 32,
            points_per_batch: None,
            pred_iou_thresh: 0.88,
            stability_score_thresh: 0.95,
            box_nms_thresh: 0.7,
            timing_encoder: None,
            timing_decoder: None,
        }
    }
}

impl SamConfig {
    /// The mask generator's parameters (the others at [`crate::masks::sam::SamParams`]'
    /// defaults).
    pub fn params(&self) -> crate::masks::sam::SamParams {
        crate::masks::sam::SamParams {
            points_per_side: self.points_per_side,
            points_per_batch: self.points_per_batch,
            pred_iou_thresh: self.pred_iou_thresh,
            stability_score_thresh: self.stability_score_thresh,
            box_nms_thresh: self.box_nms_thresh,
            ..Default::default()
        }
    }
}

/// The graph segmenter; `None` keeps [`crate::masks::graph::GraphParams`]' default.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GraphConfig {
    /// Scale parameter k (larger = larger segments); default 500.
    pub k: Option<f32>,
    /// Minimum segment size, pixels; default 500.
    pub min_size: Option<u32>,
}

impl GraphConfig {
    /// The segmenter's parameters.
    pub fn params(&self) -> crate::masks::graph::GraphParams {
        let mut p = crate::masks::graph::GraphParams::default();
        if let Some(k) = self.k {
            p.k = k;
        }
        if let Some(m) = self.min_size {
            p.min_size = m;
        }
        p
    }
}

/// `clip.batch` default on a GPU execution provider: there the batched service ran ViT-B/16
/// fp16 1.45x faster than at 32 on an H100 (docs/results/gpu-models.md, "CLIP batch").
pub const CLIP_BATCH_GPU: usize = 64;
/// `clip.batch` default on the CPU execution provider.
pub const CLIP_BATCH_CPU: usize = 32;

/// The CLIP visual tower embedding each mask's crop (stage: clip).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ClipConfig {
    /// CLIP visual tower ONNX (`pixel_values f32[B,3,224,224]`, or `pixels u8[B,3,224,224]` from
    /// `scripts/clip-u8-pixels.py`, `-> [B,D]`). Required.
    pub visual: PathBuf,
    /// Crops per CLIP batch; `None` (default): [`CLIP_BATCH_GPU`] on a GPU provider,
    /// [`CLIP_BATCH_CPU`] on the CPU.
    pub batch: Option<usize>,
    /// Where each mask crop's white fill is applied relative to CLIP's resize (default: before
    /// it, the paper's order).
    pub crop_fill: crate::clip::CropFill,
}

/// Which weight rasterizer runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RasterBackend {
    /// wgpu compute (Vulkan: a GPU, or Mesa lavapipe on CPU-only machines).
    #[default]
    Gpu,
    /// The slow f64 CPU reference (for checking).
    Cpu,
}

/// The weight rasterizer (stage: raster).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RasterConfig {
    /// Raster resolution relative to the images (default 0.5); the weights `w_kp` are computed
    /// at this resolution, masks are resampled to it.
    pub scale: f64,
    /// Which rasterizer (default: GPU).
    pub backend: RasterBackend,
}

impl Default for RasterConfig {
    fn default() -> Self {
        RasterConfig {
            scale: 0.5,
            backend: RasterBackend::Gpu,
        }
    }
}

/// The mixture form's default slot count S: each Gaussian keeps the mean of its 4 strongest mask
/// embeddings. Measured held-out on snowmiku (docs/results/tradeoffs.md, "Both mask sources and two
/// splits"): above the dense `E_k` with graph masks (0.351 → 0.399) and color-sam (0.495 → 0.500),
/// on a second split too, at 52–68 bytes per Gaussian and no measurable encode time.
pub const DEFAULT_MIXTURE_KEEP: usize = 4;

/// The aggregation `a_kj = Σ_{p∈M_j} w_kp` → `E_k = Σ a_kj E_j / Σ a_kj` and the extra
/// reductions written beside the embeddings (stage: aggregate).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AggregateConfig {
    /// Keep only the K largest contributors per pixel; `None` (default): all, as in the paper.
    pub top_k_per_pixel: Option<usize>,
    /// Specificity weighting of each mask's `a_kj` (default: none, as in the paper).
    pub mask_weighting: MaskWeighting,
    /// Which masks a pixel covered by several gives its weights to (default: the finest).
    pub overlap: MaskOverlap,
    /// Erode every mask by this many image pixels for the `a_kj` only (default 0: whole masks;
    /// [`crate::aggregate::ImageStageParams::mask_erode`]).
    pub mask_erode: u32,
    /// Also write `embeddings-level{0,1,2}.safetensors`, one reduction per SAM granularity level
    /// (default off; needs [`MaskSource::Sam`]).
    pub levels: bool,
    /// `Σ a_kj` below which a Gaussian is unobserved and gets no embedding (default 1e-6).
    pub min_weight: f64,
    /// Memory for per-image contributions before spilling to disk, MiB (default 4096); with the
    /// dense file, the views batched for one sweep over its spilled tiles.
    pub contribution_memory_mb: usize,
    /// Memory for the reduction's f64 accumulator, MiB (default 2048; larger scenes are reduced
    /// in chunks; with the dense file, its tiles past it spill to disk,
    /// [`crate::aggregate::DenseFold`]).
    pub accumulator_memory_mb: usize,
    /// Write `mixture.safetensors`: a shared codebook of the mask embeddings plus each
    /// Gaussian's S largest `a_kj` (S ≥ 1); default [`DEFAULT_MIXTURE_KEEP`] (the default
    /// output); `None`: no mixture, which needs [`OutputConfig::dense`].
    pub mixture_keep: Option<usize>,
    /// Where the reduction to `E_k` runs (default [`ReduceOn::Auto`]).
    pub reduce_on: ReduceOn,
    /// Device memory the label sums kept for the device reduction may take, MiB (16 B per
    /// (Gaussian, label) key of every view); `None` (the default): sized from the GPUs' free
    /// memory at the start ([`crate::pipeline::budget`]).
    pub device_reduce_memory_mb: Option<usize>,
}

/// Where the reduction `E_k = Σ a_kj E_j / Σ a_kj` runs (`encode --reduce`). Both give the same
/// observed Gaussians, kept pairs and masks' record, and `E_k` within f64 round-off.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum ReduceOn {
    /// On the GPU where it can (GPU rasterizers with f64, no `--levels`) and the dense file is
    /// not asked for (its rows would cross to the host anyway: at 30M Gaussians the host's
    /// reduction, which overlaps their write, was the faster), else on the host. When the kept
    /// label sums meet the device memory limit during the run, the views kept so far are
    /// brought back to the host, which reduces (`Counts::device_reduce_fallback` in the report).
    /// The default: measured faster and lighter than the host at 2M and 30M Gaussians on an
    /// H100 (docs/results/scaling.md, docs/results/gpu-models.md).
    #[default]
    Auto,
    /// On the GPU (also on a CPU Vulkan device such as lavapipe); an error where it cannot,
    /// and with the dense file, which is always folded on the host as the views come
    /// ([`crate::aggregate::DenseFold`]).
    Device,
    /// On the host: every view's `a_kj` read back and folded in f64 on the CPU as it comes
    /// (machines without a GPU with f64, and `--dense`, reduce here under `auto` too).
    Host,
}

impl Default for AggregateConfig {
    fn default() -> Self {
        AggregateConfig {
            top_k_per_pixel: None,
            mask_weighting: MaskWeighting::None,
            overlap: MaskOverlap::Finest,
            mask_erode: 0,
            levels: false,
            min_weight: 1e-6,
            contribution_memory_mb: 4096,
            accumulator_memory_mb: 2048,
            mixture_keep: Some(DEFAULT_MIXTURE_KEEP),
            reduce_on: ReduceOn::Auto,
            device_reduce_memory_mb: None,
        }
    }
}

/// The output folder and format.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OutputConfig {
    /// Output folder (`mixture.safetensors`, `segments.safetensors`, `report.json`, the
    /// optional forms). Required.
    pub dir: PathBuf,
    /// Also write the dense embeddings `embeddings.safetensors`: one `E_k` row of D values per
    /// observed Gaussian in [`OutputConfig::precision`] (about 1 KiB a Gaussian at f16 and
    /// D = 512, against 52–68 bytes for the mixture). Default off: the mixture, the segments and
    /// the report are what the shards, the servers and the queries need; the dense file is for
    /// tools that read `E_k` rows directly (`eval-colors`, `eval-objects`, the Qdrant upload
    /// without expansion) and is the only form a cluster encode writes.
    pub dense: bool,
    /// Stored precision of the embeddings (default f16).
    pub precision: StoredPrecision,
    /// Progress bars on stderr (default on).
    pub progress: bool,
}

impl Default for OutputConfig {
    fn default() -> Self {
        OutputConfig {
            dir: PathBuf::new(),
            precision: StoredPrecision::F16,
            progress: true,
            dense: false,
        }
    }
}

/// Where the work runs: threads, GPUs, front workers, the ONNX Runtime execution provider. None
/// of it changes the result (beyond the f64 summation order of the reduction).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ExecutionConfig {
    /// ONNX Runtime execution provider for SAM and CLIP (default `auto`: CUDA where the loaded
    /// runtime has it and a GPU answers, else the CPU).
    pub ep: ExecutionProvider,
    /// Cap of each model session's CUDA memory arena, GiB; `None` (default): no cap beyond the
    /// card.
    pub gpu_mem_limit_gb: Option<f64>,
    /// Worker threads (ONNX Runtime intra-op and CPU stages; the geometric segments run beside
    /// the encode on a quarter of them, at least one); `None` (default): all cores.
    pub threads: Option<usize>,
    /// GPUs to rasterize on (default 1); ignored with [`RasterBackend::Cpu`].
    pub gpus: GpuCount,
    /// Front workers (decode → masks → CLIP crops); `None` (default): 1 per GPU plus 1 with the
    /// models on the CPU, 4 per GPU with the models on GPUs; at most the cores.
    pub front_workers: Option<usize>,
}

impl Default for ExecutionConfig {
    fn default() -> Self {
        ExecutionConfig {
            ep: ExecutionProvider::Auto,
            gpu_mem_limit_gb: None,
            threads: None,
            gpus: GpuCount::Count(1),
            front_workers: None,
        }
    }
}

impl ExecutionConfig {
    /// [`ExecutionConfig::threads`], or every core.
    pub fn resolved_threads(&self) -> usize {
        self.threads.unwrap_or_else(|| {
            std::thread::available_parallelism()
                .map(|n| n.get())
                .unwrap_or(1)
        })
    }
}

/// How many GPUs: a positive count or every one. Serialised as the count or `"all"`; its
/// `Debug` form (`Count(2)`, `All`) is what `report.json` records.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(try_from = "GpuCountRepr", into = "GpuCountRepr")]
pub enum GpuCount {
    /// Exactly this many GPUs (an error if fewer are visible).
    Count(usize),
    /// Every discrete GPU visible.
    All,
}

impl Default for GpuCount {
    fn default() -> Self {
        GpuCount::Count(1)
    }
}

impl std::str::FromStr for GpuCount {
    type Err = String;
    /// `all` (any case) or a count ≥ 1.
    fn from_str(s: &str) -> Result<Self, String> {
        if s.eq_ignore_ascii_case("all") {
            return Ok(GpuCount::All);
        }
        match s.parse::<usize>() {
            Ok(n) if n >= 1 => Ok(GpuCount::Count(n)),
            _ => Err(format!("{s:?}: give a count >= 1 or `all`")),
        }
    }
}

/// The serialised form of [`GpuCount`]: a number or a word.
#[derive(Serialize, Deserialize)]
#[serde(untagged)]
enum GpuCountRepr {
    Count(usize),
    Word(String),
}

impl From<GpuCount> for GpuCountRepr {
    fn from(g: GpuCount) -> Self {
        match g {
            GpuCount::Count(n) => GpuCountRepr::Count(n),
            GpuCount::All => GpuCountRepr::Word("all".into()),
        }
    }
}

impl TryFrom<GpuCountRepr> for GpuCount {
    type Error = String;
    fn try_from(r: GpuCountRepr) -> Result<Self, String> {
        match r {
            GpuCountRepr::Count(n) => Ok(GpuCount::Count(n)),
            GpuCountRepr::Word(w) => w.parse(),
        }
    }
}

/// A setting of [`EncodeConfig`], named by its path (`masks.sam.encoder`) in [`ConfigError`]s;
/// a front end maps it to its own spelling (a command-line flag, a form field).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum Field {
    /// [`SceneConfig::dir`].
    SceneDir,
    /// [`ClipConfig::visual`].
    ClipVisual,
    /// [`OutputConfig::dir`].
    OutputDir,
    /// [`SamConfig::encoder`].
    SamEncoder,
    /// [`SamConfig::decoder`].
    SamDecoder,
    /// [`SamConfig::timing_encoder`].
    SamTimingEncoder,
    /// [`SamConfig::timing_decoder`].
    SamTimingDecoder,
    /// [`AggregateConfig::mixture_keep`].
    MixtureKeep,
    /// [`ExecutionConfig::gpus`].
    Gpus,
}

impl Field {
    /// The field's path in [`EncodeConfig`], e.g. `masks.sam.encoder`.
    pub fn path(self) -> &'static str {
        match self {
            Field::SceneDir => "scene.dir",
            Field::ClipVisual => "clip.visual",
            Field::OutputDir => "output.dir",
            Field::SamEncoder => "masks.sam.encoder",
            Field::SamDecoder => "masks.sam.decoder",
            Field::SamTimingEncoder => "masks.sam.timing_encoder",
            Field::SamTimingDecoder => "masks.sam.timing_decoder",
            Field::MixtureKeep => "aggregate.mixture_keep",
            Field::Gpus => "execution.gpus",
        }
    }
}

impl std::fmt::Display for Field {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.path())
    }
}

/// What a cluster encode cannot do ([`EncodeConfig::check_cluster`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum ClusterUnsupported {
    /// Per-level embeddings ([`AggregateConfig::levels`]).
    Levels,
}

/// An [`EncodeConfig`] that cannot run, found before anything is loaded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum ConfigError {
    /// A required setting is not set.
    #[error("{field} is not set: {}", missing_what(*field))]
    Missing {
        /// Which one.
        field: Field,
    },
    /// A count that must be at least 1 is 0.
    #[error("{field} is 0: it must be at least 1")]
    NotPositive {
        /// Which one.
        field: Field,
    },
    /// Per-level embeddings asked for with masks that have no granularity levels.
    #[error(
        "aggregate.levels needs masks with granularity levels (SAM's three multimask outputs): \
         use SAM masks (masks.source sam), or turn levels off"
    )]
    LevelsNeedSam,
    /// A setting a cluster encode cannot honour.
    #[error("{}", cluster_unsupported(*.0))]
    ClusterUnsupported(ClusterUnsupported),
    /// Neither embeddings form is asked for: the run would write no embeddings at all.
    #[error(
        "no embeddings output: aggregate.mixture_keep is none and output.dense is off; keep the \
         mixture (aggregate.mixture_keep S >= 1, the default) or ask for the dense file \
         (output.dense)"
    )]
    NoEmbeddingsOutput,
}

fn missing_what(field: Field) -> &'static str {
    match field {
        Field::SceneDir => {
            "the scene folder (point_cloud.ply, images/, sparse/0 or transforms.json)"
        }
        Field::ClipVisual => "the CLIP visual tower (ONNX)",
        Field::OutputDir => "the output folder",
        Field::SamEncoder | Field::SamDecoder => {
            "SAM masks need the SAM image encoder and prompt decoder (ONNX); or use graph masks"
        }
        Field::SamTimingEncoder | Field::SamTimingDecoder => {
            "a SAM timing model needs both its image encoder and its prompt decoder (ONNX)"
        }
        Field::MixtureKeep | Field::Gpus => "a positive count",
    }
}

fn cluster_unsupported(what: ClusterUnsupported) -> &'static str {
    match what {
        ClusterUnsupported::Levels => {
            "a cluster encode does not write per-level embeddings yet (aggregate.levels): write \
             them with a one-process encode"
        }
    }
}

impl From<ConfigError> for slag_common::Error {
    fn from(e: ConfigError) -> Self {
        slag_common::Error::Invalid(e.to_string())
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use std::path::Path;

    use super::*;

    fn graph_config() -> EncodeConfig {
        EncodeConfig {
            masks: MasksConfig::graph(),
            ..EncodeConfig::new("scene", "clip.onnx", "out")
        }
    }

    /// A cluster encode's settings: dense embeddings only.
    fn cluster_config() -> EncodeConfig {
        let mut c = graph_config();
        c.aggregate.mixture_keep = None;
        c.output.dense = true;
        c.scene.views.mode = crate::views::SelectionMode::All;
        c
    }

    #[test]
    fn defaults_are_the_command_lines() {
        let c = EncodeConfig::new("s", "c.onnx", "o");
        assert_eq!(c.masks.source, MaskSource::Sam);
        assert_eq!(c.masks.sam.points_per_side, 32);
        assert_eq!(c.masks.sam.pred_iou_thresh, 0.88);
        assert_eq!(c.raster.scale, 0.5);
        assert_eq!(c.raster.backend, RasterBackend::Gpu);
        assert_eq!(c.aggregate.overlap, MaskOverlap::Finest);
        assert_eq!(c.aggregate.contribution_memory_mb, 4096);
        assert_eq!(c.execution.ep, ExecutionProvider::Auto);
        assert_eq!(c.execution.gpus, GpuCount::Count(1));
        assert_eq!(c.output.precision, StoredPrecision::F16);
        assert!(c.output.progress);
        assert_eq!(c.scene.every, 1);
        assert_eq!(c.aggregate.mixture_keep, Some(DEFAULT_MIXTURE_KEEP));
        assert!(!c.output.dense, "the dense file is written only when asked");
        assert_eq!(c.ply(), Path::new("s/point_cloud.ply"));
    }

    #[test]
    fn json_round_trip_and_partial_files_take_defaults() {
        let mut c = graph_config();
        c.execution.gpus = GpuCount::All;
        c.aggregate.mixture_keep = Some(8);
        let text = serde_json::to_string(&c).unwrap();
        assert!(text.contains(r#""gpus":"all""#), "{text}");
        let back: EncodeConfig = serde_json::from_str(&text).unwrap();
        assert_eq!(back, c);
        let partial: EncodeConfig = serde_json::from_str(
            r#"{"scene": {"dir": "s"}, "clip": {"visual": "c.onnx"}, "output": {"dir": "o"},
                "masks": {"source": "graph"}, "execution": {"gpus": 2}}"#,
        )
        .unwrap();
        assert_eq!(partial.masks.source, MaskSource::Graph);
        assert_eq!(partial.execution.gpus, GpuCount::Count(2));
        assert_eq!(partial.raster, RasterConfig::default());
        assert!(partial.validate().is_ok());
        let typo = serde_json::from_str::<EncodeConfig>(r#"{"raster": {"scael": 1.0}}"#);
        assert!(typo.is_err(), "unknown fields are refused");
    }

    #[test]
    fn validation_names_the_field() {
        assert!(graph_config().validate().is_ok());
        let sam = EncodeConfig::new("s", "c.onnx", "o");
        assert_eq!(
            sam.validate(),
            Err(ConfigError::Missing {
                field: Field::SamEncoder
            })
        );
        let mut c = graph_config();
        c.aggregate.levels = true;
        assert_eq!(c.validate(), Err(ConfigError::LevelsNeedSam));
        let mut c = graph_config();
        c.aggregate.mixture_keep = Some(0);
        let e = c.validate().unwrap_err();
        assert!(e.to_string().contains("aggregate.mixture_keep"), "{e}");
        assert!(!e.to_string().contains("--"), "no flag names: {e}");
        let mut c = graph_config();
        c.aggregate.mixture_keep = None;
        assert_eq!(c.validate(), Err(ConfigError::NoEmbeddingsOutput));
        c.output.dense = true;
        assert!(c.validate().is_ok(), "the dense file alone is an output");
        let c = EncodeConfig {
            masks: MasksConfig::graph(),
            ..Default::default()
        };
        assert_eq!(
            c.validate(),
            Err(ConfigError::Missing {
                field: Field::SceneDir
            })
        );
    }

    /// Changes one setting.
    type Set = fn(&mut EncodeConfig);

    #[test]
    fn the_cluster_refuses_what_it_cannot_honour() {
        assert!(cluster_config().check_cluster().is_ok());
        assert!(
            graph_config().check_cluster().is_ok(),
            "the default outputs and views run on a cluster"
        );
        let workers: [Set; 3] = [
            |c| c.execution.gpus = GpuCount::Count(2),
            |c| c.execution.gpus = GpuCount::All,
            |c| c.execution.front_workers = Some(3),
        ];
        for set in workers {
            let mut c = cluster_config();
            set(&mut c);
            assert!(c.check_cluster().is_ok(), "{:?}", c.execution);
        }
        let mut c = cluster_config();
        c.aggregate.levels = true;
        assert_eq!(
            c.check_cluster(),
            Err(ConfigError::ClusterUnsupported(ClusterUnsupported::Levels))
        );
    }

    #[test]
    fn gpu_counts_parse() {
        assert_eq!("all".parse::<GpuCount>(), Ok(GpuCount::All));
        assert_eq!("ALL".parse::<GpuCount>(), Ok(GpuCount::All));
        assert_eq!("3".parse::<GpuCount>(), Ok(GpuCount::Count(3)));
        assert!("0".parse::<GpuCount>().is_err());
        assert!("x".parse::<GpuCount>().is_err());
        assert_eq!(format!("{:?}", GpuCount::Count(1)), "Count(1)");
    }
}
