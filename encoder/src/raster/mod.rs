//! The weight rasterizer: the 3DGS forward pass (EWA splatting, 16x16 tiles, front-to-back
//! alpha blending) that yields, per pixel, every contributing Gaussian's blend weight
//! `w_kp = α_kp · T_kp` instead of a colour (SLAG's Semantic Embedding stage).
//!
//! Conventions follow the INRIA rasterizer / gsplat: 0.3 px low-pass added to the 2D covariance,
//! `α = min(0.99, o · exp(-½ dᵀ Σ⁻¹ d))`, contributions with `α < 1/255` skipped, a pixel stops
//! once `T < 1e-4`.
//!
//! | module | role |
//! |---|---|
//! | [`project`] | the EWA projection math (the one written-down definition; the WGSL mirrors it) |
//! | [`cpu`] | [`CpuRasterizer`]: slow, simple f64 reference |
//! | [`gpu`] | [`GpuRasterizer`]: wgpu compute kernels (`gpu/*.wgsl`, one file per kernel family, beside the Rust pass that dispatches it) |
//! | [`colour`] | SH colour render composited with the same weights, and PSNR, for validation |

pub mod colour;
pub mod cpu;
pub mod gpu;
pub mod project;
#[cfg(test)]
mod stream_tests;
#[cfg(test)]
mod testdata;
#[cfg(test)]
mod tests;

pub use colour::{psnr, render_colour};
pub use cpu::CpuRasterizer;
pub use gpu::{GpuRasterizer, PhaseTimings};

use rayon::prelude::*;
use std::sync::Arc;

use slag_common::camera::Intrinsics;
use slag_common::{Error, Result};

/// Per-pixel contributor lists of one rendered view, in compressed-sparse-row form.
///
/// Pixel `p = y * width + x` owns entries `offsets[p] .. offsets[p + 1]` of `ids` / `weights`,
/// ordered front to back. `weights[e] = α·T` of Gaussian `ids[e]` at that pixel, in (0, 1];
/// per pixel the weights sum to `1 - T_final ≤ 1`.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PixelWeights {
    /// Raster width, pixels.
    pub width: u32,
    /// Raster height, pixels.
    pub height: u32,
    /// `width * height + 1` offsets into `ids` / `weights`.
    pub offsets: Vec<u32>,
    /// Gaussian indices (into the scene's Gaussians), front to back per pixel.
    pub ids: Vec<u32>,
    /// Blend weights `α·T`, parallel to `ids`.
    pub weights: Vec<f32>,
}

impl PixelWeights {
    /// The contributors `(ids, weights)` of pixel `(x, y)`.
    pub fn pixel(&self, x: u32, y: u32) -> (&[u32], &[f32]) {
        let p = (y * self.width + x) as usize;
        let (a, b) = (self.offsets[p] as usize, self.offsets[p + 1] as usize);
        (&self.ids[a..b], &self.weights[a..b])
    }
}

impl PixelWeights {
    /// Total number of `(id, weight)` entries over all pixels.
    pub fn len(&self) -> usize {
        self.ids.len()
    }
    /// True when no pixel has any contributor.
    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }
    /// Mean number of contributors per pixel (0 for an empty raster).
    pub fn mean_contributors(&self) -> f64 {
        let n = self.width as f64 * self.height as f64;
        if n == 0.0 {
            0.0
        } else {
            self.ids.len() as f64 / n
        }
    }
}

/// A per-pixel blend-weight rasterizer (the 3DGS forward pass without colours).
///
/// Implementations must agree: same contributor ids per pixel in the same front-to-back order and
/// weights within f32 round-off (the GPU path is tested against [`CpuRasterizer`]).
pub trait WeightRasterizer: Send {
    /// Renders the per-pixel weights of one view. `intrinsics` give the raster size (already
    /// scaled for `--raster-scale`, see [`raster_intrinsics`]); `world_to_camera` is the COLMAP pose.
    ///
    /// Errors: an empty raster ([`Error::Param`] `raster_size`) or one over 2^28 pixels; GPU
    /// failures ([`Error::Gpu`]) or output larger than the device allows ([`Error::Limit`]: a
    /// command line adds the flag that lowers the raster scale).
    fn rasterize(
        &mut self,
        intrinsics: &Intrinsics,
        world_to_camera: &slag_common::camera::WorldToCamera,
    ) -> Result<PixelWeights>;
    /// Per-label sums of one view's blend weights, `Σ_{p: labels[p] = l} w_kp` for every
    /// Gaussian k and label l ≠ 0 with a contribution: the image stage's `a_kj` before masks are
    /// expanded from labels (see [`crate::pipeline::view_contribution`]), without the per-pixel
    /// lists ever leaving the device. `labels` is `[height × width]` row-major at the raster size
    /// of `intrinsics`, 0 = no label. The sums may come in any order, a key several times
    /// ([`LabelSums::records`]).
    ///
    /// `Ok(None)`: this rasterizer has no such path (the caller rasterizes and sums on the
    /// host; the default). The GPU rasterizer always sums, at any scene size (compact
    /// per-tile records, see [`gpu`]). Errors: as [`Self::rasterize`], and [`Error::Internal`] when `labels` does not
    /// hold one label per raster pixel.
    fn label_sums(
        &mut self,
        intrinsics: &Intrinsics,
        world_to_camera: &slag_common::camera::WorldToCamera,
        labels: &[u32],
    ) -> Result<Option<LabelSums>> {
        let _ = (intrinsics, world_to_camera, labels);
        Ok(None)
    }
    /// The host work of a view that this rasterizer lets another thread do before the view
    /// reaches it ([`ViewPrecompute`]), so that its own thread only drives the device: the GPU
    /// rasterizer's sort depths. `None` (the default): there is none.
    fn view_precompute(&self) -> Option<Arc<dyn ViewPrecompute>> {
        None
    }
    /// [`Self::label_sums`] with the view's host work done ahead ([`ViewPrecompute::precompute`]
    /// for this `world_to_camera`; work made for another view is not used). The default
    /// ignores it.
    fn label_sums_precomputed(
        &mut self,
        intrinsics: &Intrinsics,
        world_to_camera: &slag_common::camera::WorldToCamera,
        labels: &[u32],
        precomputed: Option<PrecomputedView>,
    ) -> Result<Option<LabelSums>> {
        let _ = precomputed;
        self.label_sums(intrinsics, world_to_camera, labels)
    }
    /// One view of the coverage pass ([`crate::views`]): the Gaussians whose total blend weight
    /// in the view, `W_k = Σ_p w_kp` over every raster pixel of `intrinsics`, reaches `floor`,
    /// as a bitset over the scene (bit `k % 64` of word `k / 64`, `⌈N / 64⌉` words). `W_k` and
    /// `floor` are 64-bit fixed point, `2^32` = one raster pixel, the per-pixel weights truncated
    /// to it and summed exactly: the totals of [`Self::label_sums`] with every pixel in one
    /// label. A floor of 0 counts as 1 (a Gaussian must contribute). The rasterizer keeps, per
    /// Gaussian, the largest `W_k` of a view that saw it ([`Self::take_coverage_maxima`]).
    /// `precomputed` is the view's host work done ahead, as for
    /// [`Self::label_sums_precomputed`].
    ///
    /// `Ok(None)`: this rasterizer has no such path (the default; the pass then sums
    /// [`Self::label_sums`] or the per-pixel lists on the host). Errors: as [`Self::rasterize`].
    fn coverage_view(
        &mut self,
        intrinsics: &Intrinsics,
        world_to_camera: &slag_common::camera::WorldToCamera,
        floor: u64,
        precomputed: Option<PrecomputedView>,
    ) -> Result<Option<Vec<u64>>> {
        let _ = (intrinsics, world_to_camera, floor, precomputed);
        Ok(None)
    }
    /// The maxima that [`Self::coverage_view`] kept since the last call, then forgotten: per
    /// Gaussian (`N` values) the largest total blend weight (its fixed point) of a view that saw
    /// it, 0 when none did. `Ok(None)` for a rasterizer without [`Self::coverage_view`] (the
    /// default).
    ///
    /// Errors: device failures.
    fn take_coverage_maxima(&mut self) -> Result<Option<Vec<u64>>> {
        Ok(None)
    }
    /// Starts keeping every labelled view's sums on the device for the device reduction
    /// ([`Self::label_sums_kept`], then [`Self::reduce_kept`]): `dim` is the embedding width,
    /// `budget_bytes` the most device memory the kept sums may take, `on_cpu_adapter` whether a
    /// CPU device (lavapipe) may keep them too. Returns whether this rasterizer keeps them; the
    /// default (and a device without f64) does not, and the encoder reduces on the host.
    fn keep_on_device(&mut self, dim: usize, budget_bytes: u64, on_cpu_adapter: bool) -> bool {
        let _ = (dim, budget_bytes, on_cpu_adapter);
        false
    }
    /// Streams the kept views ([`Self::keep_on_device`] first, nothing kept yet): instead of
    /// keeping every view to the end, [`Self::fold_kept`] folds them a wave at a time into a
    /// running state of `keep` mixture pairs and `Σ a_kj` per Gaussian, so that the device
    /// memory does not grow with the views ([`gpu`]'s `fold` module). [`Self::reduce_kept`]
    /// then writes the mixture only (no dense rows, every Gaussian). Returns whether it
    /// streams; the default (and a state that passes half the budget) does not.
    fn stream_kept(&mut self, keep: usize) -> bool {
        let _ = keep;
        false
    }
    /// With [`Self::stream_kept`], folds the kept views whose index in the encode's view list
    /// is below `below` into the running state when the kept records passed the wave size
    /// (half the budget left beside the state); no view below `below` may come after. Returns
    /// whether a wave ran; the default does nothing.
    ///
    /// Errors: device failures; a tile's records past a binding ([`Error::Limit`]).
    fn fold_kept(&mut self, below: usize) -> Result<bool> {
        let _ = below;
        Ok(false)
    }
    /// [`Self::stream_kept`] on share `share` of `shares` rasterizers (from 0) that stream
    /// together (a run on several GPUs): the running state covers that share of the Gaussians
    /// only. Returns where the others send their views' records of that share; `None`: it
    /// does not stream (the default). Every rasterizer then hears whether all stream
    /// ([`Self::share_kept_with`]) before it keeps a view.
    fn stream_kept_share(
        &mut self,
        keep: usize,
        share: usize,
        shares: usize,
    ) -> Option<gpu::ek::KeptInbox> {
        let _ = (keep, share, shares);
        None
    }
    /// After [`Self::stream_kept_share`]: `Some` with the other rasterizers' inboxes when every
    /// one streams: from here each view this rasterizer keeps goes, as it is kept, to the
    /// rasterizers whose shares it holds records of, and [`Self::fold_kept`] takes in what
    /// they sent before it folds (its `below` counts a view only once it was sent); `None`
    /// when one does not, and this one stops streaming too. The default does nothing.
    fn share_kept_with(&mut self, peers: Option<Vec<gpu::ek::KeptInbox>>) {
        let _ = peers;
    }
    /// The Gaussian ids `[first, end)` this rasterizer's streamed share covers
    /// ([`Self::stream_kept_share`]), which its [`Self::reduce_kept`] writes
    /// ([`DeviceReduce::gaussians`]); `None` without one (the default).
    fn kept_share(&self) -> Option<(u32, u32)> {
        None
    }
    /// [`Self::label_sums_precomputed`] whose sums stay on the device, with the view's masks
    /// (`masks`) for their expansion at the reduction: nothing per `a_kj` is read back. Returns
    /// the view's contributions and, with [`KeptMasks::dominant`], each Gaussian's dominant mask
    /// for the masks' record; `Ok(None)` when this rasterizer does not keep sums
    /// ([`Self::keep_on_device`]).
    ///
    /// Errors: as [`Self::label_sums`]; the kept sums would pass the budget ([`Error::Limit`]
    /// `GpuMemory`). A view that fails is not kept; the views kept before it stay
    /// ([`Self::export_kept`] brings them back).
    fn label_sums_kept(
        &mut self,
        intrinsics: &Intrinsics,
        world_to_camera: &slag_common::camera::WorldToCamera,
        labels: &[u32],
        precomputed: Option<PrecomputedView>,
        masks: KeptMasks<'_>,
    ) -> Result<Option<KeptView>> {
        let _ = (intrinsics, world_to_camera, labels, precomputed, masks);
        Ok(None)
    }
    /// Keeps the masks' record ([`slag_common::mask_record`], `slots` slots per Gaussian, for an
    /// encode of `view_count` views) on the device from here on, once this rasterizer keeps the
    /// views' sums there ([`Self::keep_on_device`]): each kept view's dominant masks enter it
    /// there ([`KeptMasks::view`]) and [`Self::label_sums_kept`] returns none. Returns whether it
    /// does; the default (and a scene whose record does not fit the device) does not, and the
    /// caller records the dominant masks [`KeptMasks::dominant`] returns.
    fn keep_mask_record(&mut self, slots: usize, view_count: usize) -> bool {
        let _ = (slots, view_count);
        false
    }
    /// The masks' record kept on the device ([`Self::keep_mask_record`]), read back and freed
    /// there; `None` when none was kept (the default).
    ///
    /// Errors: device failures.
    fn take_mask_record(&mut self) -> Result<Option<slag_common::mask_record::MaskRecord>> {
        Ok(None)
    }
    /// The device reduction of every kept view (`E_k`, its kept mixture pairs, the unobserved
    /// rule: the host reduction's, see [`gpu`]'s `ek` module), tile by tile of Gaussian ids
    /// ascending into `sink`; the kept sums are freed with the rasterizer.
    ///
    /// Errors: nothing kept (the default: [`Error::Internal`]); device failures; `sink`'s.
    fn reduce_kept(
        &mut self,
        params: &DeviceReduce,
        sink: &mut dyn FnMut(KeptTile) -> Result<()>,
    ) -> Result<KeptReduced> {
        let _ = (params, sink);
        Err(Error::internal(
            "this rasterizer keeps no sums on its device",
        ))
    }
    /// Every view this rasterizer kept, as host data for another rasterizer's
    /// [`Self::import_kept`] (a run on several GPUs reduces on one); keeping stops. `None`: it
    /// kept nothing (the default).
    ///
    /// Errors: device failures reading the sums back.
    fn export_kept(&mut self) -> Result<Option<KeptExport>> {
        Ok(None)
    }
    /// The next batch of what this rasterizer kept, for another rasterizer's
    /// [`Self::import_kept`], with at most about `max_bytes` of records: the first batch has
    /// every view, later ones continue it ([`KeptExport::continues`]); keeping stops at the
    /// first; `None` once all went. The default hands everything over in one batch
    /// ([`Self::export_kept`]).
    ///
    /// Errors: device failures reading the sums back.
    fn export_kept_batch(&mut self, max_bytes: u64) -> Result<Option<KeptExport>> {
        let _ = max_bytes;
        self.export_kept()
    }
    /// Per block of Gaussians, how many records this rasterizer's own kept views hold: the
    /// block's size in Gaussians and `[blocks]` counts, for splitting the reduction between
    /// devices by work ([`Self::export_kept_range`]); `None` when it keeps nothing (the default).
    fn kept_block_records(&self) -> Option<(u32, Vec<u64>)> {
        None
    }
    /// The next batch of this rasterizer's own kept records of the Gaussians in `cursor`'s
    /// range, with at most about `max_bytes` of records, for the rasterizer that reduces that
    /// range ([`Self::import_kept`], then [`Self::reduce_kept`] with
    /// [`DeviceReduce::gaussians`]): a run on several GPUs splits the reduction by Gaussians,
    /// each device sending the others their ranges. The first batch has every view this
    /// rasterizer kept itself, later ones continue it; keeping stops at the first; its own
    /// range's records stay. `None` once all went, or nothing was kept (the default).
    ///
    /// Errors: a range not on block bounds ([`Error::Internal`]); device failures reading the
    /// sums back.
    fn export_kept_range(
        &mut self,
        cursor: &mut KeptRangeCursor,
        max_bytes: u64,
    ) -> Result<Option<KeptExport>> {
        let _ = (cursor, max_bytes);
        Ok(None)
    }
    /// What uploads other rasterizers' kept records to this one's device without holding this
    /// rasterizer ([`gpu::ek::KeptUploader`]), for [`Self::import_uploaded`]; `None` where it
    /// keeps nothing on a device (the default).
    fn kept_uploader(&self) -> Option<gpu::ek::KeptUploader> {
        None
    }
    /// [`Self::import_kept`] of a batch whose records [`Self::kept_uploader`] put on this
    /// rasterizer's device already.
    ///
    /// Errors: as [`Self::import_kept`]; a batch uploaded to another device
    /// ([`Error::Internal`]).
    fn import_uploaded(&mut self, kept: gpu::ek::UploadedKept) -> Result<()> {
        let _ = kept;
        Err(Error::internal(
            "this rasterizer keeps no sums on its device",
        ))
    }
    /// Adds the views another rasterizer kept ([`Self::export_kept`], or a batch of them:
    /// [`Self::export_kept_batch`], [`Self::export_kept_range`]) to this one's, for one
    /// [`Self::reduce_kept`] over all of them; keeping stops (the views kept so far are this
    /// rasterizer's own).
    ///
    /// Errors: this rasterizer keeps nothing (the default: [`Error::Internal`]); a batch that
    /// continues an export whose first batch did not come.
    fn import_kept(&mut self, kept: KeptExport) -> Result<()> {
        let _ = kept;
        Err(Error::internal(
            "this rasterizer keeps no sums on its device",
        ))
    }
    /// A short name for logs and reports (e.g. the GPU adapter).
    fn name(&self) -> &str;
    /// Phase timings of the last successful [`Self::rasterize`] or [`Self::label_sums`] run,
    /// where the rasterizer measures them (the GPU rasterizer); `None` by default.
    fn last_phases(&self) -> Option<PhaseTimings> {
        None
    }
}

/// One view's masks as the device reduction expands its label sums
/// ([`WeightRasterizer::label_sums_kept`]).
#[derive(Debug, Clone, Copy)]
pub struct KeptMasks<'a> {
    /// `[L]` the masks of each pixel label (label 0: none), as [`crate::aggregate::PixelLabels`]
    /// holds them.
    pub masks_of: &'a [Vec<u32>],
    /// `[M]` each mask's weighting factor (`aggregate::image::mask_factors`); empty: all 1.
    pub factors: &'a [f32],
    /// `[M × D]` the masks' CLIP embeddings `E_j`, row-major.
    pub embeddings: &'a [f32],
    /// Also find each Gaussian's dominant mask of the view (the masks' record).
    pub dominant: bool,
    /// The view's index in the encode's view list: the view the masks' record kept on the
    /// device ([`WeightRasterizer::keep_mask_record`]) enters its dominant masks as.
    pub view: usize,
}

/// What [`WeightRasterizer::label_sums_kept`] returns of a view.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct KeptView {
    /// `(pixel, Gaussian)` contributions over labelled pixels.
    pub contributions: u64,
    /// With [`KeptMasks::dominant`]: `(Gaussian, mask, a_kj)` per Gaussian of the view, the
    /// mask of largest `a_kj` (ties: the smaller mask), Gaussians ascending.
    pub dominant: Vec<(u32, u32, f32)>,
}

/// Knobs of the device reduction ([`WeightRasterizer::reduce_kept`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DeviceReduce {
    /// `aggregate::ReduceParams::min_total_weight`: below it a Gaussian is unobserved.
    pub min_total_weight: f64,
    /// Kept `(a_kj, codebook row)` pairs per Gaussian (the mixture's `S`), 1 to 32.
    pub keep: usize,
    /// Also return the unit rows `E_k` (the dense file).
    pub dense: bool,
    /// Only the Gaussian ids `[first, end)` (a run on several GPUs gives each one range,
    /// [`WeightRasterizer::export_kept_range`]); `None`: every Gaussian. A range starts and ends
    /// on a block of [`WeightRasterizer::kept_block_records`] (or at the last Gaussian).
    pub gaussians: Option<(u32, u32)>,
}

/// One tile of the device reduction: its observed Gaussians, ascending.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct KeptTile {
    /// `[B]` Gaussian ids.
    pub ids: Vec<u32>,
    /// `[B]` `Σ_i Σ_j a_kj`, rounded to f32.
    pub total_weights: Vec<f32>,
    /// `[B + 1]` where each Gaussian's kept pairs start in [`KeptTile::kept`] (the last: its
    /// length).
    pub kept_starts: Vec<u32>,
    /// The kept `(a_kj, codebook row)` pairs, Gaussian after Gaussian, at most `keep` each
    /// (unordered within a Gaussian).
    pub kept: Vec<(f32, u32)>,
    /// With [`DeviceReduce::dense`]: `[B × D]` the unit `E_k`, f32; else empty.
    pub rows: Vec<f32>,
}

impl KeptTile {
    /// The kept pairs of the tile's `i`-th Gaussian (empty past the tile).
    pub fn kept_of(&self, i: usize) -> &[(f32, u32)] {
        match (self.kept_starts.get(i), self.kept_starts.get(i + 1)) {
            (Some(&a), Some(&b)) => self.kept.get(a as usize..b as usize).unwrap_or_default(),
            _ => &[],
        }
    }
}

/// The views one rasterizer kept on its device, as host data ([`WeightRasterizer::export_kept`]):
/// per view its label table and codebook rows, per kept band its records and block index.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct KeptExport {
    /// Embedding width D.
    pub(crate) dim: usize,
    /// Per view, in keeping order: its label table (the device reduction's layout, offsets
    /// relative to its start), its masks' embeddings `[M × D]` and its index in the encode's
    /// view list ([`KeptMasks::view`]).
    pub(crate) views: Vec<(Vec<u32>, Vec<f32>, u32)>,
    /// Per band: its view, its records (16 bytes each), where each block of Gaussians starts.
    pub(crate) parts: Vec<(u32, Vec<u8>, Vec<u32>)>,
    /// Whether this batch continues the export whose first batch brought the views
    /// ([`WeightRasterizer::export_kept_batch`]): its `views` is then empty, and its bands'
    /// views are those of that batch.
    pub(crate) continues: bool,
    /// Which rasterizer it came from, as whoever moves it numbers them (0 unless set): an
    /// importer takes batches of several sources interleaved, each source's bands pointing at
    /// the views of that source's first batch.
    pub(crate) source: u32,
}

/// Where an export of one range of Gaussians stands ([`WeightRasterizer::export_kept_range`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct KeptRangeCursor {
    /// The Gaussian ids `[first, end)` exported.
    pub(crate) gaussians: std::ops::Range<u32>,
    /// The next of the exporter's own bands.
    pub(crate) next_part: usize,
    /// Whether the first batch (the views) went.
    pub(crate) started: bool,
}

impl KeptRangeCursor {
    /// An export of the kept records of the Gaussian ids `[first, end)`, from its start.
    pub fn new(gaussians: std::ops::Range<u32>) -> Self {
        Self {
            gaussians,
            next_part: 0,
            started: false,
        }
    }
}

/// One kept view brought back to the host ([`KeptExport::into_host_views`]): what the host's
/// image stage expands into the view's `a_kj` (`aggregate::image::expand_label_records`, then
/// the masks' factors), the same entries it makes of a view whose sums were read back.
#[derive(Debug, Clone, Default, PartialEq)]
pub(crate) struct KeptHostView {
    /// The view's records, one per (Gaussian, label) key and band (not [`LabelSums::sorted`]).
    pub(crate) sums: LabelSums,
    /// `[L]` the masks of each pixel label (label 0: none).
    pub(crate) masks_of: Vec<Vec<u32>>,
    /// `[M]` each mask's weighting factor.
    pub(crate) factors: Vec<f32>,
    /// `[M × D]` the masks' CLIP embeddings.
    pub(crate) embeddings: Vec<f32>,
    /// The view's index in the encode's view list ([`KeptMasks::view`]).
    pub(crate) view: usize,
}

/// What [`WeightRasterizer::reduce_kept`] leaves besides the tiles.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct KeptReduced {
    /// Tiles the reduction used (at the end: the streamed reduction's waves come before).
    pub tiles: usize,
    /// Times the kept views were reduced: 1 when every view was kept to the end; with the
    /// streamed reduction ([`WeightRasterizer::stream_kept`]), its waves.
    pub waves: usize,
    /// Bytes of the streamed reduction's running state on the device (0 without it).
    pub state_bytes: u64,
    /// The most bytes of label sums kept on the device at once.
    pub peak_kept_bytes: u64,
    /// Bytes of every label sum kept over the run (16 per record).
    pub records_bytes: u64,
    /// `[M × D]` every kept view's mask embeddings, by view index ([`KeptMasks::view`]) and then
    /// mask: the codebook the kept pairs' rows index.
    pub codebook: Vec<f32>,
}

/// A rasterizer's per-view host work, done on the caller's thread
/// ([`WeightRasterizer::view_precompute`]).
pub trait ViewPrecompute: Send + Sync {
    /// What the rasterizer needs of the view `world_to_camera` (world-to-camera, COLMAP
    /// convention).
    fn precompute(&self, world_to_camera: &slag_common::camera::WorldToCamera) -> PrecomputedView;
}

/// A view's host work done ahead ([`ViewPrecompute::precompute`]).
#[derive(Debug, Clone, PartialEq)]
pub struct PrecomputedView {
    /// The view it was made for.
    pub world_to_camera: slag_common::camera::WorldToCamera,
    /// `[N]` per Gaussian its sort depth: the f64 camera-frame depth clamped at 0, rounded to
    /// f32 (the key the rasterizers order a tile by, with the Gaussian id).
    pub sort_depths: Vec<f32>,
}

/// One per-label sum of blend weights ([`WeightRasterizer::label_sums`]): Gaussian `gaussian`
/// received `Σ w_kp` over the pixels labelled `label`, in exact 64-bit fixed point with 32
/// fractional bits (each `w_kp` truncated to a multiple of 2^-32 before the sum; units: pixels
/// at the raster resolution). `repr(C)`, 16 bytes: the layout of the GPU's records (Gaussian,
/// label, low and high word of the sum) on a little-endian host, so a readback is one copy.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct LabelSum {
    /// Gaussian index (source `.ply` order).
    pub gaussian: u32,
    /// Pixel label (≥ 1).
    pub label: u32,
    /// `Σ w_kp · 2^32`, truncated per term.
    pub sum: u64,
}

/// One view's [`WeightRasterizer::label_sums`].
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct LabelSums {
    /// The sums as the rasterizer made them: unless [`LabelSums::sorted`], in any order, and a
    /// (Gaussian, label) key may stand several times (the GPU writes one record per tile and
    /// reduces a band of tile rows at a time); [`LabelSums::reduced`] sorts and adds them.
    pub records: Vec<LabelSum>,
    /// Contributions (pixel, Gaussian) summed: those of labelled pixels only.
    pub contributions: u64,
    /// `records` are already sorted by (Gaussian, label), one per key (the GPU reduced the
    /// whole view in one band): [`LabelSums::reduced`] returns them as they are.
    pub sorted: bool,
}

impl LabelSum {
    /// The sum in pixels (`sum / 2^32`).
    pub fn weight(&self) -> f64 {
        self.sum as f64 / 4_294_967_296.0
    }
}

impl LabelSums {
    /// The records sorted by (Gaussian, label), the sums of one key added (integers: exact, so
    /// the result does not depend on the records' order), one entry per key.
    pub fn reduced(self) -> Vec<LabelSum> {
        let mut records = self.records;
        if self.sorted {
            return records;
        }
        records.par_sort_unstable_by_key(|e| (u64::from(e.gaussian) << 32) | u64::from(e.label));
        records.dedup_by(|next, kept| {
            if (next.gaussian, next.label) == (kept.gaussian, kept.label) {
                kept.sum += next.sum;
                true
            } else {
                false
            }
        });
        records
    }
}

/// The intrinsics of the weight raster for a photo's full-resolution `intrinsics` at `scale`
/// (`--raster-scale`, in (0, 4]): [`Intrinsics::scaled`], after checking the scale.
///
/// Errors: [`Error::Param`] `raster_scale` for a non-finite or out-of-range scale; as
/// [`validate_raster`].
pub fn raster_intrinsics(intrinsics: &Intrinsics, scale: f64) -> Result<Intrinsics> {
    if !(scale.is_finite() && scale > 0.0 && scale <= 4.0) {
        return Err(Error::param(
            "raster_scale",
            scale,
            "a value in (0, 4], e.g. 0.5",
        ));
    }
    let k = intrinsics.scaled(scale);
    validate_raster(&k)?;
    Ok(k)
}

/// Checks a raster's intrinsics: non-zero size, at most 2^28 pixels, finite positive focal lengths.
///
/// Errors: an empty raster ([`Error::Param`] `raster_size`), more than 2^28 pixels
/// ([`Error::Limit`] [`slag_common::Resource::RasterPixels`]), bad focal lengths
/// ([`Error::Invalid`]).
pub(crate) fn validate_raster(k: &Intrinsics) -> Result<()> {
    let n = k.width as u64 * k.height as u64;
    if n == 0 {
        return Err(Error::param(
            "raster_size",
            format!("{}x{}", k.width, k.height),
            "a raster of at least one pixel (a larger raster_scale)",
        ));
    }
    if n > (1 << 28) {
        return Err(Error::limit(
            slag_common::Resource::RasterPixels,
            format!("{}x{} = {n} pixels", k.width, k.height),
            "2^28 pixels",
        ));
    }
    let ok = |v: f64| v.is_finite();
    if !(ok(k.fx) && ok(k.fy) && k.fx > 0.0 && k.fy > 0.0 && ok(k.cx) && ok(k.cy)) {
        return Err(Error::Invalid(format!(
            "camera intrinsics must be finite with positive focal lengths, got {k:?}; check the camera file"
        )));
    }
    Ok(())
}
