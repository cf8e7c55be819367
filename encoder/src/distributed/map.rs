//! The map side: each worker encodes its images (masks → CLIP → raster → `a_kj`) and splits
//! each image's `a_kj` by partition `p = k mod P` into [`ToReducer`] records.

use std::cell::RefCell;
use std::time::Instant;

use slag_common::Result;
use timely::container::CapacityContainerBuilder;
use timely::dataflow::InputHandle;

use super::FAULT_EXIT_STATUS;
use super::config::{ClusterJob, Stages};
use super::records::{ImagePart, JobKey, MapStats, ToReducer};
use crate::aggregate::ImageContribution;
use crate::pipeline::{back_stage, front_stage};

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
    /// Whether some partition lacks view `view` (it must be mapped).
    fn needed(&self, view: usize) -> bool {
        self.held.iter().any(|&h| h as usize <= view)
    }

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

/// The map side of worker `w`: images `w, w + P, …` that some partition lacks (`shares.held`);
/// sends each image's parts to the partitions that lack it and advances the input's time so
/// they leave at once. Records the worker's figures in `stats`, the parts sent in `shares`.
#[allow(clippy::too_many_arguments)]
pub(super) fn map_side(
    worker: &mut timely::worker::Worker,
    input: &mut Input,
    job: &ClusterJob,
    aborted: &RefCell<Option<String>>,
    views: &[slag_common::camera::View],
    stages: &mut Stages,
    key: &JobKey,
    (stats, shares): (&mut MapStats, &mut Shares),
) -> Result<()> {
    let (w, peers) = (worker.index(), worker.peers());
    let dim = key.dim as usize;
    let fault_after: Option<u64> = std::env::var("SLAG_FAULT_EXIT_AFTER_IMAGES")
        .ok()
        .and_then(|v| v.trim().parse().ok());
    let delay = map_delay();
    let raster_intrinsics = views
        .iter()
        .map(|v| crate::raster::raster_intrinsics(&v.intrinsics, job.params.raster_scale))
        .collect::<Result<Vec<_>>>()?;
    let t_map = Instant::now();
    for (round, i) in (w..views.len()).step_by(peers).enumerate() {
        if aborted.borrow().is_some() {
            break;
        }
        if !shares.needed(i) {
            stats.resumed += 1;
            continue;
        }
        if let Some(d) = delay {
            std::thread::sleep(d);
        }
        let item = front_stage(&views[i], i, &mut *stages.masks, &mut *stages.crops, dim)?;
        let n_masks = item.masks.len();
        let (decode_s, masks_s, clip_s) = (item.decode_s, item.masks_s, item.clip_s);
        let out = back_stage(
            &mut *stages.rasterizer,
            views,
            &raster_intrinsics,
            item,
            dim,
            job.params.image_stage,
        )?;
        stats.work.add(&out.work(
            decode_s,
            masks_s,
            clip_s,
            n_masks,
            out.contribution.entries.len(),
        ));
        let c = out.contribution;
        let scene = (key.gaussians, views.len() as u32);
        shares.send(input, split(&c, i as u32, peers, scene, job.params.dense));
        input.advance_to(round as u64 + 1);
        worker.step();
        tracing::info!(
            worker = w,
            image = i,
            views = views.len(),
            masks = n_masks,
            "image sent"
        );
        if fault_after == Some(stats.work.images) {
            eprintln!(
                "SLAG_FAULT_EXIT_AFTER_IMAGES={}: process exits after image {i}",
                stats.work.images
            );
            std::process::exit(FAULT_EXIT_STATUS);
        }
    }
    stats.wall_s = t_map.elapsed().as_secs_f64();
    Ok(())
}
