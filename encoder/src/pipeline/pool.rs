//! The encode's worker pool: front threads (decode → masks → CLIP crops), three back threads per
//! rasterizer (prepare: the masks' pixel labels and the sort depths; raster: the GPU's label
//! sums; image: the host side of `a_kj`, the reduction and expansion of the sums), the bounded
//! queues between them, and the first error, which stops every worker. What it leaves
//! ([`Pooled`]: every image's `a_kj`, what the workers measured) goes to [`super::finish`].

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, mpsc};
use std::time::Instant;

use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle};
use slag_common::camera::{Intrinsics, View};
use slag_common::scene::Gaussians;
use slag_common::{Error, Result};

use super::devices::{StreamSharing, ViewsDone};
use super::fallback::ReduceFallback;
use super::feed::ViewFeed;
pub(crate) use super::sinks::dominant_masks;
use super::sinks::{PoolSinks, finish_image};
use super::{
    BackPrepared, BackRaster, CropEmbedder, EncodeParams, FrontItem, Keep, SceneInput,
    back_prepare, back_raster, front_stage, no_views,
};
use crate::aggregate::ContributionStore;
use crate::masks::MaskGenerator;
use crate::raster::{ViewPrecompute, WeightRasterizer};
use crate::report::{Counts, ImageWork, QueueStats, StageTimings, WorkerShare};
use slag_common::mask_record::MaskRecord;

/// What the worker pool leaves for the finish ([`super::finish::finish`]): the scene's
/// Gaussians, every image's `a_kj` (and, with [`EncodeParams::levels`], per SAM level), the
/// models' names and what the workers measured.
pub(crate) struct Pooled {
    /// The scene's Gaussians (the reduction needs their means), shared with the segments when
    /// they run beside the encode.
    pub gaussians: Arc<Gaussians>,
    /// Embedding width D.
    pub dim: usize,
    /// The crop embedder's model id.
    pub model_id: String,
    /// The mask generator's name.
    pub mask_name: String,
    /// Front workers that ran.
    pub fronts: usize,
    /// The rasterizers' names, one per back worker.
    pub rasterizers: Vec<String>,
    /// Every image's contribution.
    pub store: ContributionStore,
    /// Per SAM level `l`, every image's contribution of that level's masks; empty without
    /// [`EncodeParams::levels`].
    pub level_stores: Vec<ContributionStore>,
    /// Stage timings so far (scene load, the per-image stages).
    pub timings: StageTimings,
    /// Counts so far (views, Gaussians, masks, entries).
    pub counts: Counts,
    /// Each worker's share of the run.
    pub workers: Vec<WorkerShare>,
    /// Occupancy of the queues between the stages.
    pub queue: QueueStats,
    /// Which views were encoded and what choosing them cost.
    pub selection: crate::views::SelectionReport,
    /// The masks' record, with [`EncodeParams::mask_record_slots`].
    pub mask_record: Option<MaskRecord>,
    /// The rasterizers that kept their views' sums on their devices, for the device reduction
    /// ([`WeightRasterizer::reduce_kept`]); empty: the store holds the `a_kj`.
    pub device: Vec<Box<dyn WeightRasterizer>>,
    /// Why the device reduction gave way to the host's during the run
    /// ([`super::fallback`]); `None`: it did not.
    pub reduce_fallback: Option<crate::report::DeviceReduceFallback>,
    /// The front workers' models (SAM and CLIP sessions, or handles to a GPU's), kept from the
    /// workers' threads so that the caller lets them go beside the tail: the reduction does not
    /// need them, and tearing a GPU's sessions down takes time.
    pub retired: Vec<FrontStages>,
}

/// The encode pipeline over a pool of workers: `fronts.len()` front threads (decode → masks →
/// CLIP crops, on the CPU / ONNX Runtime) and one back thread per rasterizer returned by
/// `make_rasterizers` (one per GPU: raster → `a_kj`), that leave every
/// image's `a_kj` for the one reduction over all images ([`super::finish`]).
///
/// Scheduling is dynamic at both ends: front workers take the next unclaimed view from a shared
/// counter, and back workers take the next finished front item from one bounded queue (depth
/// 2 × rasterizers), so an image with many masks or a slow GPU holds up only its own worker
/// (the paper saw large stragglers with a static split). The per-image contributions of all
/// workers go to one [`ContributionStore`]; the reduction (`E_k`, f64) runs once at the end, so
/// the result equals a one-worker run up to the f64 summation order.
///
/// `hooks` holds the run's start (the workers' [`WorkerShare`] times count from it). The
/// Gaussians come from `shared` (the load the segments share) when given, else the pool loads
/// them ([`SceneInput::load_sharing`]).
///
/// Errors: the first error of any worker stops the others; the scene's and the rasterizers'
/// set-up errors. All fronts must embed with the same model (same `model_id` and `dim`).
pub(crate) fn run_pool(
    scene: &SceneInput,
    shared: Option<super::scene_load::SceneLoad>,
    fronts: Vec<FrontStages>,
    make_rasterizers: impl FnOnce(&Gaussians) -> Result<Vec<Box<dyn WeightRasterizer>>>,
    params: &EncodeParams,
    hooks: PoolHooks<'_>,
) -> Result<Pooled> {
    let PoolHooks {
        t_total,
        on_device_keep,
    } = hooks;
    let mut t = StageTimings::default();
    let model = FrontModel::of(&fronts)?;
    let (gaussians, training, views_total, load_s) = scene.load_sharing(shared)?;
    t.load_scene = load_s;
    if training.is_empty() {
        return Err(no_views(scene, views_total));
    }
    let (views, selection, made) = select_views(
        scene,
        &gaussians,
        training,
        make_rasterizers,
        params.progress,
    )?;
    let raster_intrinsics = raster_intrinsics_of(&views, params.raster_scale)?;
    log_scene_loaded(gaussians.len(), views.len(), fronts.len());
    let n_fronts = fronts.len();
    let sinks = PoolSinks::new(params, (model.dim, gaussians.len()), views.len())?;
    let shared = Shared::new(
        (&views, &raster_intrinsics),
        params,
        model.dim,
        (t_total, on_device_keep),
        (sinks, ViewFeed::Counter(AtomicUsize::new(0))),
    );
    let queues = Queues::for_fronts(&fronts);
    let (slots, bound_gpus) = (queues.slots(), queues.bound_gpus);
    let (workers, rasterizers) = run_workers(&shared, fronts, queues, || {
        checked_rasterizers(made.into_rasterizers(&gaussians), bound_gpus)
    });
    let retired = shared.take_retired();
    shared.bring_back_late();
    let mut left = shared.finish(slots)?;
    let shape = (gaussians.len(), views.len());
    let mask_record = gather_mask_record(left.mask_record.take(), &mut left.device, params, shape)?;
    let mut counts = Counts {
        views_total,
        views_used: views.len(),
        gaussians: gaussians.len(),
        ..Default::default()
    };
    left.totals.fill(&mut t, &mut counts);
    Ok(Pooled {
        gaussians,
        dim: model.dim,
        model_id: model.model_id,
        mask_name: model.mask_name,
        fronts: n_fronts,
        rasterizers,
        store: left.store,
        level_stores: left.level_stores,
        timings: t,
        counts,
        workers,
        queue: left.queue,
        selection,
        mask_record,
        device: left.device,
        reduce_fallback: left.reduce_fallback,
        retired,
    })
}

/// The log line of a loaded scene: its Gaussians, the views to encode and the front workers.
fn log_scene_loaded(gaussians: usize, views: usize, fronts: usize) {
    // Under the pipeline's target, where the README's sample output shows this line.
    tracing::info!(
        target: "slag_encoder::pipeline",
        gaussians,
        views,
        fronts,
        "scene loaded"
    );
}

/// The masks' record of the run (with [`EncodeParams::mask_record_slots`]): the views recorded on
/// the host (`host`) merged with each device's kept record, read back from the rasterizers in
/// `device` (all at once); an empty record of `(Gaussians, views)` when no view recorded
/// anything.
///
/// Errors: device failures reading a record back; records of other shapes
/// ([`MaskRecord::merge`]).
fn gather_mask_record(
    host: Option<Option<MaskRecord>>,
    device: &mut [Box<dyn WeightRasterizer>],
    params: &EncodeParams,
    (gaussians, views): (usize, usize),
) -> Result<Option<MaskRecord>> {
    let (Some(mut out), Some(slots)) = (host, params.mask_record_slots) else {
        return Ok(None);
    };
    let t0 = Instant::now();
    // Each device reads its record back on a thread of its own.
    let taken: Vec<Result<Option<MaskRecord>>> = std::thread::scope(|s| {
        let handles: Vec<_> = device
            .iter_mut()
            .map(|r| s.spawn(move || r.take_mask_record()))
            .collect();
        handles
            .into_iter()
            .map(|h| {
                h.join()
                    .unwrap_or_else(|_| Err(Error::internal("a masks' record reader panicked")))
            })
            .collect()
    });
    for kept in taken {
        if let Some(kept) = kept? {
            match &mut out {
                Some(r) => r.merge(&kept)?,
                None => out = Some(kept),
            }
        }
    }
    tracing::debug!(
        seconds = t0.elapsed().as_secs_f64(),
        "masks' record gathered"
    );
    match out {
        Some(r) => Ok(Some(r)),
        None => MaskRecord::new(gaussians, slots, views).map(Some),
    }
}

/// The raster intrinsics of every view at `raster_scale`, checked (scale range, raster size)
/// before any image work. Errors: the first view whose raster is refused.
fn raster_intrinsics_of(views: &[View], raster_scale: f64) -> Result<Vec<Intrinsics>> {
    views
        .iter()
        .map(|v| crate::raster::raster_intrinsics(&v.intrinsics, raster_scale))
        .collect()
}

/// Where the pool's progress bars draw: stderr when `progress`, else nowhere.
fn progress_display(progress: bool) -> MultiProgress {
    MultiProgress::with_draw_target(if progress {
        ProgressDrawTarget::stderr()
    } else {
        ProgressDrawTarget::hidden()
    })
}

/// The embedding model every front worker uses, and the first front's mask generator.
struct FrontModel {
    dim: usize,
    model_id: String,
    mask_name: String,
}

impl FrontModel {
    /// Errors: [`Error::Param`] for no fronts; [`Error::Mismatch`] when fronts embed with
    /// different models (model id or width `D`).
    fn of(fronts: &[FrontStages]) -> Result<Self> {
        let Some(first) = fronts.first() else {
            return Err(Error::param("fronts", 0, "at least one front worker"));
        };
        let dim = first.crops.dim();
        let model_id = first.crops.model_id().to_string();
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
        Ok(FrontModel {
            dim,
            model_id,
            mask_name: first.masks.name().to_string(),
        })
    }
}

/// The first error of any worker, and whether there was one (every worker checks between
/// images and stops).
#[derive(Default)]
struct Failure {
    failed: AtomicBool,
    first: Mutex<Option<Error>>,
}

impl Failure {
    /// Records `e` unless an earlier error is recorded; every worker stops at its next check.
    fn fail(&self, e: Error) {
        self.failed.store(true, Ordering::SeqCst);
        if let Ok(mut slot) = self.first.lock() {
            slot.get_or_insert(e);
        }
    }

    fn has_failed(&self) -> bool {
        self.failed.load(Ordering::SeqCst)
    }

    /// Errors: the first recorded error.
    fn into_result(self) -> Result<()> {
        match self.first.into_inner().ok().flatten() {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }
}

/// What the caller of [`run_pool`] hooks into it.
pub(crate) struct PoolHooks<'a> {
    /// The run's start: the workers' times count from it.
    pub(crate) t_total: Instant,
    /// Called once, when the first rasterizer starts keeping its views' sums on its device.
    pub(crate) on_device_keep: Option<&'a (dyn Fn() + Sync)>,
}

/// What every worker of [`run_pool`] shares: the views and settings, where the fronts take
/// their views, the first error, the queues' gauge, the image stage's sinks and totals, the
/// progress bars.
pub(super) struct Shared<'a> {
    views: &'a [View],
    raster_intrinsics: &'a [Intrinsics],
    params: &'a EncodeParams,
    dim: usize,
    t_total: Instant,
    /// Where a free front worker takes its next view.
    feed: ViewFeed,
    failure: Failure,
    queue: QueueGauge,
    /// What the back workers add up (under one lock, once per image).
    totals: Mutex<ImageWork>,
    sinks: PoolSinks,
    /// [`PoolHooks::on_device_keep`], taken by the first rasterizer that keeps.
    on_device_keep: Mutex<Option<&'a (dyn Fn() + Sync)>>,
    /// The rasterizers that kept their views' sums on the device, handed back at their end.
    device: Mutex<Vec<KeepingRasterizer>>,
    /// Whether `--reduce auto` gave way to the host's reduction ([`super::fallback`]).
    fallback: ReduceFallback,
    /// Each front worker's models once it is done ([`Pooled::retired`]).
    retired: Mutex<Vec<FrontStages>>,
    bar_front: ProgressBar,
    bar_back: ProgressBar,
    /// The run's rasterizers, once made: the device reduction streams with one
    /// ([`keep_on_device`]), or on several shared between them ([`StreamSharing`]).
    rasterizers: AtomicUsize,
    /// With several rasterizers, how they stream their kept views together.
    sharing: std::sync::OnceLock<StreamSharing>,
}

/// A rasterizer that kept views on its device, with the views it kept in keeping order (their
/// indices in the encode's view list).
type KeepingRasterizer = (Box<dyn WeightRasterizer>, Vec<usize>);

/// What the workers leave ([`Shared::finish`]).
struct WorkersLeft {
    store: ContributionStore,
    level_stores: Vec<ContributionStore>,
    /// With the masks' record: its views recorded on the host, if any.
    mask_record: Option<Option<MaskRecord>>,
    device: Vec<Box<dyn WeightRasterizer>>,
    reduce_fallback: Option<crate::report::DeviceReduceFallback>,
    totals: ImageWork,
    queue: QueueStats,
}

impl<'a> Shared<'a> {
    /// What the workers of a run share, before any started: the encode's `views` with their
    /// raster intrinsics, the `dim`-wide embeddings, the run's start `t_total` and its hook,
    /// the `sinks`, where the fronts take their views (`feed`), and the progress bars (shown
    /// with [`EncodeParams::progress`]).
    pub(super) fn new(
        (views, raster_intrinsics): (&'a [View], &'a [Intrinsics]),
        params: &'a EncodeParams,
        dim: usize,
        (t_total, on_device_keep): (Instant, Option<&'a (dyn Fn() + Sync)>),
        (sinks, feed): (PoolSinks, ViewFeed),
    ) -> Self {
        let multi = progress_display(params.progress);
        Shared {
            views,
            raster_intrinsics,
            params,
            dim,
            t_total,
            feed,
            failure: Failure::default(),
            queue: QueueGauge::default(),
            totals: Mutex::new(ImageWork::default()),
            sinks,
            device: Mutex::new(Vec::new()),
            on_device_keep: Mutex::new(on_device_keep),
            fallback: ReduceFallback::default(),
            retired: Mutex::new(Vec::new()),
            bar_front: bar(&multi, views.len(), "masks + CLIP"),
            bar_back: bar(&multi, views.len(), "raster + a_kj"),
            rasterizers: AtomicUsize::new(0),
            sharing: std::sync::OnceLock::new(),
        }
    }

    /// After the workers: the first worker's error, if any (`handed::run_handed`,
    /// whose sinks forward every view and keep nothing to finish).
    pub(super) fn into_failure(self) -> Result<()> {
        self.bar_front.finish();
        self.bar_back.finish();
        self.failure.into_result()
    }
}

impl Shared<'_> {
    /// Brings the views `rasterizer` kept (`kept`: their indices in `views`, in keeping order)
    /// back to the store ([`ReduceFallback::bring_back`]). A masks' record the device kept is
    /// dropped (a view that failed may have entered some of its bands there) and its views are
    /// recorded on the host from their `a_kj`, as the host path records them.
    ///
    /// Errors: as that; the device's reading the record back; [`Error::Internal`] for kept
    /// views the worker did not count, or a poisoned record.
    fn bring_back(&self, rasterizer: &mut dyn WeightRasterizer, kept: &[usize]) -> Result<()> {
        let record = match rasterizer.take_mask_record()? {
            Some(_) => self.sinks.record.as_ref(),
            None => None,
        };
        let (store, totals) = (&self.sinks.store, &self.totals);
        self.fallback
            .bring_back(rasterizer, self.dim, store, totals, |i, c| {
                let Some(record) = record else {
                    return Ok(());
                };
                let view = kept.get(i).copied().ok_or_else(|| {
                    Error::internal(format!("kept view {i} of {} counted", kept.len()))
                })?;
                let poisoned = |_| Error::internal("masks' record poisoned by a panicked worker");
                let dominant = dominant_masks(&c.entries);
                record.lock().map_err(poisoned)?.add_view(view, &dominant)
            })
    }

    /// After the workers: the front workers' models they handed back ([`Pooled::retired`]).
    fn take_retired(&self) -> Vec<FrontStages> {
        match self.retired.lock() {
            Ok(mut r) => std::mem::take(&mut *r),
            Err(_) => Vec::new(),
        }
    }

    /// After the workers: when the run gave way to the host's reduction, the rasterizers that
    /// ended before it did bring their views back too; an error fails the run.
    fn bring_back_late(&self) {
        if !self.fallback.is_set() || self.failure.has_failed() {
            return;
        }
        let Ok(mut device) = self.device.lock() else {
            return self
                .failure
                .fail(Error::internal("kept rasterizers poisoned"));
        };
        for (mut r, kept_views) in device.drain(..) {
            if let Err(e) = self.bring_back(&mut *r, &kept_views) {
                return self.failure.fail(e);
            }
        }
    }

    /// What the workers left, the queues' occupancy over their `slots`; the progress bars end.
    ///
    /// Errors: the first worker error; [`Error::Internal`] for a store or record poisoned by a
    /// panicked worker, or when not every view reached the store.
    fn finish(self, slots: usize) -> Result<WorkersLeft> {
        self.failure.into_result()?;
        let poisoned = |_| Error::internal("contribution store poisoned by a panicked worker");
        let PoolSinks {
            store,
            level_stores,
            record,
            ..
        } = self.sinks;
        let store = store.into_inner().map_err(poisoned)?;
        // A view brought back from a device is there twice: empty, then with its a_kj.
        if store.len() != self.views.len() + self.fallback.views() {
            return Err(Error::internal(format!(
                "only {} of {} images reached the reduction",
                store.len(),
                self.views.len()
            )));
        }
        let level_stores = level_stores
            .into_iter()
            .map(|ls| ls.into_inner().map_err(poisoned))
            .collect::<Result<Vec<_>>>()?;
        let mask_record = record
            .map(|r| {
                r.into_inner()
                    .map(|h| h.record)
                    .map_err(|_| Error::internal("masks' record poisoned by a panicked worker"))
            })
            .transpose()?;
        let device = self
            .device
            .into_inner()
            .map_err(|_| Error::internal("kept rasterizers poisoned by a panicked worker"))?;
        self.bar_front.finish();
        self.bar_back.finish();
        Ok(WorkersLeft {
            store,
            level_stores,
            mask_record,
            device: device.into_iter().map(|(r, _)| r).collect(),
            reduce_fallback: self.fallback.into_report(),
            totals: self.totals.into_inner().unwrap_or_default(),
            queue: self.queue.stats(slots),
        })
    }
}

/// The bounded queues from the fronts to the back workers: one for all rasterizers, or, when
/// the fronts are bound to GPUs, one per GPU so an image stays on the GPU whose SAM and CLIP
/// made its masks. Each queue holds two finished images per rasterizer it feeds (the unbound
/// fronts' queue: two per front, at most 8).
pub(super) struct Queues {
    senders: Vec<mpsc::SyncSender<FrontItem>>,
    receivers: Vec<Arc<Mutex<mpsc::Receiver<FrontItem>>>>,
    capacity: usize,
    /// How many GPUs the fronts are bound to, if they are.
    pub(super) bound_gpus: Option<usize>,
}

impl Queues {
    pub(super) fn for_fronts(fronts: &[FrontStages]) -> Self {
        let bound_gpus = fronts.iter().filter_map(|f| f.gpu).max().map(|g| g + 1);
        let (n, capacity) = match bound_gpus {
            Some(n) => (n, 2),
            None => (1, (2 * fronts.len()).clamp(2, 8)),
        };
        let (senders, receivers) = (0..n)
            .map(|_| {
                let (tx, rx) = mpsc::sync_channel::<FrontItem>(capacity);
                (tx, Arc::new(Mutex::new(rx)))
            })
            .unzip();
        Queues {
            senders,
            receivers,
            capacity,
            bound_gpus,
        }
    }

    /// The queues' slots together.
    fn slots(&self) -> usize {
        self.receivers.len() * self.capacity
    }
}

/// `made`, checked: at least one rasterizer, and one for each GPU the fronts are bound to.
///
/// Errors: `made`'s; [`Error::Param`] for none; [`Error::Internal`] for too few.
pub(super) fn checked_rasterizers(
    made: Result<Vec<Box<dyn WeightRasterizer>>>,
    bound_gpus: Option<usize>,
) -> Result<Vec<Box<dyn WeightRasterizer>>> {
    let r = made?;
    if r.is_empty() {
        return Err(Error::param("rasterizers", 0, "at least one rasterizer"));
    }
    if r.len() < bound_gpus.unwrap_or(1) {
        return Err(Error::internal(format!(
            "front workers are bound to {} GPUs but there are {} rasterizers",
            bound_gpus.unwrap_or(1),
            r.len()
        )));
    }
    Ok(r)
}

/// Runs every worker to the end of the views or the first error, and returns their shares
/// (fronts first) and the rasterizers' names. The fronts start first; `rasterizers` makes the
/// rasterizers (device, upload of the Gaussians) while the first images go through SAM and
/// CLIP, so that set-up is off the critical path; its error stops the run like a worker's.
pub(super) fn run_workers(
    shared: &Shared<'_>,
    fronts: Vec<FrontStages>,
    queues: Queues,
    rasterizers: impl FnOnce() -> Result<Vec<Box<dyn WeightRasterizer>>>,
) -> (Vec<WorkerShare>, Vec<String>) {
    let Queues {
        senders, receivers, ..
    } = queues;
    let n_queues = receivers.len();
    std::thread::scope(|s| {
        let mut handles = Vec::new();
        for (w, mut front) in fronts.into_iter().enumerate() {
            let tx = senders[front.gpu.unwrap_or(0) % n_queues].clone();
            handles.push(s.spawn(move || {
                let share = front_loop(w, &mut front, &tx, shared);
                if let Ok(mut retired) = shared.retired.lock() {
                    retired.push(front);
                }
                share
            }));
        }
        // The back workers hold the only receivers: when every front is done, the queue closes.
        drop(senders);
        let rasterizers = rasterizers().unwrap_or_else(|e| {
            shared.failure.fail(e);
            Vec::new()
        });
        let names: Vec<String> = rasterizers.iter().map(|r| r.name().to_string()).collect();
        shared.rasterizers.store(names.len(), Ordering::SeqCst);
        if names.len() > 1 {
            let _ = shared
                .sharing
                .set(StreamSharing::new(names.len(), shared.views.len()));
        }
        for (g, rasterizer) in rasterizers.into_iter().enumerate() {
            let rx = Arc::clone(&receivers[g % n_queues]);
            let name = format!("raster-{g} {}", names[g]);
            handles.extend(spawn_back(s, g, rasterizer, rx, name, shared));
        }
        // Without rasterizers (their set-up failed) the fronts see the queues close and stop.
        drop(receivers);
        let mut shares = Vec::with_capacity(handles.len());
        for h in handles {
            match h.join() {
                Ok(share) => shares.push(share),
                Err(_) => shared
                    .failure
                    .fail(Error::internal("an encode worker thread panicked")),
            }
        }
        tracing::debug!(
            target: "slag_encoder::pipeline",
            seconds = shared.t_total.elapsed().as_secs_f64(),
            "workers done"
        );
        (shares, names)
    })
}

/// Front worker `w`'s loop: takes the next view from the run's feed, runs its masks and CLIP
/// crops ([`front_stage`]) and hands the item to its queue `tx`, until the views are done, the
/// queue is gone, or a worker failed (its own error is recorded).
fn front_loop(
    w: usize,
    front: &mut FrontStages,
    tx: &mpsc::SyncSender<FrontItem>,
    shared: &Shared<'_>,
) -> WorkerShare {
    let mut share = stage_share(format!("front-{w}"));
    let failed = || shared.failure.has_failed();
    while let Some(i) = shared.feed.next(shared.views.len(), failed) {
        let Some(view) = shared.views.get(i) else {
            let n = shared.views.len();
            shared
                .failure
                .fail(Error::internal(format!("view {i} handed out of {n}")));
            break;
        };
        let t0 = Instant::now();
        if share.images == 0 {
            share.first_s = (t0 - shared.t_total).as_secs_f64();
        }
        let item = front_stage(view, i, &mut *front.masks, &mut *front.crops, shared.dim);
        share.busy_s += t0.elapsed().as_secs_f64();
        share.last_s = shared.t_total.elapsed().as_secs_f64();
        shared.bar_front.inc(1);
        match item {
            Ok(item) => {
                share.images += 1;
                let bytes = item.bytes();
                shared.queue.enter(bytes);
                if tx.send(item).is_err() {
                    shared.queue.leave(bytes);
                    break;
                }
                // Free again: its item is in the queue.
                shared.feed.fronted();
            }
            Err(e) => {
                shared.failure.fail(e);
                break;
            }
        }
    }
    share
}

/// The three back threads of rasterizer `g`, a view handed on from one to the next through a
/// channel of one (a view's labels or label sums, a few MB): *prepare* takes the next front item
/// from `rx` and makes its pixel labels and sort depths, *raster* (named `name`) runs the GPU,
/// *image* reduces and expands the last view's sums into the sinks. The GPU never waits for host
/// work. Their host work runs on a rayon pool of the rasterizer's own ([`back_pool`]), so that
/// it never queues behind the front workers' jobs (SAM post-processing, crops) in the global
/// pool.
fn spawn_back<'scope>(
    s: &'scope std::thread::Scope<'scope, '_>,
    g: usize,
    rasterizer: Box<dyn WeightRasterizer>,
    rx: Arc<Mutex<mpsc::Receiver<FrontItem>>>,
    name: String,
    shared: &'scope Shared<'_>,
) -> [std::thread::ScopedJoinHandle<'scope, WorkerShare>; 3] {
    let pool = Arc::new(back_pool(g));
    let (to_raster, from_prepare) = mpsc::sync_channel::<BackPrepared>(1);
    let (to_image, from_raster) = mpsc::sync_channel::<BackRaster>(1);
    let precompute = rasterizer.view_precompute();
    let prepare = {
        let pool = Arc::clone(&pool);
        s.spawn(move || back_prepare_thread(g, rx, to_raster, precompute, &pool, shared))
    };
    let raster = {
        let pool = Arc::clone(&pool);
        let back = (from_prepare, to_image);
        s.spawn(move || back_raster_thread((g, name), rasterizer, back, &pool, shared))
    };
    let image = s.spawn(move || back_image_thread(g, from_raster, &pool, shared));
    [prepare, raster, image]
}

/// The *prepare* thread of [`spawn_back`]: the next finished front item from `rx`, its pixel
/// labels and sort depths (with the rasterizer's view `precompute`), handed on to the raster.
fn back_prepare_thread(
    g: usize,
    rx: Arc<Mutex<mpsc::Receiver<FrontItem>>>,
    to_raster: mpsc::SyncSender<BackPrepared>,
    precompute: Option<Arc<dyn ViewPrecompute>>,
    pool: &Option<rayon::ThreadPool>,
    shared: &Shared<'_>,
) -> WorkerShare {
    let (views, raster_intrinsics, params) =
        (shared.views, shared.raster_intrinsics, shared.params);
    // Take the next finished front item; the lock is held only while waiting.
    let items = std::iter::from_fn(|| {
        let item = rx.lock().ok()?.recv().ok()?;
        shared.queue.leave(item.bytes());
        Some(item)
    });
    let step = |item, _: &mut WorkerShare| {
        let pre = precompute.as_deref();
        back_prepare(
            views,
            raster_intrinsics,
            item,
            shared.dim,
            params.image_stage,
            pre,
        )
    };
    let send = |out| to_raster.send(out).is_ok();
    let mut share = stage_share(format!("prepare-{g}"));
    stage_loop(
        &mut share,
        shared.t_total,
        &shared.failure,
        pool.as_ref(),
        items,
        step,
        send,
    );
    share
}

/// The *raster* thread of [`spawn_back`] (named `name`): each prepared view through the GPU,
/// its sums handed on to the image thread, or kept on the device for the device reduction
/// ([`keep_on_device`]), in which case the rasterizer is handed to the pool's end.
fn back_raster_thread(
    (g, name): (usize, String),
    mut rasterizer: Box<dyn WeightRasterizer>,
    (from_prepare, to_image): (mpsc::Receiver<BackPrepared>, mpsc::SyncSender<BackRaster>),
    pool: &Option<rayon::ThreadPool>,
    shared: &Shared<'_>,
) -> WorkerShare {
    let failure = &shared.failure;
    let n_views = shared.views.len();
    let (mut keep, sharing) = raster_keep_setup(g, &mut *rasterizer, shared);
    // The views kept on the device, in keeping order.
    let mut kept_views = Vec::new();
    let mut done = ViewsDone::new(n_views);
    let step = |prepared, share: &mut WorkerShare| {
        let mut out = back_raster(&mut *rasterizer, prepared, keep)?;
        if let Some(p) = rasterizer.last_phases() {
            share.raster_phases_ms.get_or_insert_default().add(&p);
        }
        if out.is_kept() {
            kept_views.push(out.item.view);
        }
        if let Some(e) = out.take_gave_up_keeping() {
            shared.fallback.give_way(rasterizer.name(), &e);
        }
        // Before this view goes on: the views kept so far reach the store first.
        if keep.is_some() && shared.fallback.is_set() {
            keep = None;
            shared.bring_back(&mut *rasterizer, &std::mem::take(&mut kept_views))?;
        }
        // The streamed reduction folds the views before the first not rastered yet; once a
        // wave ran, the host can no longer take the reduction over (a view past the budget is
        // then the run's error).
        let view = out.item.view;
        if let Some(k) = keep.as_mut()
            && rasterizer
                .fold_kept(sharing.map_or_else(|| done.add(view), |s| s.view_done(view)))?
        {
            k.fall_back = false;
        }
        Ok(out)
    };
    let send = |out| to_image.send(out).is_ok();
    let mut share = stage_share(name);
    let views = from_prepare.iter();
    stage_loop(
        &mut share,
        shared.t_total,
        failure,
        pool.as_ref(),
        views,
        step,
        send,
    );
    if keep.is_some()
        && let Ok(mut device) = shared.device.lock()
    {
        device.push((rasterizer, kept_views));
    }
    share
}

/// Whether rasterizer `g` keeps its views on the device ([`keep_on_device`]; an error is the
/// run's failure), running the device-keep hook once, and whether it streams with the other GPUs
/// ([`StreamSharing::join`]: then views cross devices as they come, and the host cannot take over).
fn raster_keep_setup<'s>(
    g: usize,
    rasterizer: &mut dyn WeightRasterizer,
    shared: &'s Shared<'_>,
) -> (Option<Keep>, Option<&'s StreamSharing>) {
    let n_views = shared.views.len();
    let alone = shared.rasterizers.load(Ordering::SeqCst) == 1;
    let mut keep = match keep_on_device(rasterizer, shared.params, shared.dim, n_views, alone) {
        Ok(keep) => keep,
        Err(e) => {
            shared.failure.fail(e);
            None
        }
    };
    if keep.is_some() {
        let hook = shared.on_device_keep.lock().ok().and_then(|mut h| h.take());
        if let Some(hook) = hook {
            hook();
        }
    }
    let streamed = keep.and(stream_keep(shared.params));
    let sharing = shared
        .sharing
        .get()
        .filter(|s| s.join(g, rasterizer, streamed));
    if let Some(k) = keep.as_mut().filter(|_| sharing.is_some()) {
        k.fall_back = false;
    }
    (keep, sharing)
}

/// The *image* thread of [`spawn_back`]: the last view's sums reduced and expanded into the
/// sinks.
fn back_image_thread(
    g: usize,
    from_raster: mpsc::Receiver<BackRaster>,
    pool: &Option<rayon::ThreadPool>,
    shared: &Shared<'_>,
) -> WorkerShare {
    let (dim, params) = (shared.dim, shared.params);
    let step = |raster: BackRaster, _: &mut WorkerShare| {
        let view = raster.item.view;
        let res = finish_image(raster, dim, params, &shared.sinks, &shared.totals);
        if let Some(view) = shared.views.get(view) {
            tracing::debug!(view = %view.name, "image done");
        }
        shared.bar_back.inc(1);
        res
    };
    let mut share = stage_share(format!("image-{g}"));
    let views = from_raster.iter();
    stage_loop(
        &mut share,
        shared.t_total,
        &shared.failure,
        pool.as_ref(),
        views,
        step,
        |()| true,
    );
    share
}

/// Whether `rasterizer` keeps its views' sums on the device for the device reduction
/// ([`crate::config::ReduceOn`]): `Some` with whether the masks' record wants the dominant
/// masks and whether a device memory limit gives way to the host (`auto`,
/// [`super::fallback`]), or `None` for the host reduction. A rasterizer that keeps the sums
/// keeps the masks' record of an encode of `n_views` views there too where it can
/// ([`WeightRasterizer::keep_mask_record`]); its views' dominant masks are then not wanted. The
/// device reduction needs GPU rasterizers whose devices have f64, no per-level files and no
/// dense file (folded on the host, [`crate::aggregate::DenseFold`]). The only rasterizer of a
/// run (`alone`) streams its views when only the mixture is written
/// ([`WeightRasterizer::stream_kept`]): its device memory does not grow with the views; on
/// several GPUs they stream together ([`StreamSharing`]), or, where they cannot, each keeps
/// its own views and each reduces one range of Gaussians at the end ([`super::devices`]).
///
/// Errors: `--reduce device` where it cannot run ([`Error::Param`] `reduce`).
fn keep_on_device(
    rasterizer: &mut dyn WeightRasterizer,
    params: &EncodeParams,
    dim: usize,
    n_views: usize,
    alone: bool,
) -> Result<Option<Keep>> {
    use crate::config::ReduceOn;
    let forced = params.reduce_on == ReduceOn::Device;
    // With the dense file every row crosses to the host anyway: the host folds each view into
    // its dense accumulators as it comes (`aggregate::DenseFold`), so no device keeps them.
    let possible = match params.reduce_on {
        ReduceOn::Host => false,
        ReduceOn::Auto | ReduceOn::Device => !params.levels && !params.dense,
    };
    let keeps =
        possible && rasterizer.keep_on_device(dim, params.device_reduce_budget_bytes, forced);
    if forced && !keeps {
        return Err(Error::param(
            "reduce",
            "device",
            "GPU rasterizers whose devices have f64, no --levels and no --dense (the dense file \
             is reduced on the host as the views come: leave --reduce at auto, or --reduce host)",
        ));
    }
    if keeps
        && alone
        && let Some(keep) = stream_keep(params)
    {
        rasterizer.stream_kept(keep);
    }
    let record_on_device = keeps
        && params
            .mask_record_slots
            .is_some_and(|slots| rasterizer.keep_mask_record(slots, n_views));
    Ok(keeps.then_some(Keep {
        dominant: params.mask_record_slots.is_some() && !record_on_device,
        fall_back: !forced,
    }))
}

/// The mixture pairs per Gaussian of the streamed device reduction, when it may stream: only
/// the mixture is written (no dense file).
fn stream_keep(params: &EncodeParams) -> Option<usize> {
    params.mixture_keep.filter(|_| !params.dense)
}

/// The rasterizers of a run: already made (for the coverage pass), or still to be made (while
/// the fronts start, off the critical path).
enum Rasterizers<F> {
    Made(Vec<Box<dyn WeightRasterizer>>),
    ToMake(F),
}

impl<F> Rasterizers<F>
where
    F: FnOnce(&Gaussians) -> Result<Vec<Box<dyn WeightRasterizer>>>,
{
    /// The rasterizers, made now if they were not yet.
    fn into_rasterizers(self, gaussians: &Gaussians) -> Result<Vec<Box<dyn WeightRasterizer>>> {
        match self {
            Rasterizers::Made(r) => Ok(r),
            Rasterizers::ToMake(make) => make(gaussians),
        }
    }
}

/// The views the encode uses among the scene's `training` views ([`crate::views::choose`]).
/// Coverage selection needs the rasterizers first: they are made here and handed on; otherwise
/// `make_rasterizers` is handed on unused. With `progress` a bar on stderr counts the coverage
/// pass's views.
///
/// Errors: as [`crate::views::choose`] and `make_rasterizers`.
fn select_views<F>(
    scene: &SceneInput,
    gaussians: &Gaussians,
    training: Vec<slag_common::camera::View>,
    make_rasterizers: F,
    progress: bool,
) -> Result<(
    Vec<slag_common::camera::View>,
    crate::views::SelectionReport,
    Rasterizers<F>,
)>
where
    F: FnOnce(&Gaussians) -> Result<Vec<Box<dyn WeightRasterizer>>>,
{
    if scene.selection.mode != crate::views::SelectionMode::Coverage {
        let (views, report) = crate::views::choose(training, &scene.selection, gaussians, &mut [])?;
        return Ok((views, report, Rasterizers::ToMake(make_rasterizers)));
    }
    let mut rasterizers = make_rasterizers(gaussians)?;
    let bar = bar(&progress_display(progress), training.len(), "coverage pass");
    let (views, report) = crate::views::choose_shown(
        training,
        &scene.selection,
        gaussians,
        &mut rasterizers,
        &bar,
    )?;
    bar.finish();
    if let Some(c) = &report.coverage {
        tracing::info!(
            target: "slag_encoder::pipeline",
            candidates = report.candidates,
            chosen = views.len(),
            observed = c.observed,
            covered = c.covered,
            pass_s = format!("{:.2}", report.pass_s),
            "views chosen by coverage"
        );
    }
    Ok((views, report, Rasterizers::Made(rasterizers)))
}

/// A back thread's [`WorkerShare`], named.
fn stage_share(name: String) -> WorkerShare {
    WorkerShare {
        name,
        ..Default::default()
    }
}

/// One back thread's loop: each input (until `inputs` ends or the pool has failed) goes through
/// `step`, inside the rasterizer's rayon `pool` (so that its parallel work never queues behind
/// the front workers' jobs in the global pool), its time is counted in `share`, and its output
/// is handed on (`send` false: the next thread is gone, having said why); the first error goes
/// to `failure` and ends the loop. The loop itself runs on the calling thread, not in the pool: the
/// three threads of a rasterizer share one pool, which may have only two threads.
fn stage_loop<I, O: Send>(
    share: &mut WorkerShare,
    t_total: Instant,
    failure: &Failure,
    pool: Option<&rayon::ThreadPool>,
    inputs: impl Iterator<Item = I>,
    mut step: impl FnMut(I, &mut WorkerShare) -> Result<O> + Send,
    mut send: impl FnMut(O) -> bool,
) where
    I: Send,
{
    for input in inputs {
        if failure.has_failed() {
            break;
        }
        let t0 = Instant::now();
        if share.images == 0 {
            share.first_s = (t0 - t_total).as_secs_f64();
        }
        let out = match pool {
            Some(pool) => pool.install(|| step(input, share)),
            None => step(input, share),
        };
        share.busy_s += t0.elapsed().as_secs_f64();
        share.last_s = t_total.elapsed().as_secs_f64();
        match out {
            Ok(out) => {
                share.images += 1;
                if !send(out) {
                    break;
                }
            }
            Err(e) => {
                failure.fail(e);
                break;
            }
        }
    }
}

/// The rayon pool of back worker `g`: as many threads as the global pool (at least 2). Each
/// rasterizer's two threads (GPU passes with their host part; the `a_kj` reduction and
/// expansion) share it; full pools let a host phase use the cores the other rasterizers leave idle
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

/// A spinner on stderr for one step of the encode's tail (`label`, right-aligned like the
/// pool's bars, then `message`), ticking until it is finished; hidden unless `show`.
pub(crate) fn tail_spinner(show: bool, label: &str, message: &str) -> ProgressBar {
    if !show {
        return ProgressBar::hidden();
    }
    let style = ProgressStyle::with_template("{prefix:>18} {spinner} {msg} {elapsed}")
        .unwrap_or_else(|_| ProgressStyle::default_spinner());
    let spinner = ProgressBar::new_spinner()
        .with_style(style)
        .with_prefix(label.to_string())
        .with_message(message.to_string());
    spinner.enable_steady_tick(std::time::Duration::from_millis(200));
    spinner
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

/// Occupancy of the queues between the front and the back stages of [`run_pool`]: images
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
    fn stats(&self, capacity: usize) -> QueueStats {
        use std::sync::atomic::Ordering::SeqCst;
        QueueStats {
            capacity_items: capacity,
            high_water_bytes: self.high_bytes.load(SeqCst) as u64,
            high_water_items: self.high_items.load(SeqCst),
            largest_item_bytes: self.largest_item.load(SeqCst) as u64,
        }
    }
}

/// The stage instances of one *front* worker: a mask generator and a crop embedder (their own
/// ONNX Runtime sessions on the CPU, or handles to the sessions of their GPU). [`run_pool`]
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
