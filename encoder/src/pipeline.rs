//! The encode pipeline: for each posed image, masks → CLIP crop embeddings → weight raster →
//! image-stage aggregation, then the reduction over all images and the output files.
//!
//! Two threads overlap the stages: the *front* thread decodes image i+1, generates its masks and
//! embeds its crops while the *back* thread rasterizes image i and computes its `a_kj`
//! (a bounded channel of depth 2 keeps memory flat). Every per-image step is independent, as in
//! the paper; only the reduction sees all images.
//!
//! [`Encoder`] runs a [`crate::config::EncodeConfig`]: [`build`] turns the config into the stage
//! instances (mask generators, front workers with their shared GPU models, rasterizers), the
//! [`EncodeParams`] and the report's header, and [`encode_pool`] runs them.

use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::Instant;

use image::RgbImage;
use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle};
use slag_common::camera::{self, Intrinsics, View, WorldToCamera};
use slag_common::embeddings::{EmbeddingsWriter, StoredPrecision, write_atomic};
use slag_common::scene::{self, Gaussians, PlyLoadOptions};
use slag_common::{Error, Result};

use crate::aggregate::{
    self, ContributionStore, ImageContribution, ImageStageParams, ReduceParams,
};
use crate::masks::compact::CompactMask;
use crate::masks::{Mask, MaskGenerator};
use crate::raster::WeightRasterizer;
pub use crate::report::WorkerShare;
use crate::report::{Counts, FormOutputs, ImageWork, LevelOutput, Outputs, Report, StageTimings};

pub mod build;
mod encoder;

pub use encoder::Encoder;

/// Embeds the masks of one image: one L2-normalised vector per mask (the paper's
/// `E_j = CLIP(crop_j(I ⊙ M_j))`).
pub trait CropEmbedder: Send {
    /// Model id recorded in the outputs (e.g. the ONNX file stem).
    fn model_id(&self) -> &str;
    /// Embedding width D.
    fn dim(&self) -> usize;
    /// `[masks.len()]` vectors of length [`CropEmbedder::dim`].
    fn embed(&mut self, image: &RgbImage, masks: &[Mask]) -> Result<Vec<Vec<f32>>>;
}

/// Where the scene comes from and what to encode.
#[derive(Debug, Clone)]
pub struct SceneInput {
    /// Scene folder with `images/` and `sparse/0` or `transforms.json`.
    pub dir: PathBuf,
    /// The `.ply` (default `<dir>/point_cloud.ply`).
    pub ply: PathBuf,
    /// Keep every N-th view (paper: 1:20 on large scenes).
    pub every: usize,
}

impl SceneInput {
    /// `dir` with the default `.ply` location.
    pub fn new(dir: &Path, ply: Option<&Path>, every: usize) -> Self {
        let ply = ply
            .map(Path::to_path_buf)
            .unwrap_or_else(|| dir.join("point_cloud.ply"));
        Self {
            dir: dir.to_path_buf(),
            ply,
            every,
        }
    }

    /// Loads the Gaussians (geometry only: the weights never need SH colours) and the views.
    pub fn load(&self) -> Result<(Gaussians, Vec<View>, usize)> {
        if !self.dir.is_dir() {
            return Err(Error::param(
                "scene",
                self.dir.display(),
                "an existing scene folder holding point_cloud.ply, images/ and sparse/0 or \
                 transforms.json",
            ));
        }
        let gaussians = scene::load_ply(&self.ply, PlyLoadOptions::default())?;
        let views = camera::load_views(&self.dir)?;
        let total = views.len();
        Ok((gaussians, camera::subsample(views, self.every), total))
    }
}

/// Parameters of one encode run besides the stage implementations.
#[derive(Debug, Clone)]
pub struct EncodeParams {
    /// Raster resolution relative to the images (`--raster-scale`, 0 < s ≤ 1 typical).
    pub raster_scale: f64,
    /// Image-stage knobs.
    pub image_stage: ImageStageParams,
    /// Reduction knobs.
    pub reduce: ReduceParams,
    /// Bytes of image contributions kept in memory before spilling to disk.
    pub contribution_budget_bytes: usize,
    /// Stored precision of the embeddings.
    pub precision: StoredPrecision,
    /// Output folder (`embeddings.safetensors`, `report.json`).
    pub out_dir: PathBuf,
    /// Show progress bars (stderr).
    pub progress: bool,
    /// Also write `<out>/mixture.safetensors`: the embeddings as a shared codebook of mask
    /// embeddings plus each Gaussian's `S` largest `a_kj` ([`aggregate::reduce_mixture`]);
    /// `None` = dense file only.
    pub mixture_keep: Option<usize>,
    /// Also write `<out>/embeddings-level{l}.safetensors` for each SAM granularity level `l`
    /// (0 subpart, 1 part, 2 whole; [`crate::levels`]): the same reduction over the `a_kj` of
    /// that level's masks only. Needs masks with levels (SAM).
    pub levels: bool,
}

/// One image after the front stages: its masks and mask embeddings (passed from the front to the
/// back thread of [`encode_pool`]; the map side of `distributed` uses it in place).
pub(crate) struct FrontItem {
    /// Index of the view in the scene's view list.
    pub view: usize,
    /// SAM (or graph) masks of the image, run-length encoded while the image waits between the
    /// stages ([`CompactMask`]; [`back_stage`] expands them right before the raster call).
    pub masks: Vec<CompactMask>,
    /// `[masks.len() * D]` CLIP crop embeddings `E_j`, row-major.
    pub embeddings: Vec<f32>,
    /// Seconds spent decoding the image.
    pub decode_s: f64,
    /// Seconds spent generating masks.
    pub masks_s: f64,
    /// Seconds spent embedding the crops.
    pub clip_s: f64,
}

impl FrontItem {
    /// Bytes the item holds (masks' runs and metadata, embeddings): what it costs while it
    /// waits in the queue between the stages.
    pub(crate) fn bytes(&self) -> usize {
        std::mem::size_of::<Self>()
            + self.masks.iter().map(CompactMask::bytes).sum::<usize>()
            + self.embeddings.capacity() * std::mem::size_of::<f32>()
    }
}

/// The front stages of `view` (number `index` of the scene's views): decode ([`read_image`]),
/// masks, CLIP crop embeddings.
///
/// Errors: those of the stages; [`Error::Internal`] when CLIP does not return one `dim`-wide
/// vector per mask.
pub(crate) fn front_stage(
    view: &View,
    index: usize,
    masks: &mut dyn MaskGenerator,
    crops: &mut dyn CropEmbedder,
    dim: usize,
) -> Result<FrontItem> {
    let t0 = Instant::now();
    let img = read_image(view)?;
    let t1 = Instant::now();
    let m = masks.generate(&img)?;
    let t2 = Instant::now();
    let e = crops.embed(&img, &m)?;
    let t3 = Instant::now();
    if e.len() != m.len() || e.iter().any(|v| v.len() != dim) {
        return Err(Error::internal(format!(
            "{}: CLIP returned {} vectors for {} masks",
            view.name,
            e.len(),
            m.len()
        )));
    }
    Ok(FrontItem {
        view: index,
        masks: crate::masks::compact::compact_all(&m),
        embeddings: e.concat(),
        decode_s: (t1 - t0).as_secs_f64(),
        masks_s: (t2 - t1).as_secs_f64(),
        clip_s: (t3 - t2).as_secs_f64(),
    })
}

/// One image after the back stages: its `a_kj` contribution and what producing it cost.
pub(crate) struct BackOut {
    /// The image's contribution to the reduction.
    pub contribution: ImageContribution,
    /// Seconds in the rasterizer (with GPU label sums: the pass and its readback).
    pub raster_s: f64,
    /// Seconds of the host side of the image stage ([`view_contribution`]).
    pub contribution_s: f64,
    /// Pixels the contributions were counted over (all, or those covered by a mask when the
    /// rasterizer summed per label; [`ViewStats`]).
    pub pixels: u64,
    /// `(pixel, Gaussian)` contributions over those pixels.
    pub raster_entries: u64,
    /// Whether the sums were made on the GPU ([`ViewStats::device_sums`]).
    pub device_sums: bool,
}

impl BackOut {
    /// This image's [`ImageWork`]: its front times (`decode_s`, `masks_s`, `clip_s`), its
    /// `n_masks` masks and `entries` non-zero `a_kj`, and the back stage's own measurements.
    pub(crate) fn work(
        &self,
        decode_s: f64,
        masks_s: f64,
        clip_s: f64,
        n_masks: usize,
        entries: usize,
    ) -> ImageWork {
        ImageWork {
            images: 1,
            decode_s,
            masks_s,
            clip_s,
            raster_s: self.raster_s,
            image_aggregate_s: self.contribution_s,
            masks: n_masks as u64,
            entries: entries as u64,
            raster_pixels: self.pixels,
            raster_entries: self.raster_entries,
            device_sum_views: u64::from(self.device_sums),
        }
    }
}

/// What [`view_contribution`] measured of one view.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ViewStats {
    /// Seconds in the rasterizer (with label sums: the GPU pass and its readback).
    pub raster_s: f64,
    /// Seconds in the host side of the image stage (labels, expansion, or the host sums).
    pub aggregate_s: f64,
    /// Raster pixels.
    pub pixels: usize,
    /// (pixel, Gaussian) contributions: all of them on the list path, those of pixels covered by
    /// a mask on the label-sum path.
    pub contributions: u64,
    /// Pixels the contributions were counted over (all, or the labelled ones).
    pub counted_pixels: usize,
    /// Whether the rasterizer summed per label on its device ([`WeightRasterizer::label_sums`]).
    pub device_sums: bool,
}

/// Raster + image stage of one view: the [`ImageContribution`] of `masks` (full resolution) and
/// their embeddings. Without `top_k_per_pixel` and with a rasterizer that sums per label on its
/// device (the GPU rasterizer), only the per-(Gaussian, label) sums leave the device (SLAG's
/// `a_kj = Σ_{p∈M_j} w_kp` with masks expanded from labels on the host); otherwise the per-pixel
/// lists are rasterized and summed by [`image_contribution`]. Both give the same `a_kj` up to
/// the device path's 2^-32 fixed point per weight.
///
/// Errors: as [`image_contribution`] and the rasterizer's.
pub fn view_contribution(
    rasterizer: &mut dyn WeightRasterizer,
    intrinsics: &Intrinsics,
    world_to_camera: &WorldToCamera,
    masks: &[Mask],
    mask_embeddings: Vec<f32>,
    dim: usize,
    params: ImageStageParams,
) -> Result<(ImageContribution, ViewStats)> {
    aggregate::image::check_image_inputs(masks, &mask_embeddings, dim)?;
    let pixels = intrinsics.width as usize * intrinsics.height as usize;
    if params.top_k_per_pixel.is_none() && !masks.is_empty() {
        let t0 = Instant::now();
        let mut labels = aggregate::pixel_labels(masks, intrinsics.width, intrinsics.height);
        if params.overlap == crate::levels::MaskOverlap::Finest {
            crate::levels::restrict_to_finest(&mut labels.masks_of, masks);
        }
        let t1 = Instant::now();
        if let Some(sums) = rasterizer.label_sums(intrinsics, world_to_camera, &labels.labels)? {
            let t2 = Instant::now();
            let mut entries = aggregate::image::expand_labels(
                sums.sums.iter().map(|e| (e.gaussian, e.label, e.weight())),
                &labels.masks_of,
            );
            aggregate::image::weight_entries(&mut entries, masks, params.mask_weighting);
            let stats = ViewStats {
                raster_s: (t2 - t1).as_secs_f64(),
                aggregate_s: (t1 - t0).as_secs_f64() + t2.elapsed().as_secs_f64(),
                pixels,
                contributions: sums.contributions,
                counted_pixels: labels.labels.iter().filter(|&&l| l != 0).count(),
                device_sums: true,
            };
            let c = ImageContribution {
                dim,
                mask_embeddings,
                entries,
            };
            return Ok((c, stats));
        }
    }
    let t0 = Instant::now();
    let weights = rasterizer.rasterize(intrinsics, world_to_camera)?;
    let t1 = Instant::now();
    let c = aggregate::image_contribution(&weights, masks, mask_embeddings, dim, params)?;
    let stats = ViewStats {
        raster_s: (t1 - t0).as_secs_f64(),
        aggregate_s: t1.elapsed().as_secs_f64(),
        pixels,
        contributions: weights.ids.len() as u64,
        counted_pixels: pixels,
        device_sums: false,
    };
    Ok((c, stats))
}

/// The back stages of a [`FrontItem`]: the image's `a_kj` from its view at `raster_intrinsics`
/// ([`view_contribution`]: GPU label sums, or weights then the host image stage).
///
/// Errors: those of the rasterizer and the image stage; [`Error::Internal`] for a view index out
/// of range of `views` or `raster_intrinsics` (an internal error).
pub(crate) fn back_stage(
    rasterizer: &mut dyn WeightRasterizer,
    views: &[View],
    raster_intrinsics: &[Intrinsics],
    item: FrontItem,
    dim: usize,
    image_stage: ImageStageParams,
) -> Result<BackOut> {
    let (Some(view), Some(k)) = (views.get(item.view), raster_intrinsics.get(item.view)) else {
        return Err(Error::internal(format!(
            "image {} has no view or raster intrinsics ({} views, {} intrinsics)",
            item.view,
            views.len(),
            raster_intrinsics.len()
        )));
    };
    let masks = crate::masks::compact::expand_all(&item.masks);
    let (contribution, vs) = view_contribution(
        rasterizer,
        k,
        &view.world_to_camera,
        &masks,
        item.embeddings,
        dim,
        image_stage,
    )?;
    Ok(BackOut {
        contribution,
        raster_s: vs.raster_s,
        contribution_s: vs.aggregate_s,
        pixels: vs.counted_pixels as u64,
        raster_entries: vs.contributions,
        device_sums: vs.device_sums,
    })
}

/// The error for a scene of which no view is left to encode: `every` skips them all
/// ([`Error::Param`] `every`), or the scene has none.
pub(crate) fn no_views(scene: &SceneInput, views_total: usize) -> Error {
    if views_total == 0 {
        Error::Invalid(format!("{}: the scene has no views", scene.dir.display()))
    } else {
        Error::param(
            "every",
            scene.every,
            format!("a step that keeps at least one of the scene's {views_total} views"),
        )
    }
}

/// Reads an image and checks it against the camera's intrinsics.
pub fn read_image(view: &View) -> Result<RgbImage> {
    // Pillow-exact JPEG decoding, so SAM/CLIP inputs match the Python reference pipeline.
    let img = crate::preprocess::load_rgb(&view.image_path)?;
    let (w, h) = (view.intrinsics.width, view.intrinsics.height);
    if img.dimensions() != (w, h) {
        return Err(Error::mismatch(
            slag_common::Mismatched::ImageSize,
            format!(
                "{} is {}x{} but its camera is {w}x{h}: images/ must hold the (undistorted) \
                 images the camera model describes",
                view.image_path.display(),
                img.width(),
                img.height()
            ),
        ));
    }
    Ok(img)
}

/// The rayon pool of back worker `g`: as many threads as the global pool (at least 2). Each
/// rasterizer alternates between its GPU passes and host work (binning sort, `a_kj` sums), one
/// image at a time; full pools let a host phase use the cores the other rasterizers leave idle
/// while they wait on their GPUs (a pool of `threads / GPUs` could stretch it). Measured: the
/// per-image back cost grows with the GPUs either way (4 H200s, quarter pools: raster +27 % over
/// 1 GPU; 2 H200s, full pools: +12 %), see docs/results/gpu-models.md. Idle rayon threads sleep, so the
/// extra threads cost no CPU. `None` (with a warning) when the
/// OS refuses the threads; the worker then uses the global pool, which is correct, only slower
/// under load.
fn back_pool(g: usize) -> Option<rayon::ThreadPool> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(rayon::current_num_threads().max(2))
        .thread_name(move |i| format!("slag-raster-{g}-{i}"))
        .build()
        .map_err(|e| {
            tracing::warn!(error = %e, "no rayon pool for rasterizer {g}; using the global pool")
        })
        .ok()
}

fn bar(multi: &MultiProgress, len: usize, label: &str) -> ProgressBar {
    let style =
        ProgressStyle::with_template("{prefix:>18} [{bar:30}] {pos}/{len} {per_sec} eta {eta}")
            .map(|s| s.progress_chars("=> "))
            .unwrap_or_else(|_| ProgressStyle::default_bar());
    multi.add(
        ProgressBar::new(len as u64)
            .with_style(style)
            .with_prefix(label.to_string()),
    )
}

/// Occupancy of the queues between the front and the back stages of [`encode_pool`]: images
/// handed over and not yet taken (a front waiting for a free slot counts: its image is held),
/// their bytes ([`FrontItem::bytes`]), and the high-water marks of both.
#[derive(Default)]
struct QueueGauge {
    items: std::sync::atomic::AtomicUsize,
    bytes: std::sync::atomic::AtomicUsize,
    high_items: std::sync::atomic::AtomicUsize,
    high_bytes: std::sync::atomic::AtomicUsize,
    largest_item: std::sync::atomic::AtomicUsize,
}

impl QueueGauge {
    /// An image of `bytes` is handed to a queue.
    fn enter(&self, bytes: usize) {
        use std::sync::atomic::Ordering::SeqCst;
        let n = self.items.fetch_add(1, SeqCst) + 1;
        self.high_items.fetch_max(n, SeqCst);
        let b = self.bytes.fetch_add(bytes, SeqCst) + bytes;
        self.high_bytes.fetch_max(b, SeqCst);
        self.largest_item.fetch_max(bytes, SeqCst);
    }

    /// An image of `bytes` left its queue (taken by a back worker, or never sent).
    fn leave(&self, bytes: usize) {
        use std::sync::atomic::Ordering::SeqCst;
        // Saturating: a leave can never outnumber its enter, but a gauge must not wrap.
        let _ = self
            .items
            .fetch_update(SeqCst, SeqCst, |v| Some(v.saturating_sub(1)));
        let _ = self
            .bytes
            .fetch_update(SeqCst, SeqCst, |v| Some(v.saturating_sub(bytes)));
    }

    /// The report's view of the gauge; `capacity` = the queues' slots together.
    fn stats(&self, capacity: usize) -> crate::report::QueueStats {
        use std::sync::atomic::Ordering::SeqCst;
        crate::report::QueueStats {
            capacity_items: capacity,
            high_water_bytes: self.high_bytes.load(SeqCst) as u64,
            high_water_items: self.high_items.load(SeqCst),
            largest_item_bytes: self.largest_item.load(SeqCst) as u64,
        }
    }
}

/// The stage instances of one *front* worker: a mask generator and a crop embedder (their own
/// ONNX Runtime sessions on the CPU, or handles to the sessions of their GPU). [`encode_pool`]
/// runs one thread per entry.
pub struct FrontStages {
    /// SAM (or graph) masks of one image.
    pub masks: Box<dyn MaskGenerator>,
    /// CLIP embeddings of the masks' crops.
    pub crops: Box<dyn CropEmbedder>,
    /// The GPU whose models this worker uses, if any: its images then go to that GPU's
    /// rasterizer (rasterizer `gpu`), so one pipeline's SAM, CLIP and raster share a GPU.
    /// `None`: any rasterizer takes them.
    pub gpu: Option<usize>,
}

impl FrontStages {
    /// A worker bound to no GPU.
    pub fn new(masks: Box<dyn MaskGenerator>, crops: Box<dyn CropEmbedder>) -> Self {
        FrontStages {
            masks,
            crops,
            gpu: None,
        }
    }
}

/// Runs the whole Semantic Embedding stage on `scene` and writes
/// `<out>/embeddings.safetensors` (+ `<out>/mixture.safetensors` with
/// [`EncodeParams::mixture_keep`]) + `<out>/report.json` (each atomically; the report last, so a
/// report's presence means the run completed).
///
/// One front worker and one rasterizer: [`encode_pool`] with a single worker on each side.
pub fn encode(
    scene: &SceneInput,
    masks: Box<dyn MaskGenerator>,
    crops: Box<dyn CropEmbedder>,
    make_rasterizer: impl FnOnce(&Gaussians) -> Result<Box<dyn WeightRasterizer>>,
    params: &EncodeParams,
    report: Report,
) -> Result<Report> {
    encode_pool(
        scene,
        vec![FrontStages::new(masks, crops)],
        |g: &Gaussians| Ok(vec![make_rasterizer(g)?]),
        params,
        report,
    )
}

/// The encode pipeline over a pool of workers: `fronts.len()` front threads (decode → masks →
/// CLIP crops, on the CPU / ONNX Runtime) and one back thread per rasterizer returned by
/// `make_rasterizers` (one per GPU: raster → `a_kj`), then one reduction over all images.
///
/// Scheduling is dynamic at both ends: front workers take the next unclaimed view from a shared
/// counter, and back workers take the next finished front item from one bounded queue (depth
/// 2 × rasterizers), so an image with many masks or a slow GPU holds up only its own worker
/// (the paper saw large stragglers with a static split). The per-image contributions of all
/// workers go to one [`ContributionStore`]; the reduction (`E_k`, f64) runs once at the end, so
/// the result equals a one-worker run up to the f64 summation order.
///
/// Errors: the first error of any worker stops the others (no output is written); otherwise as
/// [`encode`]. All fronts must embed with the same model (same `model_id` and `dim`).
pub fn encode_pool(
    scene: &SceneInput,
    fronts: Vec<FrontStages>,
    make_rasterizers: impl FnOnce(&Gaussians) -> Result<Vec<Box<dyn WeightRasterizer>>>,
    params: &EncodeParams,
    mut report: Report,
) -> Result<Report> {
    use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
    use std::sync::{Arc, Mutex};

    let t_total = Instant::now();
    let mut t = StageTimings::default();
    let Some(first) = fronts.first() else {
        return Err(Error::param("fronts", 0, "at least one front worker"));
    };
    let dim = first.crops.dim();
    let model_id = first.crops.model_id().to_string();
    let mask_name = first.masks.name().to_string();
    if let Some(f) = fronts
        .iter()
        .find(|f| f.crops.dim() != dim || f.crops.model_id() != model_id)
    {
        return Err(Error::mismatch(
            slag_common::Mismatched::EmbeddingWidth,
            format!(
                "front workers embed with different models ({model_id}, D={dim} vs {}, D={})",
                f.crops.model_id(),
                f.crops.dim()
            ),
        ));
    }
    let t0 = Instant::now();
    let (gaussians, views, views_total) = scene.load()?;
    t.load_scene = t0.elapsed().as_secs_f64();
    if views.is_empty() {
        return Err(no_views(scene, views_total));
    }
    // Raster intrinsics of every view, checked (scale range, raster size) before any image work.
    let raster_intrinsics = views
        .iter()
        .map(|v| crate::raster::raster_intrinsics(&v.intrinsics, params.raster_scale))
        .collect::<Result<Vec<_>>>()?;
    tracing::info!(
        gaussians = gaussians.len(),
        views = views.len(),
        fronts = fronts.len(),
        "scene loaded"
    );
    let n_fronts = fronts.len();
    let multi = MultiProgress::with_draw_target(if params.progress {
        ProgressDrawTarget::stderr()
    } else {
        ProgressDrawTarget::hidden()
    });
    let bar_front = bar(&multi, views.len(), "masks + CLIP");
    let bar_back = bar(&multi, views.len(), "raster + a_kj");
    let spill_dir = params.out_dir.join(".contributions.partial");
    let store = Mutex::new(ContributionStore::new(
        params.contribution_budget_bytes,
        spill_dir,
    ));
    // One more store per granularity level with `levels` (the same entries, split by level).
    let level_stores: Vec<Mutex<ContributionStore>> = if params.levels {
        (0..crate::levels::LEVELS)
            .map(|l| {
                Mutex::new(ContributionStore::new(
                    params.contribution_budget_bytes,
                    params
                        .out_dir
                        .join(format!(".contributions-level{l}.partial")),
                ))
            })
            .collect()
    } else {
        Vec::new()
    };
    let mut counts = Counts {
        views_total,
        views_used: views.len(),
        gaussians: gaussians.len(),
        ..Default::default()
    };

    // What the back workers add up (under one lock, once per image).
    let totals = Mutex::new(ImageWork::default());
    let next_view = AtomicUsize::new(0);
    let failed = AtomicBool::new(false);
    let first_error: Mutex<Option<Error>> = Mutex::new(None);
    let fail = |e: Error| {
        failed.store(true, Ordering::SeqCst);
        if let Ok(mut slot) = first_error.lock() {
            slot.get_or_insert(e);
        }
    };
    // One queue for all rasterizers, or, when the fronts are bound to GPUs, one queue per GPU so
    // an image stays on the GPU whose SAM and CLIP made its masks. Each queue holds two finished
    // images per rasterizer it feeds (the unbound fronts' queue: two per front, at most 8).
    let bound_gpus = fronts.iter().filter_map(|f| f.gpu).max().map(|g| g + 1);
    let (n_queues, capacity) = match bound_gpus {
        Some(n) => (n, 2),
        None => (1, (2 * fronts.len()).clamp(2, 8)),
    };
    let mut txs = Vec::with_capacity(n_queues);
    let mut rxs = Vec::with_capacity(n_queues);
    for _ in 0..n_queues {
        let (tx, rx) = mpsc::sync_channel::<FrontItem>(capacity);
        txs.push(tx);
        rxs.push(Arc::new(Mutex::new(rx)));
    }
    let mut shares: Vec<WorkerShare> = Vec::new();
    let mut raster_names: Vec<String> = Vec::new();
    // What waits between the stages: images handed to a queue (a front blocked on a full queue
    // included) and not yet taken by a back worker, and their bytes.
    let queue = QueueGauge::default();

    // The fronts start first; the rasterizers are set up (device, upload of the Gaussians) while
    // the first images go through SAM and CLIP, so that set-up is off the critical path.
    std::thread::scope(|s| {
        let mut handles = Vec::new();
        for (w, mut front) in fronts.into_iter().enumerate() {
            let tx = txs[front.gpu.unwrap_or(0) % n_queues].clone();
            let (views, next_view, failed, fail, bar_front, queue) =
                (&views, &next_view, &failed, &fail, &bar_front, &queue);
            handles.push(s.spawn(move || {
                let mut share = WorkerShare {
                    name: format!("front-{w}"),
                    ..Default::default()
                };
                while !failed.load(Ordering::SeqCst) {
                    let i = next_view.fetch_add(1, Ordering::SeqCst);
                    let Some(view) = views.get(i) else { break };
                    let t0 = Instant::now();
                    if share.images == 0 {
                        share.first_s = (t0 - t_total).as_secs_f64();
                    }
                    let item = front_stage(view, i, &mut *front.masks, &mut *front.crops, dim);
                    share.busy_s += t0.elapsed().as_secs_f64();
                    share.last_s = t_total.elapsed().as_secs_f64();
                    bar_front.inc(1);
                    match item {
                        Ok(item) => {
                            share.images += 1;
                            let bytes = item.bytes();
                            queue.enter(bytes);
                            if tx.send(item).is_err() {
                                queue.leave(bytes);
                                break;
                            }
                        }
                        Err(e) => {
                            fail(e);
                            break;
                        }
                    }
                }
                share
            }));
        }
        // The back workers hold the only receivers: when every front is done, the queue closes.
        drop(txs);
        let rasterizers = match make_rasterizers(&gaussians) {
            Ok(r) if r.is_empty() => {
                fail(Error::param("rasterizers", 0, "at least one rasterizer"));
                Vec::new()
            }
            Ok(r) if r.len() < bound_gpus.unwrap_or(1) => {
                fail(Error::internal(format!(
                    "front workers are bound to {} GPUs but there are {} rasterizers",
                    bound_gpus.unwrap_or(1),
                    r.len()
                )));
                Vec::new()
            }
            Ok(r) => r,
            Err(e) => {
                fail(e);
                Vec::new()
            }
        };
        raster_names = rasterizers.iter().map(|r| r.name().to_string()).collect();
        for (g, mut rasterizer) in rasterizers.into_iter().enumerate() {
            let rx = Arc::clone(&rxs[g % n_queues]);
            let name = format!("raster-{g} {}", raster_names[g]);
            let (views, raster_intrinsics, failed, fail, bar_back, store, totals) = (
                &views,
                &raster_intrinsics,
                &failed,
                &fail,
                &bar_back,
                &store,
                &totals,
            );
            let (level_stores, queue) = (&level_stores, &queue);
            handles.push(s.spawn(move || {
                let mut share = WorkerShare {
                    name,
                    ..Default::default()
                };
                // Each rasterizer's host work (binning sort, readback, a_kj sums) runs on a rayon
                // pool of its own, so that it never queues behind the front workers' jobs (SAM
                // post-processing, crops) in the global pool: the back is the pipeline's
                // critical path.
                let pool = back_pool(g);
                let mut run = || loop {
                    // Take the next finished front item; the lock is held only while waiting.
                    let item = match rx.lock() {
                        Ok(rx) => rx.recv(),
                        Err(_) => break,
                    };
                    let Ok(item) = item else { break };
                    queue.leave(item.bytes());
                    if failed.load(Ordering::SeqCst) {
                        break;
                    }
                    let t0 = Instant::now();
                    if share.images == 0 {
                        share.first_s = (t0 - t_total).as_secs_f64();
                    }
                    let res = (|| -> Result<()> {
                        let (view, n_masks) = (item.view, item.masks.len());
                        let (decode_s, masks_s, clip_s) =
                            (item.decode_s, item.masks_s, item.clip_s);
                        let mask_levels: Vec<Option<u8>> =
                            item.masks.iter().map(|m| m.level).collect();
                        let out = back_stage(
                            &mut *rasterizer,
                            views,
                            raster_intrinsics,
                            item,
                            dim,
                            params.image_stage,
                        )?;
                        if let Some(p) = rasterizer.last_phases() {
                            share.raster_phases_ms.get_or_insert_default().add(&p);
                        }
                        let t1 = Instant::now();
                        let entries = out.contribution.entries.len();
                        let mut work = out.work(decode_s, masks_s, clip_s, n_masks, entries);
                        if !level_stores.is_empty() {
                            let parts =
                                crate::levels::split_by_level(&out.contribution, &mask_levels)?;
                            for (part, ls) in parts.into_iter().zip(level_stores) {
                                ls.lock()
                                    .map_err(|_| {
                                        Error::internal(
                                            "contribution store poisoned by a panicked worker",
                                        )
                                    })?
                                    .push(part)?;
                            }
                        }
                        store
                            .lock()
                            .map_err(|_| {
                                Error::internal("contribution store poisoned by a panicked worker")
                            })?
                            .push(out.contribution)?;
                        let push_s = t1.elapsed().as_secs_f64();
                        work.image_aggregate_s += push_s;
                        if let Ok(mut tt) = totals.lock() {
                            tt.add(&work);
                        }
                        if let Some(view) = views.get(view) {
                            tracing::debug!(view = %view.name, masks = n_masks, "image done");
                        }
                        Ok(())
                    })();
                    share.busy_s += t0.elapsed().as_secs_f64();
                    bar_back.inc(1);
                    share.last_s = t_total.elapsed().as_secs_f64();
                    match res {
                        Ok(()) => share.images += 1,
                        Err(e) => {
                            fail(e);
                            break;
                        }
                    }
                };
                match &pool {
                    Some(pool) => pool.install(run),
                    None => run(),
                }
                share
            }));
        }
        // Without rasterizers (their set-up failed) the fronts see the queues close and stop.
        drop(rxs);
        for h in handles {
            match h.join() {
                Ok(share) => shares.push(share),
                Err(_) => fail(Error::internal("an encode worker thread panicked")),
            }
        }
    });
    if let Some(e) = first_error.into_inner().ok().flatten() {
        return Err(e);
    }
    let models = &mut report.models;
    models.rasterizer = raster_names.first().cloned().unwrap_or_default();
    models.rasterizers = Some(raster_names.clone());
    models.front_workers = Some(n_fronts);
    models.clip_model_id = model_id.clone();
    models.masks = mask_name;
    let store = store
        .into_inner()
        .map_err(|_| Error::internal("contribution store poisoned by a panicked worker"))?;
    let tt = totals.into_inner().unwrap_or_default();
    if store.len() != views.len() {
        return Err(Error::internal(format!(
            "only {} of {} images reached the reduction",
            store.len(),
            views.len()
        )));
    }
    tt.fill(&mut t, &mut counts);
    report.workers = shares;
    bar_front.finish();
    bar_back.finish();

    let emb_path = params.out_dir.join("embeddings.safetensors");
    let report_path = params.out_dir.join("report.json");
    // A stale report from an earlier run must not vouch for the new embeddings while they are written.
    if report_path.exists() {
        std::fs::remove_file(&report_path).map_err(|e| Error::io(&report_path, e))?;
    }
    // The reduction streams chunk by chunk into the file: the [N, D] matrix is never in memory.
    let t0 = Instant::now();
    let writer = EmbeddingsWriter::create(&emb_path, dim, params.precision)?;
    let aggregate::Streamed {
        chunks,
        writer,
        reduce_s,
    } = aggregate::reduce_to_writer(&store, &gaussians.means, dim, params.reduce, writer)?;
    let write_tail_s = t0.elapsed().as_secs_f64() - reduce_s;
    t.reduce = reduce_s;
    counts.spilled_images = store.spilled();
    counts.reduce_chunks = chunks;
    counts.observed = writer.len();
    counts.observed_fraction = writer.len() as f64 / gaussians.len().max(1) as f64;
    // The compressed form (shared codebook of mask embeddings + top-S weights), if asked for.
    let t0 = Instant::now();
    let mixture = params
        .mixture_keep
        .map(|keep| {
            let (n, p) = (gaussians.len(), params.reduce);
            aggregate::reduce_mixture(&store, n, dim, p, keep, &model_id, &gaussians.means)
        })
        .transpose()?;
    let mixture_s = t0.elapsed().as_secs_f64();
    drop(store);
    // Granularity kept apart: one ordinary embeddings file per level.
    let t0 = Instant::now();
    let mut level_files = Vec::new();
    for l in 0..crate::levels::LEVELS {
        let path = params
            .out_dir
            .join(format!("embeddings-level{l}.safetensors"));
        match level_stores.get(l) {
            Some(ls) => {
                let ls = ls.lock().map_err(|_| {
                    Error::internal("contribution store poisoned by a panicked worker")
                })?;
                let w = EmbeddingsWriter::create(&path, dim, params.precision)?;
                let streamed =
                    aggregate::reduce_to_writer(&ls, &gaussians.means, dim, params.reduce, w)?;
                let rows = streamed.writer.len();
                streamed.writer.finish(
                    &model_id,
                    gaussians.len() as u64,
                    &scene.ply.display().to_string(),
                )?;
                let bytes = std::fs::metadata(&path).map(|m| m.len()).unwrap_or(0);
                level_files.push(LevelOutput {
                    bytes,
                    level: l,
                    observed: rows,
                    path,
                });
            }
            // Level files of an earlier run must not sit beside this run's report.
            None if path.exists() => {
                std::fs::remove_file(&path).map_err(|e| Error::io(&path, e))?
            }
            None => {}
        }
    }
    drop(level_stores);
    let levels_s = t0.elapsed().as_secs_f64();

    let t0 = Instant::now();
    writer.finish(
        &model_id,
        gaussians.len() as u64,
        &scene.ply.display().to_string(),
    )?;
    let mix_path = params.out_dir.join("mixture.safetensors");
    match &mixture {
        Some(m) => m.write(&mix_path)?,
        // A mixture of an earlier run must not sit beside this run's report.
        None if mix_path.exists() => {
            std::fs::remove_file(&mix_path).map_err(|e| Error::io(&mix_path, e))?
        }
        None => {}
    }
    t.write = write_tail_s + t0.elapsed().as_secs_f64();
    t.total = t_total.elapsed().as_secs_f64();
    let emb_bytes = std::fs::metadata(&emb_path).map(|m| m.len()).unwrap_or(0);
    counts.peak_rss_bytes = crate::report::peak_rss_bytes();
    counts.queue = Some(queue.stats(n_queues * capacity));
    report.timings = t;
    report.counts = counts;
    let has_levels = !level_files.is_empty();
    report.outputs = Outputs {
        cluster: None,
        embeddings: emb_path,
        embeddings_bytes: emb_bytes,
        forms: Some(FormOutputs {
            levels: has_levels.then_some(level_files),
            levels_reduce_s: has_levels.then_some(levels_s),
            mixture: mixture.as_ref().map(|_| mix_path),
            mixture_bytes_per_gaussian: mixture.as_ref().map(|m| m.bytes_per_gaussian()),
            mixture_codebook_rows: mixture.as_ref().map(|m| m.codebook_len()),
            mixture_keep: mixture.as_ref().map(|m| m.keep),
            mixture_reduce_s: mixture.as_ref().map(|_| mixture_s),
        }),
        precision: params.precision,
        report: report_path.clone(),
    };
    let json =
        serde_json::to_vec_pretty(&report).map_err(|e| Error::internal(format!("report: {e}")))?;
    write_atomic(&report_path, &json)?;
    Ok(report)
}

impl CropEmbedder for crate::clip::ClipHandle {
    fn model_id(&self) -> &str {
        crate::clip::ClipHandle::model_id(self)
    }
    fn dim(&self) -> usize {
        crate::clip::ClipHandle::dim(self)
    }
    fn embed(&mut self, image: &RgbImage, masks: &[Mask]) -> Result<Vec<Vec<f32>>> {
        self.embed_masks(image, masks)
    }
}

impl CropEmbedder for crate::clip::ClipVisual {
    fn model_id(&self) -> &str {
        crate::clip::ClipVisual::model_id(self)
    }
    fn dim(&self) -> usize {
        crate::clip::ClipVisual::dim(self)
    }
    fn embed(&mut self, image: &RgbImage, masks: &[Mask]) -> Result<Vec<Vec<f32>>> {
        self.embed_masks(image, masks)
    }
}
