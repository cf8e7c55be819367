//! Resuming a job from its partitions' checkpoints ([`super::checkpoint`]).
//!
//! Once the job's views are agreed, each worker reads its partition's checkpoint (if any) and
//! tells every worker how many views it holds: partition `p` holds views `0..next_p` (a
//! partition takes its views in view order, so its state always covers a prefix). A worker then
//! maps view `i` only when some partition lacks it (`next_p <= i`) and sends its share only to
//! those partitions: no view is folded twice into a partition and none is lost, and views every
//! partition holds are not rasterized again.

use std::cell::RefCell;
use std::rc::Rc;
use std::time::{Duration, Instant};

use ring::digest::{Context, SHA256};
use serde::{Deserialize, Serialize};
use slag_common::camera::View;
use slag_common::scene::Gaussians;
use slag_common::{Error, Result};
use timely::container::CapacityContainerBuilder;
use timely::dataflow::InputHandle;

use super::checkpoint::{self, Saved};
use super::config::ClusterJob;
use super::inbox::build_inbox;
use super::records::JobKey;
use super::reduce::{Checkpointer, Resume};

/// SHA-256 of what a checkpoint must belong to: the job's fingerprint (`key`: Gaussians, views,
/// width, parameters), the report header's inputs, models and parameters (but the threads, GPUs,
/// fronts, memory budgets and addresses, which do not change the outputs), the processes, each
/// chosen view's name, intrinsics and pose, and the Gaussians' means, scales, rotations and
/// opacities. The images themselves are named, not read.
pub(super) fn job_digest(
    job: &ClusterJob,
    key: &JobKey,
    views: &[View],
    gaussians: &Gaussians,
    peers: usize,
) -> [u8; 32] {
    let mut h = Context::new(&SHA256);
    h.update(b"slag encode-cluster job 1\n");
    h.update(format!("{key:?} processes {peers}\n").as_bytes());
    let mut header = job.report.clone();
    let p = &mut header.parameters;
    p.threads = 0;
    (p.cluster_addresses, p.cluster_processes) = (None, None);
    (p.device_reduce_budget, p.front_workers) = (None, None);
    p.gpus.clear();
    for part in [
        serde_json::to_vec(&header.inputs),
        serde_json::to_vec(&header.models),
        serde_json::to_vec(&header.parameters),
    ] {
        h.update(&part.unwrap_or_default());
    }
    for v in views {
        let line = format!("{} {:?} {:?}\n", v.name, v.intrinsics, v.world_to_camera);
        h.update(line.as_bytes());
    }
    let floats = gaussians
        .means
        .iter()
        .chain(&gaussians.scales)
        .flatten()
        .chain(gaussians.rotations.iter().flatten())
        .chain(&gaussians.opacities);
    let mut buf = Vec::with_capacity(1 << 16);
    for x in floats {
        buf.extend_from_slice(&x.to_le_bytes());
        if buf.len() >= 1 << 16 {
            h.update(&buf);
            buf.clear();
        }
    }
    h.update(&buf);
    let mut out = [0u8; 32];
    out.copy_from_slice(h.finish().as_ref());
    out
}

/// The state partition `partition` of `peers` starts from: its checkpoint under `out` when it
/// belongs to job `digest`, none when there is none, or when it is damaged (a warning says so:
/// the partition starts afresh and the next checkpoint replaces it).
///
/// Errors: a checkpoint of another job ([`Saved::check_job`], [`Error::Format`] telling what to
/// do); an unreadable one ([`Error::Io`]).
pub(super) fn read_checkpoint(
    out: &std::path::Path,
    partition: u32,
    peers: u32,
    digest: &[u8; 32],
) -> Result<Option<Saved<'static>>> {
    let path = checkpoint::path(out, partition, peers);
    if !path.exists() {
        return Ok(None);
    }
    match checkpoint::read(&path) {
        Ok(saved) => {
            saved.check_job(&path, digest, partition, peers)?;
            Ok(Some(saved))
        }
        Err(e @ Error::Format { .. }) => {
            tracing::warn!("{e}");
            eprintln!("warning: {e}");
            Ok(None)
        }
        Err(e) => Err(e),
    }
}

/// The partition's [`Resume`] and the views it holds: the checkpoint of this job under the
/// output folder (if any) and, with `every` (`None`: checkpoints off, or the dense file, whose
/// contributions a checkpoint does not hold), where and how often to write the next ones.
///
/// Errors: as [`read_checkpoint`].
pub(super) fn partition_resume(
    job: &ClusterJob,
    (partition, peers): (u32, u32),
    digest: [u8; 32],
    every: Option<Duration>,
) -> Result<(Resume, u32)> {
    let out = &job.params.out_dir;
    let saved = read_checkpoint(out, partition, peers, &digest)?;
    let next = saved.as_ref().map_or(0, |s| s.progress.next);
    let checkpoints = every.map(|every| Checkpointer {
        path: checkpoint::path(out, partition, peers),
        job: digest,
        every,
        last: Instant::now(),
        written: next,
        count: 0,
        seconds: 0.0,
        bytes: 0,
    });
    Ok((Resume { saved, checkpoints }, next))
}

/// What worker `from` tells worker `to`: the views its partition holds (`0..n`), or why it
/// could not say.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub(super) struct ResumeNote {
    to: u32,
    from: u32,
    held: std::result::Result<u32, String>,
}

pub(super) type ResumeInput = InputHandle<u64, CapacityContainerBuilder<Vec<ResumeNote>>>;

/// What a worker has heard: each worker's note, and whether every worker closed its side.
#[derive(Default)]
pub(super) struct Notes {
    held: Vec<Option<std::result::Result<u32, String>>>,
    closed: bool,
}

/// Builds the dataflow that carries each worker's note to every worker (built identically on
/// every worker); what this worker hears lands in `notes`.
pub(super) fn build_resume_dataflow(
    worker: &mut timely::worker::Worker,
    input: &mut ResumeInput,
    notes: &Rc<RefCell<Notes>>,
) {
    // One slot per worker, each empty until its note comes.
    notes.borrow_mut().held.resize(worker.peers(), None);
    build_inbox(
        worker,
        input,
        ("resume", |n: &ResumeNote| n.to as u64),
        notes,
        (
            |notes: &mut Notes, n: ResumeNote| {
                if let Some(slot) = notes.held.get_mut(n.from as usize) {
                    slot.get_or_insert(n.held);
                }
            },
            |notes: &mut Notes| notes.closed = true,
        ),
    );
}

/// Tells every worker `held` (the views this worker's partition holds, or why it failed), closes
/// `input` and waits for every worker's note: the views each partition holds, by partition.
///
/// Errors: a worker's failure ([`Error::Invalid`] naming it), a worker that ended without a note.
pub(super) fn agree_on_resume(
    worker: &mut timely::worker::Worker,
    mut input: ResumeInput,
    notes: &RefCell<Notes>,
    held: std::result::Result<u32, String>,
) -> Result<Vec<u32>> {
    let from = worker.index() as u32;
    for to in 0..worker.peers() as u32 {
        input.send(ResumeNote {
            to,
            from,
            held: held.clone(),
        });
    }
    drop(input);
    let heard = |n: &Notes| n.closed || (!n.held.is_empty() && n.held.iter().all(Option::is_some));
    while !heard(&notes.borrow()) {
        worker.step_or_park(None);
    }
    let held = std::mem::take(&mut notes.borrow_mut().held);
    held.into_iter()
        .enumerate()
        .map(|(p, h)| match h {
            Some(Ok(n)) => Ok(n),
            Some(Err(m)) => Err(Error::Invalid(format!("process {p}: {m}"))),
            None => Err(Error::Invalid(format!(
                "process {p} ended without saying which views its partition holds"
            ))),
        })
        .collect()
}
