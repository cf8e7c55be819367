//! The map side: each worker encodes the views worker 0 hands it ([`super::handout`]: masks →
//! CLIP → raster → `a_kj`, on the encode's worker pool, [`run_handed`]: several front workers
//! and one rasterizer per GPU, while its timely worker keeps stepping) and splits each image's
//! `a_kj` by partition `p = k mod P` into [`ToReducer`] records.

use std::cell::RefCell;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use slag_common::camera::View;
use slag_common::{Error, Result};
use timely::container::CapacityContainerBuilder;
use timely::dataflow::InputHandle;

use super::FAULT_EXIT_STATUS;
use super::config::{ClusterJob, Stages};
use super::handout::{Granted, Handout, HandoutEnds};
use super::records::{ImagePart, JobKey, MapStats, ToReducer};
use crate::aggregate::ImageContribution;
use crate::pipeline::FrontStages;
use crate::pipeline::feed::{Forwarded, ViewsFeeder, handed_views};
use crate::pipeline::handed::{HandedRun, run_handed};
use crate::raster::WeightRasterizer;

/// The fingerprint of the parameters every process must share.
///
/// It holds what changes the outputs, not how a process computes them: its front workers and
/// GPUs are its own (processes may differ in both); `front` names the masks and the CLIP model
/// (every front of a process embeds with the same).
pub(super) fn job_key(
    job: &ClusterJob,
    gaussians: usize,
    views: &[slag_common::camera::View],
    front: &FrontStages,
) -> JobKey {
    let p = &job.params;
    JobKey {
        gaussians: gaussians as u64,
        views: views.len() as u64,
        dim: front.crops.dim() as u64,
        fingerprint: format!(
            "views {:?}..{:?} every {} hold_out_every {:?} selection {:?} raster_scale {} image_stage {:?} masks {} clip {} min_weight {} mixture_keep {:?} dense {} record {:?}",
            views.first().map(|v| &v.name),
            views.last().map(|v| &v.name),
            job.scene.every,
            job.scene.hold_out_every,
            job.scene.selection,
            p.raster_scale,
            p.image_stage,
            front.masks.name(),
            front.crops.model_id(),
            p.reduce.min_total_weight,
            p.mixture_keep,
            p.dense,
            p.mask_record_slots,
        ),
    }
}

/// Splits one image's contribution into the `peers` partitions (`k mod peers`), with local ids
/// `k / peers` (ascending, as [`aggregate::reduce`] requires), the image's mask count and
/// `scene` (Gaussians, views) in each, its mask table in partition 0's and, with
/// `embeddings_to_all` (the dense reduction needs them), in every partition's.
pub(super) fn split(
    c: &ImageContribution,
    image: u32,
    peers: usize,
    scene: (u64, u32),
    embeddings_to_all: bool,
) -> Vec<ImagePart> {
    let dim = c.dim.max(1);
    let mut parts: Vec<ImagePart> = (0..peers as u32)
        .map(|p| ImagePart {
            partition: p,
            image,
            dim: c.dim as u32,
            scene,
            mask_count: (c.mask_embeddings.len() / dim) as u32,
            mask_embeddings: if p == 0 || embeddings_to_all {
                c.mask_embeddings.clone()
            } else {
                Vec::new()
            },
            local_ids: Vec::new(),
            masks: Vec::new(),
            weights: Vec::new(),
        })
        .collect();
    for e in &c.entries {
        let part = &mut parts[e.gaussian as usize % peers];
        part.local_ids.push(e.gaussian / peers as u32);
        part.masks.push(e.mask);
        part.weights.push(e.weight);
    }
    parts
}

/// The test-only delay before each view a process maps ([`super::MAP_DELAY_VAR`], in
/// milliseconds; unset, empty or unparsable: none): makes one process of a loopback cluster the
/// slow one.
pub(super) fn map_delay() -> Option<std::time::Duration> {
    std::env::var(super::MAP_DELAY_VAR)
        .ok()
        .and_then(|v| v.trim().parse::<u64>().ok())
        .filter(|&ms| ms > 0)
        .map(std::time::Duration::from_millis)
}

pub(super) type Input = InputHandle<u64, CapacityContainerBuilder<Vec<ToReducer>>>;

/// Which partitions a worker's images go to, and how many went to each.
#[derive(Debug, Clone, Default)]
pub(super) struct Shares {
    /// `[P]` the views each partition holds from its checkpoint: `0..held[p]`.
    pub(super) held: Vec<u32>,
    /// `[P]` images this worker sent to each partition.
    pub(super) sent: Vec<u64>,
}

impl Shares {
    /// Sends the parts of `parts` whose partition lacks their view, counting them.
    fn send(&mut self, input: &mut Input, parts: Vec<ImagePart>) {
        self.sent.resize(self.held.len(), 0);
        for part in parts {
            let p = part.partition as usize;
            if self.held.get(p).is_some_and(|&h| h <= part.image) {
                self.sent[p] += 1;
                input.send(ToReducer::Image(part));
            }
        }
    }
}

/// One worker's map loop ([`map_side`]): its timely worker, the ends of its pool (the views it
/// hands to the fronts, the views' `a_kj` and the pool's end), what it sent.
struct MapLoop<'a, 'w> {
    worker: &'w mut timely::worker::Worker,
    input: &'w mut Input,
    job: &'w ClusterJob,
    key: &'w JobKey,
    views: usize,
    /// The process's front workers: it keeps this many views asked for or at a front.
    fronts: usize,
    feeder: ViewsFeeder,
    mapped: mpsc::Receiver<Forwarded>,
    pool_end: mpsc::Receiver<Result<()>>,
    /// Asks sent and not answered yet.
    asked: usize,
    /// No view is left for this worker (or it asks no more): its feeder is closed.
    ended: bool,
    /// The pool has ended (every view handed to it is sent, or it failed).
    pool_done: bool,
    stats: &'a mut MapStats,
    shares: &'a mut Shares,
    /// The first error of this worker's pool.
    failed: Option<Error>,
}

/// The map side of worker `w`: it runs the encode's worker pool over `stages` (its front
/// workers and its rasterizers, [`run_handed`]) on threads of their own, and, while its timely
/// worker keeps stepping (worker 0 answers every worker's asks meanwhile: `handout`, worker 0
/// only), asks worker 0 for a view whenever one of its fronts is free, hands each granted view to
/// the pool and sends each mapped view's parts to the partitions that lack the view, until no
/// view is left or the job aborted. Records the worker's figures in `stats`, the parts sent in
/// `shares`.
///
/// Errors: the pool's first error (it maps nothing more; worker 0 then hands out nothing more).
#[allow(clippy::too_many_arguments)]
pub(super) fn map_side(
    worker: &mut timely::worker::Worker,
    input: &mut Input,
    job: &ClusterJob,
    aborted: &RefCell<Option<String>>,
    views: &[View],
    stages: &mut Stages,
    key: &JobKey,
    (ends, handout): (&mut HandoutEnds, Option<&mut Handout>),
    (stats, shares): (&mut MapStats, &mut Shares),
) -> Result<()> {
    let raster_intrinsics = views
        .iter()
        .map(|v| crate::raster::raster_intrinsics(&v.intrinsics, job.params.raster_scale))
        .collect::<Result<Vec<_>>>()?;
    if let Some(h) = handout.as_deref() {
        stats.resumed = h.skipped();
    }
    let t_map = Instant::now();
    let (fronts, rasterizers) = pool_stages(stages, worker.index());
    let n_fronts = fronts.len();
    let (feeder, handed) = handed_views(map_delay());
    let (forward, mapped) = mpsc::channel::<Forwarded>();
    let (pool_ended, pool_end) = mpsc::channel::<Result<()>>();
    let woken = std::thread::current();
    let run = HandedRun {
        views,
        raster_intrinsics: &raster_intrinsics,
        params: &job.params,
        dim: key.dim as usize,
    };
    let result = std::thread::scope(|s| {
        s.spawn(move || {
            let r = run_handed(run, fronts, rasterizers, handed, forward);
            let _ = pool_ended.send(r.map(drop));
            woken.unpark();
        });
        let mut lp = MapLoop {
            worker,
            input,
            job,
            key,
            views: views.len(),
            fronts: n_fronts,
            feeder,
            mapped,
            pool_end,
            asked: 0,
            ended: false,
            pool_done: false,
            stats: &mut *stats,
            shares,
            failed: None,
        };
        lp.run(aborted, ends, handout);
        lp.failed.take()
    });
    stats.wall_s = t_map.elapsed().as_secs_f64();
    result.map_or(Ok(()), Err)
}

/// The front workers and rasterizers of worker `w`'s pool, taken from `stages` (logged).
fn pool_stages(
    stages: &mut Stages,
    w: usize,
) -> (Vec<FrontStages>, Vec<Box<dyn WeightRasterizer>>) {
    let fronts = std::mem::take(&mut stages.fronts);
    let rasterizers = std::mem::take(&mut stages.rasterizers);
    tracing::info!(
        worker = w,
        fronts = fronts.len(),
        rasterizers = rasterizers.len(),
        "map pool started"
    );
    (fronts, rasterizers)
}

impl MapLoop<'_, '_> {
    /// Steps the worker until its pool has ended and (worker 0, holding `handout`) every
    /// worker's asks are answered; closes its asks, then (worker 0) its grants.
    fn run(
        &mut self,
        aborted: &RefCell<Option<String>>,
        ends: &mut HandoutEnds,
        mut handout: Option<&mut Handout>,
    ) {
        let w = self.worker.index() as u32;
        loop {
            let stopping = self.failed.is_some() || aborted.borrow().is_some();
            let mut moved = false;
            if let Some(h) = handout.as_deref_mut() {
                if stopping {
                    h.stop();
                }
                moved |= ends.serve(h);
            }
            moved |= self.take_grants(stopping, ends);
            moved |= self.ask(stopping, ends, w);
            moved |= self.send_mapped();
            if self.pool_done {
                ends.end_asks();
                if handout.as_deref().is_none_or(|h| ends.served(h)) {
                    break;
                }
            }
            if !moved {
                self.worker.step_or_park(Some(Duration::from_millis(20)));
            } else {
                self.worker.step();
            }
        }
        ends.end_grants();
    }

    /// Hands each view granted to the pool's fronts (drops it when `stopping`); at worker 0's
    /// word that no view is left, or when `stopping`, closes the feeder. Whether anything came.
    fn take_grants(&mut self, stopping: bool, ends: &mut HandoutEnds) -> bool {
        let mut moved = false;
        while !self.ended {
            match ends.granted() {
                Granted::View(i) => {
                    self.asked = self.asked.saturating_sub(1);
                    if stopping || !self.feeder.hand(i as usize) {
                        self.ended = true;
                    }
                }
                Granted::Waiting => break,
                Granted::Ended => self.ended = true,
            }
            moved = true;
        }
        if stopping {
            self.ended = true;
        }
        if self.ended {
            self.feeder.close();
        }
        moved
    }

    /// Asks worker 0 for a view for each front that is free and has none coming: the views
    /// asked for and those at the fronts stay within the fronts. Whether it asked.
    fn ask(&mut self, stopping: bool, ends: &mut HandoutEnds, w: u32) -> bool {
        let mut moved = false;
        while !stopping && !self.ended && self.asked + self.feeder.in_fronts() < self.fronts {
            ends.ask(w);
            self.asked += 1;
            moved = true;
        }
        moved
    }

    /// Sends the parts of every view the pool has mapped; notes the pool's end (and its error).
    /// Whether anything came.
    fn send_mapped(&mut self) -> bool {
        if self.pool_done {
            return false;
        }
        let mut moved = false;
        while let Ok(f) = self.mapped.try_recv() {
            self.sent(f);
            moved = true;
        }
        let end = match self.pool_end.try_recv() {
            Ok(r) => r,
            Err(mpsc::TryRecvError::Empty) => return moved,
            Err(mpsc::TryRecvError::Disconnected) => {
                Err(Error::internal("the map pool's thread ended early"))
            }
        };
        // Every view it mapped was forwarded before it ended.
        while let Ok(f) = self.mapped.try_recv() {
            self.sent(f);
        }
        if let Err(e) = end {
            self.failed.get_or_insert(e);
        }
        (self.pool_done, self.ended) = (true, true);
        self.feeder.close();
        true
    }

    /// Sends view `f.view`'s parts and applies the fault hook.
    fn sent(&mut self, f: Forwarded) {
        let Forwarded {
            view: i,
            work,
            contribution: c,
        } = f;
        self.stats.work.add(&work);
        self.stats.views.push(i as u32);
        let peers = self.worker.peers();
        let scene = (self.key.gaussians, self.views as u32);
        let parts = split(&c, i as u32, peers, scene, self.job.params.dense);
        self.shares.send(self.input, parts);
        self.input.advance_to(self.stats.work.images);
        self.worker.step();
        tracing::info!(
            worker = self.worker.index(),
            image = i,
            views = self.views,
            masks = work.masks,
            "image sent"
        );
        exit_after_images(self.stats.work.images, i);
    }
}

/// The fault hook: exits the process with [`FAULT_EXIT_STATUS`] (as if SIGKILLed, no
/// destructors) once it has sent `images` images when `SLAG_FAULT_EXIT_AFTER_IMAGES` says so.
fn exit_after_images(images: u64, view: usize) {
    let after: Option<u64> = std::env::var("SLAG_FAULT_EXIT_AFTER_IMAGES")
        .ok()
        .and_then(|v| v.trim().parse().ok());
    if after == Some(images) {
        eprintln!("SLAG_FAULT_EXIT_AFTER_IMAGES={images}: process exits after image {view}");
        std::process::exit(FAULT_EXIT_STATUS);
    }
}
