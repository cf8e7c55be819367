//! Where the image stage's results go: the sinks of the encode's pool (the contribution store,
//! the stores per granularity level, the masks' record of the views recorded on the host, or the
//! host's streamed fold of the mixture) and the host side of one rasterized view that fills them.
//! Apart from the workers that call it ([`super::pool`]) so that either can change alone.

use std::sync::{Mutex, mpsc};
use std::time::Instant;

use slag_common::mask_record::MaskRecord;
use slag_common::{Error, Result};

use super::feed::Forwarded;
use super::{BackRaster, EncodeParams, back_finish};
use crate::aggregate::ContributionStore;
use crate::report::ImageWork;

/// Where the image stage's `a_kj` go: the contribution store; with [`EncodeParams::levels`] one
/// store per granularity level (the same entries, split by level); with
/// [`EncodeParams::mask_record_slots`] the masks' record of the views recorded on the host. Or,
/// with `forward`, each view's `a_kj` and work forwarded as it is done, and nothing stored.
pub(super) struct PoolSinks {
    pub(super) store: Mutex<ContributionStore>,
    pub(super) level_stores: Vec<Mutex<ContributionStore>>,
    pub(super) record: Option<Mutex<HostRecord>>,
    pub(super) forward: Option<mpsc::Sender<Forwarded>>,
}

/// The masks' record of the views whose dominant masks reach the host, made at the first of
/// them: a run whose rasterizers keep the record on their devices
/// ([`WeightRasterizer::keep_mask_record`]) holds none on the host until the end.
pub(super) struct HostRecord {
    pub(super) gaussians: usize,
    pub(super) slots: usize,
    pub(super) views: usize,
    pub(super) record: Option<MaskRecord>,
}

impl HostRecord {
    /// Adds view `view`'s dominant masks ([`MaskRecord::add_view`]).
    ///
    /// Errors: the record's ([`MaskRecord::new`]).
    pub(super) fn add_view(&mut self, view: usize, dominant: &[(u32, u32, f32)]) -> Result<()> {
        if dominant.is_empty() {
            return Ok(());
        }
        let record = match &mut self.record {
            Some(r) => r,
            None => self
                .record
                .insert(MaskRecord::new(self.gaussians, self.slots, self.views)?),
        };
        record.add_view(view, dominant.iter().copied());
        Ok(())
    }
}

impl PoolSinks {
    /// Empty sinks for `n_views` views of `n_gaussians` Gaussians; the stores spill under
    /// [`EncodeParams::out_dir`].
    ///
    /// Errors: [`Error::Param`] `slots` for a record of other than 1 to 64 slots; the host's
    /// fold's ([`folded_mixture`]).
    pub(super) fn new(
        params: &EncodeParams,
        (dim, n_gaussians): (usize, usize),
        n_views: usize,
    ) -> Result<Self> {
        let store = |name: String| {
            Mutex::new(ContributionStore::new(
                params.contribution_budget_bytes,
                params.out_dir.join(name),
            ))
        };
        let level_stores = if params.levels {
            (0..crate::aggregate::levels::LEVELS)
                .map(|l| store(format!(".contributions-level{l}.partial")))
                .collect()
        } else {
            Vec::new()
        };
        let record = match params.mask_record_slots {
            Some(slots) => {
                // The slots are checked now (a record of no Gaussians); the record itself is
                // allocated at its first view.
                MaskRecord::new(0, slots, n_views)?;
                Some(Mutex::new(HostRecord {
                    gaussians: n_gaussians,
                    slots,
                    views: n_views,
                    record: None,
                }))
            }
            None => None,
        };
        let main = if let Some(fold) = folded_dense(params, dim, n_gaussians)? {
            Mutex::new(ContributionStore::folding_dense(fold))
        } else {
            match folded_mixture(params, dim, n_gaussians)? {
                Some(fold) => Mutex::new(ContributionStore::folding(fold)),
                None => store(".contributions.partial".to_string()),
            }
        };
        Ok(PoolSinks {
            store: main,
            level_stores,
            record,
            forward: None,
        })
    }

    /// Sinks that forward each view's `a_kj` and work to `forward` and store nothing (the
    /// store stays empty and never spills).
    pub(super) fn forwarding(forward: mpsc::Sender<Forwarded>) -> Self {
        PoolSinks {
            store: Mutex::new(ContributionStore::new(0, std::path::PathBuf::new())),
            level_stores: Vec::new(),
            record: None,
            forward: Some(forward),
        }
    }
}

/// The host's streamed reduction of an encode that reduces on the host from the start
/// (`--reduce host`) and writes only the mixture: each view folded into a running state per
/// Gaussian as it comes ([`crate::aggregate::MixtureFold`]), none kept. `None` otherwise: the
/// dense file and the level files need every view's `a_kj`, and a run that may keep its views on
/// a device gives them to the store only if it gives way to the host.
///
/// Errors: the fold's ([`crate::aggregate::MixtureFold::new`]).
fn folded_mixture(
    params: &EncodeParams,
    dim: usize,
    n_gaussians: usize,
) -> Result<Option<crate::aggregate::MixtureFold>> {
    let host = params.reduce_on == crate::config::ReduceOn::Host;
    match params.mixture_keep {
        Some(keep)
            if host
                && !params.dense
                && !params.levels
                && keep <= crate::aggregate::MAX_FOLDED_KEEP =>
        {
            let fold = crate::aggregate::MixtureFold::new(
                n_gaussians,
                dim,
                keep,
                params.reduce.min_total_weight,
            )?;
            Ok(Some(fold))
        }
        _ => Ok(None),
    }
}

/// The host's streamed dense reduction of an encode that writes the dense file
/// ([`EncodeParams::dense`], always reduced on the host): each view folded into f64
/// accumulators per Gaussian as it comes ([`crate::aggregate::DenseFold`]), tiled by Gaussian
/// ids within the accumulator budget and spilled to `<out>/.dense-accumulators.partial` past it,
/// the views batched within the contribution budget while tiles are spilled; with the mixture
/// its pairs folded beside. `None` without the dense file, or with a mixture of more pairs per
/// Gaussian than a fold keeps ([`crate::aggregate::MAX_FOLDED_KEEP`]: every view is then kept,
/// spilling past the contribution budget, and reduced at the end).
///
/// Errors: the fold's ([`crate::aggregate::DenseFold::new`]).
fn folded_dense(
    params: &EncodeParams,
    dim: usize,
    n_gaussians: usize,
) -> Result<Option<crate::aggregate::DenseFold>> {
    let keeps_more = params
        .mixture_keep
        .is_some_and(|k| k > crate::aggregate::MAX_FOLDED_KEEP);
    if !params.dense || keeps_more {
        return Ok(None);
    }
    let p = crate::aggregate::DenseFoldParams {
        min_total_weight: params.reduce.min_total_weight,
        accumulator_budget_bytes: params.reduce.accumulator_budget_bytes,
        batch_budget_bytes: params.contribution_budget_bytes,
        spill_dir: params.out_dir.join(".dense-accumulators.partial"),
        mixture_keep: params.mixture_keep,
    };
    crate::aggregate::DenseFold::new(n_gaussians, dim, p).map(Some)
}

/// The image stage's host side of one rasterized view ([`back_finish`]): its `a_kj` pushed to
/// the sinks (split by level with `levels`; each Gaussian's dominant mask to the masks' record),
/// and its work added to `totals`; or, with [`PoolSinks::forward`], both forwarded.
///
/// Errors: the image stage's; the stores' (spill I/O); [`Error::Internal`] for a poisoned lock
/// or a forward whose receiver is gone.
pub(super) fn finish_image(
    raster: BackRaster,
    dim: usize,
    params: &EncodeParams,
    sinks: &PoolSinks,
    totals: &Mutex<ImageWork>,
) -> Result<()> {
    let PoolSinks {
        store,
        level_stores,
        record,
        forward,
    } = sinks;
    let poisoned = |_| Error::internal("contribution store poisoned by a panicked worker");
    let item = &raster.item;
    let (n_masks, decode_s, masks_s, clip_s) =
        (item.masks.len(), item.decode_s, item.masks_s, item.clip_s);
    let mask_levels: Vec<Option<u8>> = item.masks.iter().map(|m| m.level).collect();
    let raster_view = item.view;
    let out = back_finish(raster, dim, params.image_stage)?;
    let t1 = Instant::now();
    let entries = out.contribution.entries.len();
    if let Some(forward) = forward {
        let work = out.work(decode_s, masks_s, clip_s, n_masks, entries);
        let view = (raster_view, work, out.contribution);
        return forward_view(forward, view);
    }
    if let Some(record) = record {
        // Each Gaussian's dominant mask here (or from the device), found outside the record's
        // lock.
        // Kept on the device: the dominant masks reached the host only when the device holds
        // no record (empty otherwise).
        let computed;
        let dominant = match &out.dominant {
            Some(d) => d,
            None => {
                computed = dominant_masks(&out.contribution.entries);
                &computed
            }
        };
        record
            .lock()
            .map_err(|_| Error::internal("masks' record poisoned by a panicked worker"))?
            .add_view(raster_view, dominant)?;
    }
    let mut work = out.work(decode_s, masks_s, clip_s, n_masks, entries);
    if !level_stores.is_empty() {
        let parts = crate::aggregate::levels::split_by_level(&out.contribution, &mask_levels)?;
        for (part, ls) in parts.into_iter().zip(level_stores) {
            let part = crate::aggregate::store::StoredImage::from_contribution(part);
            ls.lock()
                .map_err(poisoned)?
                .push_stored_as(raster_view, part)?;
        }
    }
    // Into the store's columns here, not under the store's lock.
    let stored = crate::aggregate::store::StoredImage::from_contribution(out.contribution);
    store
        .lock()
        .map_err(poisoned)?
        .push_stored_as(raster_view, stored)?;
    work.image_aggregate_s += t1.elapsed().as_secs_f64();
    if let Ok(mut tt) = totals.lock() {
        tt.add(&work);
    }
    Ok(())
}

/// Sends one view's `(view, work, a_kj)` to `forward`.
///
/// Errors: [`Error::Internal`] when its receiver is gone.
fn forward_view(
    forward: &mpsc::Sender<Forwarded>,
    (view, work, contribution): (usize, ImageWork, crate::aggregate::ImageContribution),
) -> Result<()> {
    forward
        .send(Forwarded {
            view,
            work,
            contribution,
        })
        .map_err(|_| Error::internal("nothing takes the views' a_kj any more"))
}

/// Each Gaussian's mask of largest `a_kj` in `entries` (sorted by Gaussian), ties to the
/// smaller mask, as `(gaussian, mask, a_kj)`.
pub(crate) fn dominant_masks(entries: &[crate::aggregate::Entry]) -> Vec<(u32, u32, f32)> {
    let mut out: Vec<(u32, u32, f32)> = Vec::new();
    for e in entries {
        match out.last_mut() {
            Some(d) if d.0 == e.gaussian => {
                if e.weight > d.2 || (e.weight == d.2 && e.mask < d.1) {
                    *d = (e.gaussian, e.mask, e.weight);
                }
            }
            _ => out.push((e.gaussian, e.mask, e.weight)),
        }
    }
    out
}
