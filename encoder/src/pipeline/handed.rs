//! The encode's worker pool ([`super::pool`]) fed from outside: views handed to its front
//! workers one at a time ([`HandedViews`], the cluster's hand-out in `distributed::map`), and
//! each view's `a_kj` forwarded as soon as it is done ([`Forwarded`]) instead of stored. The
//! fronts, the bounded queues and the three back threads per rasterizer are the encode's own.

use std::sync::{Arc, mpsc};
use std::time::Instant;

use slag_common::camera::{Intrinsics, View};
use slag_common::{Error, Result};

use super::EncodeParams;
use super::feed::{Forwarded, HandedViews, ViewFeed};
use super::pool::{FrontStages, Queues, Shared, checked_rasterizers, run_workers};
use super::sinks::PoolSinks;
use crate::raster::WeightRasterizer;
use crate::report::WorkerShare;

/// What a pool fed from outside runs on: the job's `views` with their `raster_intrinsics`
/// (indexed as the handed views are), the encode's `params` and the embedding width `dim`.
pub(crate) struct HandedRun<'a> {
    pub(crate) views: &'a [View],
    pub(crate) raster_intrinsics: &'a [Intrinsics],
    pub(crate) params: &'a EncodeParams,
    pub(crate) dim: usize,
}

/// Runs the encode's pool ([`super::pool::run_pool`]'s workers: `fronts` front threads, three
/// back threads per rasterizer of `rasterizers`) over the views `feed` hands out, forwarding each
/// view's `a_kj` to `forward` as it is done, until the feeder closes or a worker fails. Nothing
/// is stored and nothing kept on a device: the views' `a_kj` go to the host (`--reduce host`),
/// and no progress bar is drawn. Returns the workers' shares (fronts first).
///
/// Errors: the first worker's error; [`Error::Param`] for no rasterizer or no front;
/// [`Error::Internal`] for a handed view out of range.
pub(crate) fn run_handed(
    run: HandedRun<'_>,
    fronts: Vec<FrontStages>,
    rasterizers: Vec<Box<dyn WeightRasterizer>>,
    feed: Arc<HandedViews>,
    forward: mpsc::Sender<Forwarded>,
) -> Result<Vec<WorkerShare>> {
    if fronts.is_empty() {
        return Err(Error::param("fronts", 0, "at least one front worker"));
    }
    let params = EncodeParams {
        reduce_on: crate::config::ReduceOn::Host,
        progress: false,
        ..run.params.clone()
    };
    let shared = Shared::new(
        (run.views, run.raster_intrinsics),
        &params,
        run.dim,
        (Instant::now(), None),
        (PoolSinks::forwarding(forward), ViewFeed::Handed(feed)),
    );
    let queues = Queues::for_fronts(&fronts);
    let bound_gpus = queues.bound_gpus;
    let (shares, _) = run_workers(&shared, fronts, queues, || {
        checked_rasterizers(Ok(rasterizers), bound_gpus)
    });
    shared.into_failure().map(|()| shares)
}
