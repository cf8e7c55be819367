//! The map side: each worker encodes the views worker 0 hands it ([`super::handout`]: masks →
//! CLIP → raster → `a_kj`, on a thread of its own while its timely worker keeps stepping) and
//! splits each image's `a_kj` by partition `p = k mod P` into [`ToReducer`] records.

use std::cell::RefCell;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use slag_common::camera::{Intrinsics, View};
use slag_common::{Error, Result};
use timely::container::CapacityContainerBuilder;
use timely::dataflow::InputHandle;

use super::FAULT_EXIT_STATUS;
use super::config::{ClusterJob, Stages};
use super::handout::{Granted, Handout, HandoutEnds};
use super::records::{ImagePart, JobKey, MapStats, ToReducer};
use crate::aggregate::ImageContribution;
use crate::aggregate::ImageStageParams;
use crate::pipeline::{back_stage, front_stage};
use crate::report::ImageWork;

/// The fingerprint of the parameters every process must share.
pub(super) fn job_key(
    job: &ClusterJob,
    gaussians: usize,
    views: &[slag_common::camera::View],
    dim: usize,
    stages: &Stages,
) -> JobKey {
    let p = &job.params;
    JobKey {
        gaussians: gaussians as u64,
        views: views.len() as u64,
        dim: dim as u64,
        fingerprint: format!(
            "views {:?}..{:?} every {} hold_out_every {:?} selection {:?} raster_scale {} image_stage {:?} masks {} clip {} min_weight {} mixture_keep {:?} dense {} record {:?}",
            views.first().map(|v| &v.name),
            views.last().map(|v| &v.name),
            job.scene.every,
            job.scene.hold_out_every,
            job.scene.selection,
            p.raster_scale,
            p.image_stage,
            stages.masks.name(),
            stages.crops.model_id(),
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

/// What a worker's map thread needs of the job to map a view: the job's views, their raster
/// intrinsics, the embedding width, the image stage's parameters and the test-only delay.
struct ViewJob<'a> {
    views: &'a [View],
    raster_intrinsics: Vec<Intrinsics>,
    dim: usize,
    image_stage: ImageStageParams,
    delay: Option<Duration>,
}

/// One view mapped: its work figures and its contribution.
type Mapped = Result<(ImageWork, ImageContribution)>;

impl ViewJob<'_> {
    /// Maps view `i` on `stages`: masks → CLIP crops → weight raster → `a_kj`.
    fn map(&self, i: usize, stages: &mut Stages) -> Mapped {
        if let Some(d) = self.delay {
            std::thread::sleep(d);
        }
        let item = front_stage(
            &self.views[i],
            i,
            &mut *stages.masks,
            &mut *stages.crops,
            self.dim,
        )?;
        let n_masks = item.masks.len();
        let (decode_s, masks_s, clip_s) = (item.decode_s, item.masks_s, item.clip_s);
        let out = back_stage(
            &mut *stages.rasterizer,
            self.views,
            &self.raster_intrinsics,
            item,
            self.dim,
            self.image_stage,
        )?;
        let entries = out.contribution.entries.len();
        let work = out.work(decode_s, masks_s, clip_s, n_masks, entries);
        Ok((work, out.contribution))
    }
}

/// Where one worker's map loop stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Turn {
    /// No view in hand: ask for one.
    Idle,
    /// Asked; waiting for worker 0's grant.
    Asked,
    /// Its map thread maps this view.
    Mapping(u32),
    /// No more views for this worker.
    Ended,
}

/// The map side of worker `w`: it asks worker 0 for a view, maps it on its map thread while its
/// timely worker keeps stepping (worker 0 answers the others' asks meanwhile: `handout`, worker
/// 0 only), sends the image's parts to the partitions that lack the view and asks again, until
/// no view is left or the job aborted. Records the worker's figures in `stats`, the parts sent
/// in `shares`.
///
/// Errors: the first view this worker failed to map (it maps nothing more; worker 0 then hands
/// out nothing more).
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
    let view_job = ViewJob {
        views,
        raster_intrinsics: views
            .iter()
            .map(|v| crate::raster::raster_intrinsics(&v.intrinsics, job.params.raster_scale))
            .collect::<Result<Vec<_>>>()?,
        dim: key.dim as usize,
        image_stage: job.params.image_stage,
        delay: map_delay(),
    };
    if let Some(h) = handout.as_deref() {
        stats.resumed = h.skipped();
    }
    let t_map = Instant::now();
    let (to_thread, views_in) = mpsc::channel::<usize>();
    let (mapped_out, mapped) = mpsc::channel::<(usize, Mapped)>();
    let woken = std::thread::current();
    let result = std::thread::scope(|s| {
        s.spawn(move || {
            for i in views_in {
                let r = view_job.map(i, stages);
                let _ = mapped_out.send((i, r));
                woken.unpark();
            }
        });
        let mut lp = MapLoop {
            worker,
            input,
            job,
            key,
            views: views.len(),
            to_thread,
            mapped,
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

/// One worker's map loop ([`map_side`]): its timely worker, its map thread's ends, what it sent.
struct MapLoop<'a, 'w> {
    worker: &'w mut timely::worker::Worker,
    input: &'w mut Input,
    job: &'w ClusterJob,
    key: &'w JobKey,
    views: usize,
    to_thread: mpsc::Sender<usize>,
    mapped: mpsc::Receiver<(usize, Mapped)>,
    stats: &'a mut MapStats,
    shares: &'a mut Shares,
    /// The first view this worker failed to map.
    failed: Option<Error>,
}

impl MapLoop<'_, '_> {
    /// Steps the worker until its views are mapped and (worker 0, holding `handout`) every
    /// worker's asks are answered; closes its asks, then (worker 0) its grants.
    fn run(
        &mut self,
        aborted: &RefCell<Option<String>>,
        ends: &mut HandoutEnds,
        mut handout: Option<&mut Handout>,
    ) {
        let w = self.worker.index() as u32;
        let mut turn = Turn::Idle;
        loop {
            let stopping = self.failed.is_some() || aborted.borrow().is_some();
            let mut moved = false;
            if let Some(h) = handout.as_deref_mut() {
                if stopping {
                    h.stop();
                }
                moved |= ends.serve(h);
            }
            let next = self.turn(turn, stopping, ends, w);
            moved |= next != turn;
            turn = next;
            if turn == Turn::Ended {
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

    /// The next turn of worker `w` from `turn` (`stopping`: the job failed, ask nothing more).
    fn turn(&mut self, turn: Turn, stopping: bool, ends: &mut HandoutEnds, w: u32) -> Turn {
        match turn {
            Turn::Idle if stopping => Turn::Ended,
            Turn::Idle => {
                ends.ask(w);
                Turn::Asked
            }
            Turn::Asked => match ends.granted() {
                Granted::View(i) if !stopping && self.to_thread.send(i as usize).is_ok() => {
                    Turn::Mapping(i)
                }
                Granted::Waiting => Turn::Asked,
                _ => Turn::Ended,
            },
            Turn::Mapping(_) => match self.mapped.try_recv() {
                Ok((i, r)) => self.sent(i, r),
                Err(mpsc::TryRecvError::Empty) => turn,
                Err(mpsc::TryRecvError::Disconnected) => {
                    self.failed
                        .get_or_insert_with(|| Error::internal("the map thread ended early"));
                    Turn::Ended
                }
            },
            Turn::Ended => Turn::Ended,
        }
    }

    /// Sends view `i`'s parts (or keeps its error) and applies the fault hook; the next turn.
    fn sent(&mut self, i: usize, mapped: Mapped) -> Turn {
        let (work, c) = match mapped {
            Ok(m) => m,
            Err(e) => {
                self.failed.get_or_insert(e);
                return Turn::Ended;
            }
        };
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
        Turn::Idle
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
