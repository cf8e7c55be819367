//! Coverage selection: a cheap weight-raster pass over the training views, then a greedy choice
//! of views until every observed Gaussian is seen from enough distinct viewpoints.
//!
//! **The pass.** Each candidate view is rasterized at [`CoverageRule::raster_scale`] (no masks,
//! no models): every Gaussian's total blend weight in the view, `W_kv = Σ_p w_kp`, converted to
//! pixels of the full-resolution image (÷ scale²). View `v` *sees* Gaussian `k` when
//! `W_kv ≥` the floor (below). Only these sets are kept ([`ViewCoverage`]): per view
//! the sorted Gaussian ids or a bitset of the scene, whichever is smaller, so memory is at most
//! `views × Gaussians / 8` bytes (62.5 MB at 2M Gaussians × 250 views), never a dense weight
//! matrix. With the GPU rasterizer the sums stay on the device: per Gaussian the label sums' total
//! with every pixel in one label (exact 64-bit fixed point, so a view's set does not depend on
//! threads or order), compared with the floor there; a view reads back one bit per Gaussian, and
//! the largest totals, for the footprints, are read once at the end
//! ([`WeightRasterizer::coverage_view`]).
//!
//! **The floor.** [`CoverageRule::min_weight`] when given; otherwise the scene's own. Blend
//! weights share a view's pixels: a view of `P` pixels gives its Gaussians at most `P` pixels of
//! weight in all, so in a scene with more Gaussians than pixels (30M Gaussians on a 990 × 742
//! image) few or none reach a pixel each, and a fixed floor of one pixel would see nothing. The
//! pass first rasterizes [`CALIBRATION_VIEWS`] candidates evenly spaced in name order (all of
//! them when there are fewer) without a floor, takes each Gaussian they show at all its
//! largest weight among them, and sets the floor to the median of those, capped at
//! [`DEFAULT_FLOOR_PX`] (one pixel). Where most Gaussians reach a pixel, as in an ordinary
//! capture, the floor is that pixel and the choice is the fixed rule's; where they do not, at
//! least about half the Gaussians the calibration views show clear it, at any density. The
//! footprints' fixed point follows the floor (a step is 1/256 of it, [`FOOTPRINT_STEPS_PER_PIXEL`]).
//! A pass whose views see no Gaussian at all is refused ([`Error::Unobserved`]): it would choose
//! no view and make an empty map.
//!
//! **The rule.** Views `u` and `v` are *distinct viewpoints* of Gaussian `k` when the directions
//! from their camera centres to `k`'s mean differ by at least [`CoverageRule::min_angle_deg`].
//! A Gaussian is covered when [`CoverageRule::min_views`] pairwise distinct viewpoints among the
//! chosen views see it, or, when the candidates cannot give it that many, as many as they give.
//! Distinct directions are what make a second view worth encoding: a mask boundary or an
//! occlusion seen from the same place is the same error twice, so a view that repeats another
//! adds nothing (a duplicate view is never picked twice), while one from elsewhere averages it out.
//!
//! **What a pair is worth.** A Gaussian matters as much as the image area it takes: its
//! *footprint* is its largest total blend weight in any candidate view, `F_k = max_v W_kv`
//! (full-resolution pixels, the pass's own figures). A (Gaussian, viewpoint) pair is worth the
//! Gaussian's footprint, so a Gaussian that no view shows on more than a pixel or two is worth
//! a pixel or two, not as much as one that fills part of every image. Footprints are kept in
//! fixed point, 1/256 of the floor.
//!
//! **The greedy.** Each step takes the view that adds the most footprint over its new (Gaussian,
//! distinct viewpoint) pairs, ties to the lower name-sorted index (lazy evaluation: a view's gain
//! never grows as views are chosen, so re-evaluating only the top is exact; the stale views on
//! top are re-evaluated together, one per thread, which changes no choice). It runs until no
//! view adds a pair, or, without a [`CoverageRule::target`] below 1, until the first view the
//! stopping rule refuses (below): the gains only fall, so no later view would be kept, and on a
//! ring of a thousand near-duplicate views most of the order lies past that point. Gains are integer sums of the fixed-point footprints, so the order is the
//! same for any thread count.
//!
//! **The stopping rule.** Every view costs the encode the same (its masks, crops and raster),
//! while the gains of the greedy order only fall: the first view gives every Gaussian it shows a
//! viewpoint, the last ones a second viewpoint to a few edge Gaussians. The encode keeps the views
//! of the order while a view adds at least [`CoverageRule::min_gain`] of what the first view
//! added (default 0.02: a view is encoded while it is worth at least 1/50 of the first, that is
//! while its coverage per encoded view costs at most 50 times the first view's). Where the gains
//! fall off a knee (a ring of near-duplicate views, a scene seen all round by a few views) this
//! stops past the knee; where every view shows a new part of the scene, no view's gain falls
//! that far and every view is kept. The rule reads only the scene's own coverage curve, no
//! count. Two further bounds can stop it earlier: the footprint-weighted fraction
//! [`CoverageRule::target`] of all the pairs (default 1: no bound) and
//! [`super::ViewSelection::count`] views.

use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::time::Instant;

use glam::DVec3;
use indicatif::ProgressBar;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use slag_common::camera::{Intrinsics, View, WorldToCamera};
use slag_common::scene::Gaussians;
use slag_common::{Error, Observation, Result};

use crate::raster::WeightRasterizer;

mod greedy;
#[cfg(test)]
mod greedy_tests;

use greedy::Gain;
pub(super) use greedy::{AtOnce, greedy};

/// The stopping rule of coverage selection (module doc).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CoverageRule {
    /// Blend weight a view must give a Gaussian to see it: `Σ_p w_kp` over the view's pixels,
    /// in pixels of the full-resolution image. `None` (the default): the scene's own floor, the
    /// lower of [`DEFAULT_FLOOR_PX`] and the median footprint of a calibration sample (module
    /// doc); a value: that floor, whatever the scene.
    pub min_weight: Option<f64>,
    /// Distinct viewpoints that must see each observed Gaussian (default 2).
    pub min_views: usize,
    /// Angle between two views' directions to a Gaussian, degrees, from which they count as
    /// distinct viewpoints of it (default 10; 0: any two views are distinct).
    pub min_angle_deg: f64,
    /// Fraction of the (Gaussian, viewpoint) pairs the rule asks for, each weighted by the
    /// Gaussian's footprint (module doc), after which no further view is chosen, in (0, 1]
    /// (default 1: no bound; the views stop at [`CoverageRule::min_gain`]).
    pub target: f64,
    /// The stopping rule: a view of the greedy order is kept while it adds at least this fraction
    /// of the footprint-weighted pairs the first view added, in [0, 1] (default 0.02; 0: every
    /// view that adds any pair).
    pub min_gain: f64,
    /// Raster resolution of the pass relative to the images, in (0, 4] (default 0.25).
    pub raster_scale: f64,
}

impl Default for CoverageRule {
    fn default() -> Self {
        CoverageRule {
            min_weight: None,
            min_views: 2,
            min_angle_deg: 10.0,
            target: 1.0,
            min_gain: 0.02,
            raster_scale: 0.25,
        }
    }
}

/// Most distinct viewpoints [`CoverageRule::min_views`] may ask for (the greedy keeps that many
/// view indices per Gaussian).
pub const MAX_MIN_VIEWS: usize = 16;

impl CoverageRule {
    /// Checks the rule's settings.
    ///
    /// Errors: [`Error::Param`] `view_coverage_weight` (not finite or < 0),
    /// `view_coverage_min_views` (outside 1..=[`MAX_MIN_VIEWS`]), `view_coverage_angle` (outside
    /// [0, 180)), `view_coverage_target` (outside (0, 1]), `view_coverage_min_gain` (outside
    /// [0, 1]), `view_coverage_raster_scale` (outside (0, 4]).
    pub fn validate(&self) -> Result<()> {
        if let Some(w) = self.min_weight
            && !(w.is_finite() && w >= 0.0)
        {
            return Err(Error::param(
                "view_coverage_weight",
                w,
                "a weight >= 0, in pixels of the full-resolution image (e.g. 1)",
            ));
        }
        if !(1..=MAX_MIN_VIEWS).contains(&self.min_views) {
            return Err(Error::param(
                "view_coverage_min_views",
                self.min_views,
                format!("a count in 1..={MAX_MIN_VIEWS}"),
            ));
        }
        let a = self.min_angle_deg;
        if !(a.is_finite() && (0.0..180.0).contains(&a)) {
            return Err(Error::param(
                "view_coverage_angle",
                a,
                "an angle in [0, 180) degrees (e.g. 10; 0: any two views)",
            ));
        }
        let t = self.target;
        if !(t.is_finite() && t > 0.0 && t <= 1.0) {
            return Err(Error::param(
                "view_coverage_target",
                t,
                "a fraction in (0, 1] (1: every pair the rule asks for)",
            ));
        }
        let g = self.min_gain;
        if !(g.is_finite() && (0.0..=1.0).contains(&g)) {
            return Err(Error::param(
                "view_coverage_min_gain",
                g,
                "a fraction in [0, 1] of the first view's gain (e.g. 0.02; 0: every view that \
                 adds a pair)",
            ));
        }
        let s = self.raster_scale;
        if !(s.is_finite() && s > 0.0 && s <= 4.0) {
            return Err(Error::param(
                "view_coverage_raster_scale",
                s,
                "a value in (0, 4], e.g. 0.25",
            ));
        }
        Ok(())
    }
}

/// The Gaussians one view sees: sorted ids, or a bitset over the scene when that is smaller.
#[derive(Debug, Clone, PartialEq, Eq)]
enum SeenSet {
    Ids(Vec<u32>),
    Bits(Vec<u64>),
}

impl SeenSet {
    /// The set of the ascending `ids` over a scene of `n` Gaussians, in its smaller form.
    fn new(ids: Vec<u32>, n: usize) -> Self {
        if ids.len() * 32 <= n {
            return SeenSet::Ids(ids);
        }
        let mut bits = vec![0u64; n.div_ceil(64)];
        for id in ids {
            bits[id as usize / 64] |= 1 << (id % 64);
        }
        SeenSet::Bits(bits)
    }

    /// The set of the bitset `words` (bit `k % 64` of word `k / 64`, no bit at `n` or past it)
    /// over a scene of `n` Gaussians, in the form [`SeenSet::new`] would give it.
    fn from_bits(mut words: Vec<u64>, n: usize) -> Self {
        words.truncate(n.div_ceil(64));
        let count: usize = words.iter().map(|w| w.count_ones() as usize).sum();
        if count * 32 > n {
            return SeenSet::Bits(words);
        }
        let mut ids = Vec::with_capacity(count);
        SeenSet::Bits(words).for_each_in(0, n, |k| ids.push(k as u32));
        SeenSet::Ids(ids)
    }

    /// Gaussians in the set.
    fn len(&self) -> usize {
        match self {
            SeenSet::Ids(v) => v.len(),
            SeenSet::Bits(v) => v.iter().map(|w| w.count_ones() as usize).sum(),
        }
    }

    /// Bytes held.
    fn bytes(&self) -> usize {
        match self {
            SeenSet::Ids(v) => v.len() * 4,
            SeenSet::Bits(v) => v.len() * 8,
        }
    }

    /// Calls `f` with every id in `lo..hi` (`lo` a multiple of 64), ascending.
    fn for_each_in(&self, lo: usize, hi: usize, mut f: impl FnMut(usize)) {
        match self {
            SeenSet::Ids(ids) => {
                let start = ids.partition_point(|&i| (i as usize) < lo);
                for &id in ids[start..].iter().take_while(|&&i| (i as usize) < hi) {
                    f(id as usize);
                }
            }
            SeenSet::Bits(words) => {
                let end = hi.div_ceil(64).min(words.len());
                for (w, &word) in words.iter().enumerate().take(end).skip(lo / 64) {
                    let mut bits = word;
                    while bits != 0 {
                        let id = w * 64 + bits.trailing_zeros() as usize;
                        if id < hi {
                            f(id);
                        }
                        bits &= bits - 1;
                    }
                }
            }
        }
    }

    /// Every id, ascending.
    fn ids(&self, n: usize) -> Vec<usize> {
        let mut out = Vec::new();
        self.for_each_in(0, n, |i| out.push(i));
        out
    }
}

/// Fixed-point steps of a footprint per full-resolution pixel at a floor of a pixel or more
/// ([`ViewCoverage::footprint`]); a floor `F` below a pixel gets `256 / F` steps to the pixel
/// (at most `256 / FINEST_FLOOR_PX`), so that a step stays 1/256 of the floor.
pub const FOOTPRINT_STEPS_PER_PIXEL: f64 = 256.0;

/// The finest floor the footprints' steps follow (full-resolution pixels): below it a step
/// stays `FINEST_FLOOR_PX / 256` pixels.
const FINEST_FLOOR_PX: f64 = 1.0 / 65_536.0;

/// The highest floor the scene's own ([`CoverageRule::min_weight`] `None`) takes: a pixel's worth
/// of a Gaussian, full-resolution pixels.
pub const DEFAULT_FLOOR_PX: f64 = 1.0;

/// Candidate views, evenly spaced in name order, whose footprints set the scene's floor (all of
/// them when there are fewer).
pub const CALIBRATION_VIEWS: usize = 16;

/// Where the pass's floor came from (`report.json`'s `view_selection.coverage.floor_source`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum FloorSource {
    /// The rule's [`CoverageRule::min_weight`].
    Given,
    /// [`DEFAULT_FLOOR_PX`]: the calibration views' median footprint reaches it (or they show
    /// no Gaussian).
    Default,
    /// The calibration views' median footprint, below [`DEFAULT_FLOOR_PX`]: a scene dense in
    /// Gaussians per pixel.
    Median,
}

/// What the coverage pass measured: per candidate view the Gaussians it sees (weight ≥ the
/// floor), in a sparse or bitset form, and per Gaussian its footprint (module doc).
#[derive(Debug, Clone, PartialEq)]
pub struct ViewCoverage {
    gaussians: usize,
    seen: Vec<SeenSet>,
    /// Per Gaussian the largest total blend weight a view that sees it gives it, in
    /// 1/`steps_per_px` full-resolution pixels (at least 1 for a seen Gaussian, 0 for one no
    /// view sees).
    footprint: Vec<u64>,
    /// The floor a view's weight had to reach: full-resolution pixels.
    floor_px: f64,
    /// Where the floor came from.
    floor_source: FloorSource,
    /// Footprint steps per full-resolution pixel ([`FOOTPRINT_STEPS_PER_PIXEL`]).
    steps_per_px: f64,
}

impl ViewCoverage {
    /// The Gaussians view `v` sees, ascending (for tests and tools).
    pub fn seen_by(&self, v: usize) -> Vec<usize> {
        self.seen
            .get(v)
            .map_or_else(Vec::new, |s| s.ids(self.gaussians))
    }

    /// Gaussian `k`'s footprint: its largest total blend weight in a view that sees it,
    /// full-resolution pixels (0 when no view sees it).
    pub fn footprint(&self, k: usize) -> f64 {
        self.footprint
            .get(k)
            .map_or(0.0, |&q| q as f64 / self.steps_per_px)
    }

    /// The floor a view's weight had to reach for the view to see a Gaussian: full-resolution
    /// pixels, and where it came from.
    pub fn floor(&self) -> (f64, FloorSource) {
        (self.floor_px, self.floor_source)
    }

    /// Gaussians some view sees.
    pub fn observed(&self) -> usize {
        self.footprint.iter().filter(|&&f| f > 0).count()
    }

    /// Candidate views measured.
    pub fn views(&self) -> usize {
        self.seen.len()
    }

    /// Bytes the per-view sets and the footprints hold.
    pub fn bytes(&self) -> usize {
        self.seen.iter().map(SeenSet::bytes).sum::<usize>() + self.footprint.len() * 8
    }
}

/// The coverage pass: the Gaussians each of `views` sees under `rule` and their footprints, the
/// views spread over `rasterizers` (one thread each, views taken in turn; each view's set depends
/// on that view alone and a footprint is a maximum over views, so the result does not depend on
/// how they were spread). `gaussians` is the scene's Gaussian count, the rasterizers' scene.
/// Without a [`CoverageRule::min_weight`], the floor is the scene's own ([`scene_floor`]).
///
/// Errors: [`Error::Param`] `view_coverage_raster_scale` or `raster_size` for a raster the scale
/// cannot make; the rasterizers' errors (the first one); [`Error::Param`] `rasterizers` when
/// there is none.
pub fn measure(
    rasterizers: &mut [Box<dyn WeightRasterizer>],
    views: &[View],
    gaussians: usize,
    rule: &CoverageRule,
) -> Result<ViewCoverage> {
    measure_shown(rasterizers, views, gaussians, rule, &ProgressBar::hidden())
}

/// [`measure`], each view rasterized counted on `progress` (its length set to the views).
///
/// Errors: as [`measure`].
pub fn measure_shown(
    rasterizers: &mut [Box<dyn WeightRasterizer>],
    views: &[View],
    gaussians: usize,
    rule: &CoverageRule,
    progress: &ProgressBar,
) -> Result<ViewCoverage> {
    if rasterizers.is_empty() {
        return Err(Error::param("rasterizers", 0, "at least one rasterizer"));
    }
    let intrinsics = views
        .iter()
        .map(|v| pass_intrinsics(&v.intrinsics, rule.raster_scale))
        .collect::<Result<Vec<_>>>()?;
    let pass = Pass {
        views,
        intrinsics: &intrinsics,
        gaussians,
        // A raster pixel is 1/scale² full-resolution ones.
        area: rule.raster_scale * rule.raster_scale,
    };
    let (floor_px, floor_source) = match rule.min_weight {
        Some(w) => (w, FloorSource::Given),
        None => scene_floor(rasterizers, &pass)?,
    };
    let steps_per_px = FOOTPRINT_STEPS_PER_PIXEL / floor_px.clamp(FINEST_FLOOR_PX, 1.0);
    progress.set_length(views.len() as u64);
    let results: Mutex<Vec<Option<SeenSet>>> = Mutex::new(vec![None; views.len()]);
    let footprint: Vec<AtomicU64> = (0..gaussians).map(|_| AtomicU64::new(0)).collect();
    let all: Vec<usize> = (0..views.len()).collect();
    let footprint_of = |w: f64| footprint_steps(w / pass.area, steps_per_px);
    pass.run(rasterizers, &all, floor_px * pass.area, |i, seen| {
        let set = match seen {
            SeenView::Weighed(seen) => {
                for &(id, w) in &seen {
                    footprint[id as usize].fetch_max(footprint_of(w), Ordering::Relaxed);
                }
                SeenSet::new(seen.into_iter().map(|(id, _)| id).collect(), gaussians)
            }
            SeenView::Bits(words) => SeenSet::from_bits(words, gaussians),
        };
        if let Ok(mut out) = results.lock() {
            out[i] = Some(set);
        }
        progress.inc(1);
    })?;
    // The device's maxima of the views that saw each Gaussian: the footprint is monotone in the
    // weight, so the footprint of the maximum is the maximum of the footprints.
    fold_device_maxima(rasterizers, |k, w| {
        footprint[k].fetch_max(footprint_of(w), Ordering::Relaxed);
    })?;
    let seen = results
        .into_inner()
        .map_err(|_| Error::internal("coverage pass: a rasterizer thread panicked"))?
        .into_iter()
        .collect::<Option<Vec<_>>>()
        .ok_or_else(|| Error::internal("coverage pass: a view was not rasterized"))?;
    Ok(ViewCoverage {
        gaussians,
        seen,
        footprint: footprint.into_iter().map(AtomicU64::into_inner).collect(),
        floor_px,
        floor_source,
        steps_per_px,
    })
}

/// Hands `fold(Gaussian, weight)` every non-zero maximum the `rasterizers` kept over the views
/// of a pass ([`WeightRasterizer::take_coverage_maxima`]; weights in raster pixels), and clears
/// them.
///
/// Errors: the rasterizers' (the first one).
fn fold_device_maxima(
    rasterizers: &mut [Box<dyn WeightRasterizer>],
    fold: impl Fn(usize, f64) + Sync,
) -> Result<()> {
    for r in rasterizers.iter_mut() {
        if let Some(maxima) = r.take_coverage_maxima()? {
            maxima.par_iter().enumerate().for_each(|(k, &m)| {
                if m > 0 {
                    fold(k, m as f64 / FIXED_ONE);
                }
            });
        }
    }
    Ok(())
}

/// One pixel of blend weight in the label sums' and the coverage totals' fixed point.
const FIXED_ONE: f64 = 4_294_967_296.0;

/// The candidate views of one pass and their rasters.
struct Pass<'a> {
    views: &'a [View],
    /// Each view's raster at the pass's scale.
    intrinsics: &'a [Intrinsics],
    /// The scene's Gaussian count.
    gaussians: usize,
    /// Full-resolution pixels per raster pixel, inverted: `scale²`.
    area: f64,
}

impl Pass<'_> {
    /// Rasterizes the views at positions `which` on `rasterizers` and hands each view's
    /// Gaussians of weight ≥ `floor` raster pixels ([`ViewSums::seen`]) to `take(position,
    /// seen)` (a rasterizer that keeps them on the device hands on their ids only, and keeps
    /// their largest weights for [`fold_device_maxima`]). Each rasterizer is a pipeline of three threads, so that its device never waits on
    /// the host: one takes the next view in turn and does its host work ahead
    /// ([`WeightRasterizer::view_precompute`]), one drives the rasterizer, one reduces the
    /// view's sums to its seen Gaussians and hands them on. Stops at the first error and
    /// returns it.
    fn run(
        &self,
        rasterizers: &mut [Box<dyn WeightRasterizer>],
        which: &[usize],
        floor: f64,
        take: impl Fn(usize, SeenView) + Sync,
    ) -> Result<()> {
        let next = AtomicUsize::new(0);
        let failure = PassFailure::default();
        std::thread::scope(|s| {
            for r in rasterizers.iter_mut() {
                let ahead = r.view_precompute();
                let (pre_tx, pre_rx) = std::sync::mpsc::sync_channel(1);
                let (sums_tx, sums_rx) = std::sync::mpsc::sync_channel::<(usize, ViewSums)>(1);
                let (next, failure, take) = (&next, &failure, &take);
                s.spawn(move || {
                    while !failure.failed() {
                        let Some(&i) = which.get(next.fetch_add(1, Ordering::SeqCst)) else {
                            break;
                        };
                        let w2c = &self.views[i].world_to_camera;
                        let pre = ahead.as_ref().map(|a| a.precompute(w2c));
                        if pre_tx.send((i, pre)).is_err() {
                            break;
                        }
                    }
                });
                s.spawn(move || {
                    for (i, pre) in pre_rx {
                        let (v, k) = (&self.views[i], &self.intrinsics[i]);
                        match view_sums(r.as_mut(), k, &v.world_to_camera, pre, floor) {
                            Ok(sums) => {
                                if sums_tx.send((i, sums)).is_err() {
                                    break;
                                }
                            }
                            Err(e) => {
                                failure.fail(e);
                                break;
                            }
                        }
                    }
                });
                s.spawn(move || {
                    for (i, sums) in sums_rx {
                        if !failure.failed() {
                            take(i, sums.seen(floor, self.gaussians));
                        }
                    }
                });
            }
        });
        failure.into_result()
    }
}

/// The first error of a pass's threads; once set, they stop taking views.
#[derive(Default)]
struct PassFailure {
    failed: AtomicBool,
    first: Mutex<Option<Error>>,
}

impl PassFailure {
    fn failed(&self) -> bool {
        self.failed.load(Ordering::SeqCst)
    }

    fn fail(&self, e: Error) {
        self.failed.store(true, Ordering::SeqCst);
        if let Ok(mut slot) = self.first.lock() {
            slot.get_or_insert(e);
        }
    }

    fn into_result(self) -> Result<()> {
        match self.first.into_inner().ok().flatten() {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }
}

/// The floor a rule without [`CoverageRule::min_weight`] uses (full-resolution pixels), and
/// where it came from: the median footprint (the largest weight any of them gives it) of the
/// Gaussians that [`CALIBRATION_VIEWS`] evenly spaced candidates show at all, capped at
/// [`DEFAULT_FLOOR_PX`]; the cap when they show none.
///
/// Errors: the rasterizers' (the first one).
fn scene_floor(
    rasterizers: &mut [Box<dyn WeightRasterizer>],
    pass: &Pass,
) -> Result<(f64, FloorSource)> {
    let sample = super::uniform(pass.views.len(), CALIBRATION_VIEWS);
    // A positive f64's bits order as the value does: the maximum of the bits is the bits of
    // the maximum.
    let best: Vec<AtomicU64> = (0..pass.gaussians).map(|_| AtomicU64::new(0)).collect();
    pass.run(rasterizers, &sample, 0.0, |_, seen| {
        if let SeenView::Weighed(seen) = seen {
            for (id, w) in seen {
                best[id as usize].fetch_max(w.to_bits(), Ordering::Relaxed);
            }
        }
    })?;
    fold_device_maxima(rasterizers, |k, w| {
        best[k].fetch_max(w.to_bits(), Ordering::Relaxed);
    })?;
    let mut shown: Vec<f64> = best
        .into_iter()
        .map(|b| f64::from_bits(b.into_inner()))
        .filter(|&w| w > 0.0)
        .collect();
    if shown.is_empty() {
        return Ok((DEFAULT_FLOOR_PX, FloorSource::Default));
    }
    let mid = (shown.len() - 1) / 2;
    let (_, &mut median, _) = shown.select_nth_unstable_by(mid, f64::total_cmp);
    let median_px = median / pass.area;
    Ok(if median_px < DEFAULT_FLOOR_PX {
        (median_px, FloorSource::Median)
    } else {
        (DEFAULT_FLOOR_PX, FloorSource::Default)
    })
}

/// A seen Gaussian's weight in full-resolution pixels as footprint steps of `steps_per_px` to
/// the pixel (at least 1).
fn footprint_steps(pixels: f64, steps_per_px: f64) -> u64 {
    ((pixels * steps_per_px).round() as u64).max(1)
}

/// The pass's raster intrinsics of a view, naming the pass's own scale in errors.
fn pass_intrinsics(k: &Intrinsics, scale: f64) -> Result<Intrinsics> {
    crate::raster::raster_intrinsics(k, scale).map_err(|e| match e {
        Error::Param {
            name: "raster_scale",
            value,
            expected,
        } => Error::Param {
            name: "view_coverage_raster_scale",
            value,
            expected,
        },
        e => e,
    })
}

/// One view's blend weights as a rasterizer gave them: the Gaussians at the floor, found on
/// the device ([`WeightRasterizer::coverage_view`]); per-label sums (every pixel in label 1);
/// or, for a rasterizer without either, its per-pixel lists.
enum ViewSums {
    Seen(Vec<u64>),
    Sums(crate::raster::LabelSums),
    Lists(crate::raster::PixelWeights),
}

/// The Gaussians a view sees, as [`ViewSums::seen`] hands them on.
enum SeenView {
    /// Ascending ids, each with its total blend weight in the view (raster pixels).
    Weighed(Vec<(u32, f64)>),
    /// A bitset over the scene (bit `k % 64` of word `k / 64`); the weights stayed on the
    /// device ([`fold_device_maxima`]).
    Bits(Vec<u64>),
}

/// View `w2c`'s weights on raster `k` ([`ViewSums`]) for a floor of `floor` raster pixels,
/// with its host work `pre` done ahead.
///
/// Errors: the rasterizer's.
fn view_sums(
    r: &mut dyn WeightRasterizer,
    k: &Intrinsics,
    w2c: &WorldToCamera,
    pre: Option<crate::raster::PrecomputedView>,
    floor: f64,
) -> Result<ViewSums> {
    if let Some(bits) = r.coverage_view(k, w2c, fixed_floor(floor), pre)? {
        return Ok(ViewSums::Seen(bits));
    }
    // A rasterizer without the device's pass has no host work ahead either.
    let labels = vec![1u32; k.width as usize * k.height as usize];
    match r.label_sums_precomputed(k, w2c, &labels, None)? {
        Some(sums) => Ok(ViewSums::Sums(sums)),
        None => Ok(ViewSums::Lists(r.rasterize(k, w2c)?)),
    }
}

/// A floor of `floor` raster pixels in the label sums' fixed point, at least 1 (a Gaussian
/// must contribute).
fn fixed_floor(floor: f64) -> u64 {
    ((floor * FIXED_ONE).ceil() as u64).max(1)
}

impl ViewSums {
    /// The Gaussians whose total blend weight in the view is at least `floor` (raster pixels):
    /// the device's bitset as it came; or, ascending by id with that weight (raster pixels),
    /// the label sums compared in their own fixed point (exact), or the per-pixel lists summed
    /// per Gaussian (f64, pixel order) over a scene of `gaussians`.
    fn seen(self, floor: f64, gaussians: usize) -> SeenView {
        SeenView::Weighed(match self {
            ViewSums::Seen(bits) => return SeenView::Bits(bits),
            ViewSums::Sums(sums) => {
                let floor_fixed = fixed_floor(floor);
                sums.reduced()
                    .into_iter()
                    .filter(|s| s.sum >= floor_fixed)
                    .map(|s| (s.gaussian, s.sum as f64 / FIXED_ONE))
                    .collect()
            }
            ViewSums::Lists(w) => {
                let mut total = vec![0f64; gaussians];
                for (&id, &wt) in w.ids.iter().zip(&w.weights) {
                    if let Some(t) = total.get_mut(id as usize) {
                        *t += f64::from(wt);
                    }
                }
                total
                    .iter()
                    .enumerate()
                    .filter(|&(_, &t)| t > 0.0 && t >= floor)
                    .map(|(i, &t)| (i as u32, t))
                    .collect()
            }
        })
    }
}

/// One step of the greedy order.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct GreedyStep {
    /// The view's name.
    pub view: String,
    /// (Gaussian, distinct viewpoint) pairs it added.
    pub gain: u64,
    /// The footprints of the Gaussians of those pairs, summed: full-resolution pixels (what the
    /// greedy ranks and the stopping rule reads).
    pub gain_px: f64,
}

/// Why the chosen views end where they do (`report.json`'s `view_selection.coverage.stop`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum CoverageStop {
    /// The next view adds less than [`CoverageRule::min_gain`] of the first view's gain.
    MinGain,
    /// The chosen views give [`CoverageRule::target`] of the footprint-weighted pairs.
    Target,
    /// [`super::ViewSelection::count`] views are chosen.
    Count,
    /// Every view that adds a pair is chosen.
    Exhausted,
}

/// What the coverage pass found and chose (`report.json`'s `view_selection.coverage`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CoverageOutcome {
    /// The rule that ran.
    pub rule: CoverageRule,
    /// Seconds rasterizing the candidates.
    pub raster_s: f64,
    /// Seconds of the greedy choice.
    pub greedy_s: f64,
    /// Bytes of the per-view sets the greedy read.
    pub seen_bytes: u64,
    /// The floor a view's blend weight had to reach to see a Gaussian: full-resolution pixels
    /// (the rule's `min_weight`, or the scene's own floor).
    pub floor_px: f64,
    /// Where the floor came from.
    pub floor_source: FloorSource,
    /// Gaussians some candidate sees (the observed ones the rule covers).
    pub observed: usize,
    /// Of those, the Gaussians some chosen view sees.
    pub observed_chosen: usize,
    /// (Gaussian, distinct viewpoint) pairs the rule asks for: per observed Gaussian
    /// `min_views`, or fewer when the candidates cannot give that many.
    pub pairs_wanted: u64,
    /// Of those, the pairs the chosen views give.
    pub pairs_chosen: u64,
    /// The pairs the rule asks for, each weighted by its Gaussian's footprint: full-resolution
    /// pixels.
    pub pairs_wanted_px: f64,
    /// Of those, the chosen views' share: full-resolution pixels.
    pub pairs_chosen_px: f64,
    /// Why the chosen views end there.
    pub stop: CoverageStop,
    /// Observed Gaussians to which the greedy assigned `min_views` distinct viewpoints among the
    /// chosen views (a lower bound: a maximal set per Gaussian, not always the largest).
    pub full_views: usize,
    /// Observed Gaussians that the chosen views cover as far as the candidates allow.
    pub covered: usize,
    /// The greedy order (the chosen views are its first ones): until no view added a pair, or,
    /// without a [`CoverageRule::target`] below 1, until the first view the stopping rule
    /// refused (or one past the count).
    pub order: Vec<GreedyStep>,
    /// Whether `order` runs until no view adds a pair. When it stops where the choice did, the
    /// figures read from the order (`pairs_wanted`, `pairs_wanted_px`, `covered`) count only
    /// its views: the greedy's later views would add pairs, and viewpoints to Gaussians.
    pub order_complete: bool,
}

/// How many views of the greedy `order` the rule keeps (module doc), cut at `cap`, and why.
fn stop_at(
    order: &[(usize, Gain)],
    rule: &CoverageRule,
    cap: Option<usize>,
) -> (usize, CoverageStop) {
    let wanted: u64 = order.iter().map(|&(_, g)| g.0).sum();
    let first = order.first().map_or(0, |&(_, g)| g.0);
    let mut chosen = 0u64;
    for (taken, &(_, g)) in order.iter().enumerate() {
        if cap.is_some_and(|c| taken >= c) {
            return (taken, CoverageStop::Count);
        }
        if chosen as f64 >= rule.target * wanted as f64 {
            return (taken, CoverageStop::Target);
        }
        if (g.0 as f64) < rule.min_gain * first as f64 {
            return (taken, CoverageStop::MinGain);
        }
        chosen += g.0;
    }
    (order.len(), CoverageStop::Exhausted)
}

/// Coverage selection over `views` (the training views, name-sorted): the pass on
/// `rasterizers` ([`measure`]), the greedy order, and the prefix the stopping rule keeps (module
/// doc), cut at `cap` views. Returns the chosen positions in `views`, ascending, and
/// what the pass found.
///
/// Errors: as [`CoverageRule::validate`] and [`measure`]; [`Error::Param`] `views` for more
/// than 2^32 − 1 views; [`Error::Unobserved`] when no candidate sees any Gaussian (no view would
/// be chosen).
pub fn select(
    rasterizers: &mut [Box<dyn WeightRasterizer>],
    gaussians: &Gaussians,
    views: &[View],
    rule: &CoverageRule,
    cap: Option<usize>,
) -> Result<(Vec<usize>, CoverageOutcome)> {
    select_shown(
        rasterizers,
        gaussians,
        views,
        rule,
        cap,
        &ProgressBar::hidden(),
    )
}

/// [`select`], the pass's views counted on `progress` ([`measure_shown`]).
///
/// Errors: as [`select`].
pub fn select_shown(
    rasterizers: &mut [Box<dyn WeightRasterizer>],
    gaussians: &Gaussians,
    views: &[View],
    rule: &CoverageRule,
    cap: Option<usize>,
    progress: &ProgressBar,
) -> Result<(Vec<usize>, CoverageOutcome)> {
    rule.validate()?;
    if u32::try_from(views.len()).is_err() {
        return Err(Error::param("views", views.len(), "at most 2^32 - 1 views"));
    }
    let t0 = Instant::now();
    let mut coverage = measure_shown(rasterizers, views, gaussians.len(), rule, progress)?;
    let raster_s = t0.elapsed().as_secs_f64();
    require_observed(&coverage)?;
    let t1 = Instant::now();
    let centres: Vec<DVec3> = views
        .iter()
        .map(|v| v.world_to_camera.camera_centre())
        .collect();
    // Without a target the choice needs the order only up to where it stops.
    let early = (rule.target >= 1.0).then_some(cap);
    let at_once = AtOnce::for_threads();
    let seen_bytes = coverage.bytes() as u64;
    let (order, slots, complete) = greedy(
        &mut coverage,
        &gaussians.means,
        &centres,
        rule,
        early,
        at_once,
    );
    let (taken, stop) = stop_at(&order, rule, cap);
    let mut outcome = outcome_of(&coverage, &order, &slots, taken, views, rule);
    outcome.seen_bytes = seen_bytes;
    outcome.stop = stop;
    outcome.order_complete = complete;
    outcome.raster_s = raster_s;
    outcome.greedy_s = t1.elapsed().as_secs_f64();
    let mut chosen: Vec<usize> = order[..taken].iter().map(|&(v, _)| v).collect();
    chosen.sort_unstable();
    Ok((chosen, outcome))
}

/// Refuses a pass that saw no Gaussian: no view would be chosen, and the map would be empty.
///
/// Errors: [`Error::Unobserved`] ([`Observation::CoveragePass`]).
fn require_observed(coverage: &ViewCoverage) -> Result<()> {
    if coverage.observed() > 0 {
        return Ok(());
    }
    let (floor, source) = coverage.floor();
    let source = match source {
        FloorSource::Given => "the rule's floor",
        FloorSource::Default | FloorSource::Median => "the scene's floor",
    };
    Err(Error::Unobserved {
        stage: Observation::CoveragePass,
        observed: 0,
        gaussians: coverage.gaussians as u64,
        expected: format!(
            "expected some Gaussian with a total blend weight of {floor:.3e} full-resolution \
             pixels ({source}) in one of the {} candidate views; no view would be chosen and \
             the map would be empty",
            coverage.views()
        ),
    })
}

/// What the pass found and the greedy chose, in the report's terms: the `order` of the greedy
/// over `views` with its first `taken` chosen, and the final viewpoint `slots`. Its times and
/// `seen_bytes` are 0 and its stop [`CoverageStop::Exhausted`], for the caller to fill in (the
/// greedy took the sets out of `coverage`).
fn outcome_of(
    coverage: &ViewCoverage,
    order: &[(usize, Gain)],
    slots: &[u32],
    taken: usize,
    views: &[View],
    rule: &CoverageRule,
) -> CoverageOutcome {
    let px = |steps: u64| steps as f64 / coverage.steps_per_px;
    let sum = |steps: &[(usize, Gain)]| {
        steps
            .iter()
            .fold((0, 0), |a, &(_, g)| (a.0 + g.0, a.1 + g.1))
    };
    let (wanted_px, wanted) = sum(order);
    let (chosen_px, pairs_chosen) = sum(&order[..taken]);
    let mut rank = vec![usize::MAX; views.len()];
    for (r, &(v, _)) in order.iter().enumerate() {
        rank[v] = r;
    }
    let t = tally(slots, rule.min_views.max(1), &rank, taken);
    CoverageOutcome {
        rule: *rule,
        raster_s: 0.0,
        greedy_s: 0.0,
        seen_bytes: 0,
        floor_px: coverage.floor_px,
        floor_source: coverage.floor_source,
        observed: coverage.observed(),
        observed_chosen: t.observed_chosen,
        pairs_wanted: wanted,
        pairs_chosen,
        pairs_wanted_px: px(wanted_px),
        pairs_chosen_px: px(chosen_px),
        stop: CoverageStop::Exhausted,
        order_complete: true,
        full_views: t.full_views,
        covered: t.covered,
        order: order
            .iter()
            .map(|&(v, (steps, gain))| GreedyStep {
                view: views[v].name.clone(),
                gain,
                gain_px: px(steps),
            })
            .collect(),
    }
}

/// Counts of the observed Gaussians under a choice ([`tally`]).
#[derive(Debug, Default, Clone, Copy)]
struct Tally {
    /// Those with a chosen viewpoint: some chosen view sees them.
    observed_chosen: usize,
    /// Those with `per` chosen viewpoints.
    full_views: usize,
    /// Those whose every viewpoint is chosen.
    covered: usize,
}

impl std::ops::Add for Tally {
    type Output = Tally;
    fn add(self, b: Tally) -> Tally {
        Tally {
            observed_chosen: self.observed_chosen + b.observed_chosen,
            full_views: self.full_views + b.full_views,
            covered: self.covered + b.covered,
        }
    }
}

/// From the final slots (`per` per Gaussian) and each view's rank in the greedy order, with the
/// first `taken` views chosen: the [`Tally`]. A Gaussian's slots start with the first view of
/// the order that sees it, so a Gaussian some chosen view sees has a chosen viewpoint.
fn tally(slots: &[u32], per: usize, rank: &[usize], taken: usize) -> Tally {
    slots
        .par_chunks(per)
        .map(|s| {
            let all = s.iter().take_while(|&&u| u != u32::MAX).count();
            let chosen = s
                .iter()
                .take_while(|&&u| u != u32::MAX)
                .filter(|&&u| rank[u as usize] < taken)
                .count();
            Tally {
                observed_chosen: usize::from(chosen > 0),
                full_views: usize::from(chosen == per),
                covered: usize::from(all > 0 && chosen == all),
            }
        })
        .reduce(Tally::default, |a, b| a + b)
}
