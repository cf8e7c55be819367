//! The encode pipeline: for each posed image, masks → CLIP crop embeddings → weight raster →
//! image-stage aggregation, then the reduction over all images and the output files.
//!
//! Threads overlap the stages: a *front* thread decodes image i+3, generates its masks and
//! embeds its crops while a rasterizer's *prepare* thread labels image i+2's pixels, its *raster*
//! thread rasterizes image i+1 and its *image* thread turns image i's label sums into its `a_kj`
//! (bounded channels between them keep memory flat). Every per-image step is independent, as in
//! the paper; only the reduction sees all images.
//!
//! [`Encoder`] runs a [`crate::config::EncodeConfig`]: [`build`] turns the config into the stage
//! instances (mask generators, front workers with their shared GPU models, rasterizers), the
//! [`EncodeParams`] and the report's header, and [`encode_pool`] runs them: the worker pool
//! (`pool`: fronts, queues, the first error), then the finish (`finish`: the reduction, the
//! level and mixture files, the writes, the report last). This file holds the per-image stages
//! both encoders share (`front_stage`; the back stage: `back_prepare`, `back_raster`,
//! `back_finish`; [`view_contribution`]).

use std::path::{Path, PathBuf};
use std::time::Instant;

use image::RgbImage;
use slag_common::camera::{self, Intrinsics, View, WorldToCamera};
use slag_common::embeddings::StoredPrecision;
use slag_common::scene::{self, Gaussians, PlyLoadOptions};
use slag_common::{Error, Result};

use crate::aggregate::ImageMask;
use crate::aggregate::{self, ImageContribution, ImageStageParams, ReduceParams};
use crate::masks::compact::CompactMask;
use crate::masks::{Mask, MaskGenerator};
use crate::raster::WeightRasterizer;
pub use crate::report::WorkerShare;
use crate::report::{ImageWork, Report};

pub mod budget;
pub mod build;
mod encoder;
mod fallback;
pub(crate) mod feed;
pub(crate) mod handed;
pub(crate) mod devices;
pub(crate) mod finish;
pub(crate) mod pool;
mod reduction;
pub(crate) mod scene_load;
pub(crate) mod segment_task;
pub(crate) mod sinks;

pub use encoder::Encoder;
pub(crate) use encoder::finish_with_segments;
pub use pool::FrontStages;

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
    /// Hold out the views with index ≡ ⌊N/2⌋ (mod N) for the 2D held-out protocol
    /// ([`crate::views::training_indices`]); `None`: none.
    pub hold_out_every: Option<usize>,
    /// Which training views are encoded ([`crate::views::choose`], run by the encode).
    pub selection: crate::views::ViewSelection,
}

/// A scene folder's `.ply`: `ply` when given, else `<dir>/point_cloud.ply` (the INRIA layout).
pub fn scene_ply(dir: &Path, ply: Option<&Path>) -> PathBuf {
    ply.map(Path::to_path_buf)
        .unwrap_or_else(|| dir.join("point_cloud.ply"))
}

impl SceneInput {
    /// `dir` with the default `.ply` location ([`scene_ply`]), every training view encoded
    /// ([`crate::views::SelectionMode::All`]; an encode from an [`crate::config::EncodeConfig`]
    /// takes its selection, coverage by default).
    pub fn new(dir: &Path, ply: Option<&Path>, every: usize) -> Self {
        Self {
            dir: dir.to_path_buf(),
            ply: scene_ply(dir, ply),
            every,
            hold_out_every: None,
            selection: crate::views::ViewSelection {
                mode: crate::views::SelectionMode::All,
                ..Default::default()
            },
        }
    }

    /// Loads the Gaussians (geometry only: the weights never need SH colours), the training
    /// views (name-sorted: [`SceneInput::every`] and [`SceneInput::hold_out_every`] applied,
    /// [`crate::views::training_views`]) and the scene's view count.
    ///
    /// Errors: no scene folder ([`Error::Param`] `scene`), unreadable `.ply` or cameras, as
    /// [`crate::views::training_indices`].
    pub fn load(&self) -> Result<(Gaussians, Vec<View>, usize)> {
        self.check_dir()?;
        let gaussians = scene::load_ply(&self.ply, PlyLoadOptions::default())?;
        let (training, total) = self.load_views()?;
        Ok((gaussians, training, total))
    }

    /// [`SceneInput::load`] for the encode's pool, its Gaussians from `shared` (the load the
    /// segments share, [`scene_load::SceneLoad`]) when given, else loaded here; the same checks
    /// in the same order. Returns the Gaussians (shared with the segments when they run), the
    /// training views, the scene's view count and the seconds spent reading the `.ply` and the
    /// cameras (the `.ply`'s own load, not the wait for a shared one).
    ///
    /// Errors: as [`SceneInput::load`].
    pub(crate) fn load_sharing(
        &self,
        shared: Option<scene_load::SceneLoad>,
    ) -> Result<(std::sync::Arc<Gaussians>, Vec<View>, usize, f64)> {
        let t0 = Instant::now();
        self.check_dir()?;
        let (gaussians, ply_s) = match shared {
            Some(load) => {
                let waited = Instant::now();
                let l = load.wait()?;
                (l.gaussians, l.seconds - waited.elapsed().as_secs_f64())
            }
            None => {
                let g = scene::load_ply(&self.ply, PlyLoadOptions::default())?;
                (std::sync::Arc::new(g), 0.0)
            }
        };
        let (training, views_total) = self.load_views()?;
        let seconds = t0.elapsed().as_secs_f64() + ply_s;
        Ok((gaussians, training, views_total, seconds))
    }

    /// Errors: no scene folder ([`Error::Param`] `scene`).
    fn check_dir(&self) -> Result<()> {
        if self.dir.is_dir() {
            return Ok(());
        }
        Err(Error::param(
            "scene",
            self.dir.display(),
            "an existing scene folder holding point_cloud.ply, images/ and sparse/0 or \
             transforms.json",
        ))
    }

    /// The training views and the scene's view count ([`SceneInput::load`]).
    fn load_views(&self) -> Result<(Vec<View>, usize)> {
        let views = camera::load_views(&self.dir)?;
        let total = views.len();
        let training = crate::views::training_views(views, self.every, self.hold_out_every)?;
        Ok((training, total))
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
    /// Output folder (`mixture.safetensors`, `report.json`; with [`EncodeParams::dense`]
    /// `embeddings.safetensors`).
    pub out_dir: PathBuf,
    /// Write the dense embeddings `<out>/embeddings.safetensors`; off: only the mixture form
    /// (then [`EncodeParams::mixture_keep`] must be set), and no dense row is ever made.
    pub dense: bool,
    /// Show progress bars (stderr).
    pub progress: bool,
    /// Also write `<out>/mixture.safetensors`: the embeddings as a shared codebook of mask
    /// embeddings plus each Gaussian's `S` largest `a_kj` ([`aggregate::reduce_mixture`]);
    /// `None` = dense file only (needs [`EncodeParams::dense`]).
    pub mixture_keep: Option<usize>,
    /// Also write `<out>/embeddings-level{l}.safetensors` for each SAM granularity level `l`
    /// (0 subpart, 1 part, 2 whole; [`crate::levels`]): the same reduction over the `a_kj` of
    /// that level's masks only. Needs masks with levels (SAM).
    pub levels: bool,
    /// Keep the masks' record ([`slag_common::mask_record`]) with this many views per Gaussian
    /// (the segmentation's mask term; 8 bytes per slot and Gaussian); `None`: not kept.
    pub mask_record_slots: Option<usize>,
    /// Where the reduction runs ([`crate::config::ReduceOn`]).
    pub reduce_on: crate::config::ReduceOn,
    /// Device memory the label sums kept for the device reduction may take, bytes
    /// ([`budget::device_reduce_budget`]).
    pub device_reduce_budget_bytes: u64,
}

/// One image after the front stages: its masks and mask embeddings (passed from the front to the
/// back thread of [`encode_pool`]; the map side of `distributed` uses it in place).
pub(crate) struct FrontItem {
    /// Index of the view in the scene's view list.
    pub view: usize,
    /// SAM (or graph) masks of the image, run-length encoded while the image waits between the
    /// stages ([`CompactMask`]; [`back_prepare`] labels them from their runs and [`back_finish`]
    /// expands them only for the per-pixel lists).
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
    /// The image's contribution to the reduction (empty when its sums stayed on the device).
    pub contribution: ImageContribution,
    /// When the sums stayed on the device: each Gaussian's dominant mask of the view, for the
    /// masks' record.
    pub dominant: Option<Vec<(u32, u32, f32)>>,
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
/// Its three parts, [`prepare_view`] (the labels), [`raster_view`] (the rasterizer's) and
/// [`finish_view`] (the reduction and expansion), run one after the other here; the encoder runs
/// them on three threads per rasterizer, so that the rasterizer never waits for host work.
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
    let prepared = prepare_view(intrinsics, world_to_camera, masks, params, None);
    let r = raster_view(rasterizer, intrinsics, world_to_camera, prepared, None)?;
    finish_view(r, masks, mask_embeddings, dim, params).map(|(c, _, stats)| (c, stats))
}

/// What a rasterizer made of one view ([`raster_view`]), for the host side of its image stage
/// ([`finish_view`]).
pub(crate) struct RasteredView {
    out: Rastered,
    stats: ViewStats,
    /// The device memory limit on which the view's sums went the host's way instead of being
    /// kept ([`KeepView::fall_back`]); the views kept before stay kept.
    gave_up_keeping: Option<Error>,
}

enum Rastered {
    /// The device's per-(Gaussian, label) sums, the labels' masks and the masks' weighting
    /// factors ([`aggregate::image::mask_factors`]).
    Sums {
        sums: crate::raster::LabelSums,
        masks_of: Vec<Vec<u32>>,
        factors: Vec<f32>,
    },
    /// Per-pixel lists, for [`image_contribution`].
    Weights(crate::raster::PixelWeights),
    /// The sums stayed on the device for the device reduction
    /// ([`WeightRasterizer::label_sums_kept`]); with the masks' record, each Gaussian's dominant
    /// mask of the view.
    Kept { dominant: Vec<(u32, u32, f32)> },
}

/// Each Gaussian's dominant mask of one view, `(Gaussian, mask, a_kj)`, Gaussians ascending
/// (the masks' record's input).
pub(crate) type DominantMasks = Vec<(u32, u32, f32)>;

/// How the views are offered to the device reduction ([`back_raster`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Keep {
    /// The masks' record wants each Gaussian's dominant mask.
    pub(crate) dominant: bool,
    /// A device memory limit on keeping a view ([`Error::Limit`] `GpuMemory`: the kept sums'
    /// budget, or the device full with them) sends the view the host's way instead of failing
    /// (`--reduce auto`).
    pub(crate) fall_back: bool,
}

/// The device reduction's inputs of a view ([`raster_view`]): its mask embeddings and how it
/// is offered ([`Keep`]).
#[derive(Clone, Copy)]
pub(crate) struct KeepView<'a> {
    pub(crate) embeddings: &'a [f32],
    pub(crate) keep: Keep,
    /// The view's index in the encode's view list.
    pub(crate) view: usize,
}

/// Whether `e` is a device memory limit ([`Keep::fall_back`]).
fn is_device_memory(e: &Error) -> bool {
    matches!(
        e,
        Error::Limit {
            resource: slag_common::Resource::GpuMemory,
            ..
        }
    )
}

/// The pixel labels of one view and what the image stage needs of its masks afterwards, made
/// before the view reaches its rasterizer ([`prepare_view`]).
pub(crate) struct PreparedView {
    /// `None`: the per-pixel lists are needed (`top_k_per_pixel`, or no masks).
    labels: Option<aggregate::PixelLabels>,
    /// The rasterizer's host work of the view, done ahead ([`WeightRasterizer::view_precompute`]).
    precomputed: Option<crate::raster::PrecomputedView>,
    /// [`aggregate::image::mask_factors`] of the masks, with labels (empty without).
    factors: Vec<f32>,
    /// Seconds the labels took.
    labels_s: f64,
}

/// The first, host-only part of [`view_contribution`]: the pixel labels of `masks` at the raster
/// size of `intrinsics`, unless `top_k_per_pixel` needs the per-pixel lists, and with labels the
/// rasterizer's own host work of the view (`precompute`, [`WeightRasterizer::view_precompute`]).
pub(crate) fn prepare_view<M: ImageMask>(
    intrinsics: &Intrinsics,
    world_to_camera: &WorldToCamera,
    masks: &[M],
    params: ImageStageParams,
    precompute: Option<&dyn crate::raster::ViewPrecompute>,
) -> PreparedView {
    let t0 = Instant::now();
    // Labels of equal mask sets merged: integer sums on the device, so the a_kj are the same.
    let labels = (params.top_k_per_pixel.is_none() && !masks.is_empty()).then(|| {
        aggregate::stage_labels(masks, intrinsics.width, intrinsics.height, params).merged()
    });
    let precomputed = labels
        .as_ref()
        .and(precompute)
        .map(|p| p.precompute(world_to_camera));
    // Only the label sums read the factors here; the per-pixel lists' image stage makes its own.
    let factors = match labels {
        Some(_) => aggregate::image::mask_factors(masks, params.mask_weighting),
        None => Vec::new(),
    };
    PreparedView {
        labels,
        precomputed,
        factors,
        labels_s: t0.elapsed().as_secs_f64(),
    }
}

/// The rasterizer's part of [`view_contribution`]: the device's label sums of the prepared
/// labels (kept on the device with `keep`, when the rasterizer keeps them; with
/// [`Keep::fall_back`] a device memory limit sends them the host's way, recorded in the
/// result), or the per-pixel lists when the rasterizer has no label sums or there are no
/// labels. `stats.aggregate_s` holds the labels' host time so far.
///
/// Errors: the rasterizer's.
pub(crate) fn raster_view(
    rasterizer: &mut dyn WeightRasterizer,
    intrinsics: &Intrinsics,
    world_to_camera: &WorldToCamera,
    prepared: PreparedView,
    keep: Option<KeepView<'_>>,
) -> Result<RasteredView> {
    let pixels = intrinsics.width as usize * intrinsics.height as usize;
    let PreparedView {
        labels,
        mut precomputed,
        factors,
        labels_s,
    } = prepared;
    // The stats of a view summed per label on the device (kept there or read back).
    let counted_pixels = labels
        .as_ref()
        .map_or(0, |l| l.labels.iter().filter(|&&l| l != 0).count());
    let t0 = Instant::now();
    let sums_stats = |contributions| ViewStats {
        raster_s: t0.elapsed().as_secs_f64(),
        aggregate_s: labels_s,
        pixels,
        contributions,
        counted_pixels,
        device_sums: true,
    };
    let mut gave_up_keeping = None;
    if let (Some(labels), Some(keep)) = (&labels, keep) {
        // Taken: a rasterizer that keeps nothing falls back without it (only slower).
        let pre = precomputed.take();
        match keep_view(rasterizer, intrinsics, world_to_camera, labels, pre, &factors, keep) {
            Ok(Some(view)) => {
                let stats = sums_stats(view.contributions);
                let out = Rastered::Kept {
                    dominant: view.dominant,
                };
                return Ok(RasteredView { out, stats, gave_up_keeping });
            }
            Ok(None) => {}
            Err(e) if keep.keep.fall_back && is_device_memory(&e) => gave_up_keeping = Some(e),
            Err(e) => return Err(e),
        }
    }
    let out = if let Some(labels) = labels
        && let Some(sums) = rasterizer.label_sums_precomputed(
            intrinsics,
            world_to_camera,
            &labels.labels,
            precomputed,
        )?
    {
        let stats = sums_stats(sums.contributions);
        let out = Rastered::Sums {
            sums,
            masks_of: labels.masks_of,
            factors,
        };
        RasteredView { out, stats, gave_up_keeping: None }
    } else {
        raster_weights(rasterizer, intrinsics, world_to_camera, labels_s)?
    };
    Ok(RasteredView { gave_up_keeping, ..out })
}

/// The kept step of [`raster_view`]: the view's sums kept on the device
/// ([`WeightRasterizer::label_sums_kept`]) with its masks; `Ok(None)` when the rasterizer
/// keeps none. `precomputed`: the view's host work done ahead; `factors`: the masks'.
///
/// Errors: the rasterizer's.
fn keep_view(
    rasterizer: &mut dyn WeightRasterizer,
    intrinsics: &Intrinsics,
    world_to_camera: &WorldToCamera,
    labels: &aggregate::PixelLabels,
    precomputed: Option<crate::raster::PrecomputedView>,
    factors: &[f32],
    keep: KeepView<'_>,
) -> Result<Option<crate::raster::KeptView>> {
    rasterizer.label_sums_kept(
        intrinsics,
        world_to_camera,
        &labels.labels,
        precomputed,
        crate::raster::KeptMasks {
            masks_of: &labels.masks_of,
            factors,
            embeddings: keep.embeddings,
            dominant: keep.keep.dominant,
            view: keep.view,
        },
    )
}

/// The per-pixel lists' step of [`raster_view`] (no labels, or no label sums here);
/// `labels_s`: the labels' host time so far.
///
/// Errors: the rasterizer's.
fn raster_weights(
    rasterizer: &mut dyn WeightRasterizer,
    intrinsics: &Intrinsics,
    world_to_camera: &WorldToCamera,
    labels_s: f64,
) -> Result<RasteredView> {
    let pixels = intrinsics.width as usize * intrinsics.height as usize;
    let t0 = Instant::now();
    let weights = rasterizer.rasterize(intrinsics, world_to_camera)?;
    let stats = ViewStats {
        raster_s: t0.elapsed().as_secs_f64(),
        aggregate_s: labels_s,
        pixels,
        contributions: weights.ids.len() as u64,
        counted_pixels: pixels,
        device_sums: false,
    };
    Ok(RasteredView {
        out: Rastered::Weights(weights),
        stats,
        gave_up_keeping: None,
    })
}

/// The host's half of [`view_contribution`]: the label sums reduced and expanded to masks, or
/// the per-pixel lists summed per mask; `masks` are needed only for the lists. A view kept on
/// the device gives an empty contribution and its dominant masks.
///
/// Errors: as [`image_contribution`].
pub(crate) fn finish_view(
    r: RasteredView,
    masks: &[Mask],
    mask_embeddings: Vec<f32>,
    dim: usize,
    params: ImageStageParams,
) -> Result<(ImageContribution, Option<DominantMasks>, ViewStats)> {
    let t0 = Instant::now();
    let mut stats = r.stats;
    let mut dominant = None;
    let c = match r.out {
        Rastered::Sums {
            sums,
            masks_of,
            factors,
        } => sums_contribution(sums, &masks_of, &factors, mask_embeddings, dim),
        Rastered::Weights(weights) => {
            aggregate::image_contribution(&weights, masks, mask_embeddings, dim, params)?
        }
        Rastered::Kept { dominant: d } => {
            dominant = Some(d);
            ImageContribution {
                dim,
                mask_embeddings: Vec::new(),
                entries: Vec::new(),
            }
        }
    };
    stats.aggregate_s += t0.elapsed().as_secs_f64();
    Ok((c, dominant, stats))
}

/// An image's contribution from its view's label sums (any order, a key several times): the
/// sums reduced and expanded from labels to the masks `masks_of` names, each mask's `a_kj`
/// times its factor (`factors`; empty: all 1), with the masks' embeddings `[M × dim]`.
pub(crate) fn sums_contribution(
    sums: crate::raster::LabelSums,
    masks_of: &[Vec<u32>],
    factors: &[f32],
    mask_embeddings: Vec<f32>,
    dim: usize,
) -> ImageContribution {
    let mut entries = aggregate::image::expand_label_records(sums, masks_of);
    aggregate::image::apply_mask_factors(&mut entries, factors);
    ImageContribution {
        dim,
        mask_embeddings,
        entries,
    }
}

/// A [`FrontItem`] with its view's camera and labels, ready for its rasterizer
/// ([`back_prepare`]).
pub(crate) struct BackPrepared {
    item: FrontItem,
    intrinsics: Intrinsics,
    world_to_camera: WorldToCamera,
    prepared: PreparedView,
}

/// The first part of the back stage of a [`FrontItem`] (the image's `a_kj` from its view at
/// `raster_intrinsics`, [`view_contribution`]: GPU label sums, or weights then the host image
/// stage; then [`back_raster`] and [`back_finish`]): the item's view and its pixel labels, made
/// from the masks' runs (not expanded), and the rasterizer's host work of the view
/// (`precompute`).
///
/// Errors: the image stage's input checks; [`Error::Internal`] for a view index out of range of
/// `views` or `raster_intrinsics` (an internal error).
pub(crate) fn back_prepare(
    views: &[View],
    raster_intrinsics: &[Intrinsics],
    item: FrontItem,
    dim: usize,
    image_stage: ImageStageParams,
    precompute: Option<&dyn crate::raster::ViewPrecompute>,
) -> Result<BackPrepared> {
    let (Some(view), Some(k)) = (views.get(item.view), raster_intrinsics.get(item.view)) else {
        return Err(Error::internal(format!(
            "image {} has no view or raster intrinsics ({} views, {} intrinsics)",
            item.view,
            views.len(),
            raster_intrinsics.len()
        )));
    };
    aggregate::image::check_image_inputs(&item.masks, &item.embeddings, dim)?;
    let prepared = prepare_view(
        k,
        &view.world_to_camera,
        &item.masks,
        image_stage,
        precompute,
    );
    Ok(BackPrepared {
        item,
        intrinsics: *k,
        world_to_camera: view.world_to_camera,
        prepared,
    })
}

/// The rasterizer's part of the back stage ([`raster_view`]): what [`back_finish`] completes.
pub(crate) struct BackRaster {
    /// The front's item (its masks compact, its embeddings).
    pub item: FrontItem,
    rastered: RasteredView,
}

impl BackRaster {
    /// The device memory limit on which this view went the host's way instead of being kept
    /// ([`Keep::fall_back`]), taken; `None`: it did not.
    pub(crate) fn take_gave_up_keeping(&mut self) -> Option<Error> {
        self.rastered.gave_up_keeping.take()
    }

    /// Whether the view's sums stayed on the device ([`WeightRasterizer::label_sums_kept`]).
    pub(crate) fn is_kept(&self) -> bool {
        matches!(self.rastered.out, Rastered::Kept { .. })
    }
}

/// The rasterizer's part of the back stage; `keep`: `Some` when the rasterizer keeps the sums
/// on its device ([`Keep`]).
///
/// Errors: the rasterizer's.
pub(crate) fn back_raster(
    rasterizer: &mut dyn WeightRasterizer,
    p: BackPrepared,
    keep: Option<Keep>,
) -> Result<BackRaster> {
    let keep = keep.map(|keep| KeepView {
        embeddings: &p.item.embeddings,
        keep,
        view: p.item.view,
    });
    let rastered = raster_view(
        rasterizer,
        &p.intrinsics,
        &p.world_to_camera,
        p.prepared,
        keep,
    )?;
    Ok(BackRaster {
        item: p.item,
        rastered,
    })
}

/// The host's half of the back stage ([`finish_view`]).
///
/// Errors: the image stage's.
pub(crate) fn back_finish(
    r: BackRaster,
    dim: usize,
    image_stage: ImageStageParams,
) -> Result<BackOut> {
    let BackRaster { item, rastered } = r;
    // Only the per-pixel lists need the masks' pixels.
    let masks = match rastered.out {
        Rastered::Weights(_) => crate::masks::compact::expand_all(&item.masks),
        Rastered::Sums { .. } | Rastered::Kept { .. } => Vec::new(),
    };
    let (contribution, dominant, vs) =
        finish_view(rastered, &masks, item.embeddings, dim, image_stage)?;
    Ok(BackOut {
        contribution,
        dominant,
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

/// Runs the whole Semantic Embedding stage on `scene` and writes `<out>/mixture.safetensors`
/// with [`EncodeParams::mixture_keep`], `<out>/embeddings.safetensors` with
/// [`EncodeParams::dense`], and `<out>/report.json` (each atomically; the report last, so a
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
/// The encode over a pool of workers ([`pool::run_pool`]: `fronts.len()` front threads,
/// decode → masks → CLIP crops, and one back thread per rasterizer that `make_rasterizers`
/// returns, raster → `a_kj`), then the one reduction over all images and the output files
/// ([`finish::finish`]): `<out>/embeddings.safetensors`, the optional forms, `<out>/report.json`
/// last.
///
/// Scheduling is dynamic at both ends: front workers take the next unclaimed view from a shared
/// counter, and back workers take the next finished front item from one bounded queue (depth
/// 2 × rasterizers), so an image with many masks or a slow GPU holds up only its own worker
/// (the paper saw large stragglers with a static split). The per-image contributions of all
/// workers go to one [`aggregate::ContributionStore`]; the reduction (`E_k`, f64) runs once at the end, so
/// the result equals a one-worker run up to the f64 summation order.
///
/// Errors: the first error of any worker stops the others (no output is written); otherwise as
/// [`encode`]. All fronts must embed with the same model (same `model_id` and `dim`).
pub fn encode_pool(
    scene: &SceneInput,
    fronts: Vec<FrontStages>,
    make_rasterizers: impl FnOnce(&Gaussians) -> Result<Vec<Box<dyn WeightRasterizer>>>,
    params: &EncodeParams,
    report: Report,
) -> Result<Report> {
    encode_pool_with(scene, fronts, make_rasterizers, params, report, |_, _| {})
}

/// [`encode_pool`] that calls `on_tail` as soon as the last view is done, before the
/// reduction, with the masks' record (with [`EncodeParams::mask_record_slots`]) and whether the
/// reduction will run on the device (the host's cores are then free but for the write).
///
/// Errors: as [`encode_pool`].
pub fn encode_pool_with(
    scene: &SceneInput,
    fronts: Vec<FrontStages>,
    make_rasterizers: impl FnOnce(&Gaussians) -> Result<Vec<Box<dyn WeightRasterizer>>>,
    params: &EncodeParams,
    report: Report,
    on_tail: impl FnOnce(Option<std::sync::Arc<slag_common::mask_record::MaskRecord>>, bool),
) -> Result<Report> {
    let pool = EncodePool {
        scene,
        shared: None,
        fronts,
        params,
        on_device_keep: None,
    };
    encode_pool_sharing(pool, make_rasterizers, report, on_tail)
}

/// What [`encode_pool_sharing`] runs: `scene`'s encode with `fronts` and `params`, its
/// Gaussians from `shared` ([`SceneInput::load_sharing`]) when given.
pub(crate) struct EncodePool<'a> {
    pub(crate) scene: &'a SceneInput,
    pub(crate) shared: Option<scene_load::SceneLoad>,
    pub(crate) fronts: Vec<FrontStages>,
    pub(crate) params: &'a EncodeParams,
    /// Called (once) when the first rasterizer starts keeping its views' sums on its device:
    /// the host's per-view work is light from then on.
    pub(crate) on_device_keep: Option<&'a (dyn Fn() + Sync)>,
}

/// [`encode_pool_with`] with the Gaussians of a load shared with the segments
/// ([`EncodePool::shared`]).
///
/// Errors: as [`encode_pool`].
pub(crate) fn encode_pool_sharing(
    pool: EncodePool<'_>,
    make_rasterizers: impl FnOnce(&Gaussians) -> Result<Vec<Box<dyn WeightRasterizer>>>,
    report: Report,
    on_tail: impl FnOnce(Option<std::sync::Arc<slag_common::mask_record::MaskRecord>>, bool),
) -> Result<Report> {
    let EncodePool {
        scene,
        shared,
        fronts,
        params,
        on_device_keep,
    } = pool;
    let t_total = Instant::now();
    let hooks = pool::PoolHooks {
        t_total,
        on_device_keep,
    };
    let mut pooled = pool::run_pool(scene, shared, fronts, make_rasterizers, params, hooks)?;
    let record = pooled.mask_record.take().map(std::sync::Arc::new);
    on_tail(record, !pooled.device.is_empty());
    // The fronts' sessions are torn down beside the tail, and that is waited for before
    // returning: none outlives the encode.
    let retired = std::mem::take(&mut pooled.retired);
    let teardown = std::thread::spawn(move || {
        let t0 = Instant::now();
        drop(retired);
        t0.elapsed().as_secs_f64()
    });
    let finished = finish::finish(scene, pooled, params, report, t_total);
    if let Ok(seconds) = teardown.join() {
        tracing::debug!(target: "slag_encoder::pipeline", seconds, "front models let go");
    }
    finished
}

/// [`CropEmbedder`] for the CLIP front-ends that have the same inherent `model_id`, `dim` and
/// `embed_masks`: a worker's own session ([`crate::clip::ClipVisual`]) and a handle to a GPU's
/// shared CLIP service ([`crate::clip::ClipHandle`]).
macro_rules! crop_embedder_by_inherent_methods {
    ($($clip:ty),+) => {$(
        impl CropEmbedder for $clip {
            fn model_id(&self) -> &str {
                <$clip>::model_id(self)
            }
            fn dim(&self) -> usize {
                <$clip>::dim(self)
            }
            fn embed(&mut self, image: &RgbImage, masks: &[Mask]) -> Result<Vec<Vec<f32>>> {
                self.embed_masks(image, masks)
            }
        }
    )+};
}

crop_embedder_by_inherent_methods!(crate::clip::ClipHandle, crate::clip::ClipVisual);
