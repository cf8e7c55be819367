//! `--reduce auto` giving way to the host's reduction during the run. When keeping a view's
//! label sums on the device meets a device memory limit (the kept sums' budget,
//! `--device-reduce-memory-mb`, or the device full with them), that view goes the host's way,
//! the views kept so far are brought back as the host's contributions (the same `a_kj` the
//! host's image stage makes of them), and the run goes on on the host. On several GPUs every
//! rasterizer brings its views back, so that one reduction, the host's, sees every view. A
//! masks' record kept on the host already holds the kept views' dominant masks; one kept on the
//! device is dropped (a view that failed may have entered some of its bands there) and the
//! views brought back are recorded on the host from their `a_kj`, as the host path does.
//!
//! `--reduce device` never gives way: the limit is its error.

use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

use slag_common::{Error, Result};

use crate::aggregate::store::StoredImage;
use crate::aggregate::{ContributionStore, ImageContribution};
use crate::raster::WeightRasterizer;
use crate::report::{DeviceReduceFallback, ImageWork};

/// Whether, and why, the run's device reduction gave way to the host's, and how many views
/// were brought back from the devices.
#[derive(Default)]
pub(crate) struct ReduceFallback {
    set: AtomicBool,
    reason: Mutex<Option<String>>,
    views: AtomicUsize,
}

impl ReduceFallback {
    /// Whether the run gave way: every rasterizer that keeps views brings them back.
    pub(crate) fn is_set(&self) -> bool {
        self.set.load(Ordering::SeqCst)
    }

    /// Records that rasterizer `name` gave way on `e` (the first reason is the one reported),
    /// with a warning.
    pub(crate) fn give_way(&self, name: &str, e: &Error) {
        tracing::warn!(
            rasterizer = name,
            error = %e,
            "keeping the label sums on the device for its reduction met its memory limit: the \
             views kept so far go back to the host, which reduces (--device-reduce-memory-mb \
             raises the limit; --reduce host reduces on the host from the start, folding each view \
             as it comes when only the mixture is written)"
        );
        if let Ok(mut reason) = self.reason.lock() {
            reason.get_or_insert_with(|| e.to_string());
        }
        self.set.store(true, Ordering::SeqCst);
    }

    /// Views brought back from the devices so far ([`Self::bring_back`]): their images are in
    /// the store twice, once empty (while kept) and once with their `a_kj`.
    pub(crate) fn views(&self) -> usize {
        self.views.load(Ordering::SeqCst)
    }

    /// The report's record of it ([`DeviceReduceFallback`]); `None`: the run did not give way.
    pub(crate) fn into_report(self) -> Option<DeviceReduceFallback> {
        let views_brought_back = self.views();
        let reason = self.reason.into_inner().ok().flatten()?;
        Some(DeviceReduceFallback {
            reason,
            views_brought_back,
        })
    }

    /// Brings every view `rasterizer` kept back to the host ([`WeightRasterizer::export_kept`];
    /// keeping stops): each view's label sums expanded into its `a_kj`
    /// ([`super::sums_contribution`], embeddings of width `dim`), handed to `on_view` with its
    /// place in keeping order, pushed to `store` under its view index (the store visits views
    /// by index), their entries added to `totals`.
    ///
    /// Errors: the device's (reading the sums back); a malformed export ([`Error::Internal`]);
    /// `on_view`'s; the store's (spill I/O); a lock poisoned by a panicked worker.
    pub(crate) fn bring_back(
        &self,
        rasterizer: &mut dyn WeightRasterizer,
        dim: usize,
        store: &Mutex<ContributionStore>,
        totals: &Mutex<ImageWork>,
        mut on_view: impl FnMut(usize, &ImageContribution) -> Result<()>,
    ) -> Result<()> {
        let Some(kept) = rasterizer.export_kept()? else {
            return Ok(());
        };
        let poisoned = |_| Error::internal("contribution store poisoned by a panicked worker");
        let mut entries = 0u64;
        for (i, v) in kept.into_host_views()?.into_iter().enumerate() {
            let c = super::sums_contribution(v.sums, &v.masks_of, &v.factors, v.embeddings, dim);
            on_view(i, &c)?;
            entries += c.entries.len() as u64;
            let stored = StoredImage::from_contribution(c);
            store
                .lock()
                .map_err(poisoned)?
                .push_stored_as(v.view, stored)?;
            self.views.fetch_add(1, Ordering::SeqCst);
        }
        if let Ok(mut t) = totals.lock() {
            t.entries += entries;
        }
        Ok(())
    }
}
