//! The encode as a map/reduce job over several processes (and machines), on timely dataflow's
//! multi-process TCP cluster (`slag-encoder encode-cluster`).
//!
//! ```text
//!   views  (worker 0):  the view selection (coverage by default) on its rasterizer, run once;
//!          the chosen names sent to every worker ([`views`]) before the map starts
//!   hand-out (worker 0): the next view nobody has taken, to whichever worker asks ([`handout`])
//!   map    (worker w, the views it was handed, on the encode's worker pool: its front workers
//!          and one rasterizer per GPU):  masks → CLIP crops → weight raster → a_kj
//!          (aggregate::image_contribution), split by partition p = k mod P
//!   exchange (timely Exchange pact, key p): the image's a_kj of partition p with local ids k / P
//!          and its mask count; its mask table E_j to partition 0 (to all with --dense)
//!   reduce (worker p):  for k ≡ p mod P only, as views arrive (folded in view order): the
//!          mixture's running state (aggregate::MixtureFold over the partition's Gaussians;
//!          partition 0 also keeps the codebook), the masks' record of its Gaussians; with
//!          --dense its contributions, then E_k = Σ a_kj E_j / Σ a_kj by aggregate::reduce
//!   gather (worker 0):  rows of every partition + per-partition counts → mixture.safetensors,
//!          (embeddings.safetensors), report.json, written by process 0 only after every process
//!          has finished; the masks' record and the segments (computed on process 0 beside the
//!          job) after them, as `encode` writes them
//! ```
//!
//! One timely worker per process. Each process owns its ONNX Runtime sessions and its GPU
//! rasterizers and runs `encode`'s worker pool (`pipeline::handed`): `--front-workers` front
//! workers and one rasterizer per `--gpus` GPU, with `encode`'s defaults; `--threads` goes to
//! ONNX Runtime and rayon. These are each process's own (processes may differ in GPUs); every
//! other encode argument and the host list are the same on every process; process `I` listens
//! on line `I` of the list.
//!
//! # Views by work done
//!
//! A process asks worker 0 for the next view nobody has taken ([`handout`]) whenever one of its
//! front workers is free (it keeps at most as many views asked for or at its fronts as it has
//! fronts), so a slower process (a slower GPU, a busier host) maps fewer views instead of
//! holding the job back. The outputs do not depend on who mapped what, nor on the order in which
//! a process's views finish: each partition folds the views in view order, and the end records
//! count the images each worker sent. Each process maps on threads of its own while its timely
//! worker keeps stepping (answering asks on worker 0, folding its partition's parts as they
//! arrive); the report lists the views each process mapped (`outputs.cluster.workers[].views`).
//!
//! # What the map emits
//!
//! An image's per-Gaussian terms factorise through its mask table, so the map side ships the
//! sparse `a_kj` (12 bytes each) instead of dense f64 `[D]` partial sums (4 KiB per Gaussian at
//! D = 512): on snowmiku ~35 non-zero `a_kj` per Gaussian over 49 views. The mixture needs each
//! view's mask count (to number the codebook's atoms) but its mask embeddings only where the
//! codebook is assembled. A Gaussian's terms are added in view order whichever partition holds it,
//! so the mixture and the record are those of a one-process `encode --reduce host` bit for bit; the
//! dense reduction is [`crate::aggregate::reduce`] unchanged over each partition's local ids.
//!
//! # Memory
//!
//! A map worker holds the images of its pool, as `encode` does (one per front worker, the
//! queue to its rasterizers, three per rasterizer). A reducer holds the running state of `N / P`
//! Gaussians (`MixtureFold::state_bytes_per_gaussian`, the record's slots) and the views that
//! arrived before an earlier one; with `--dense` its partition's contributions up to
//! `contribution_budget_bytes`, the rest spilled to `OUT/.cluster-<process>.partial/`, and an f64
//! accumulator chunked to `reduce.accumulator_budget_bytes`. Process 0 holds the codebook and the
//! final rows, as `encode` does.
//!
//! # Completeness and failure
//!
//! Every map worker ends with a `Done` record to every partition carrying the number of images it
//! sent and a fingerprint of the job (Gaussians, views, embedding width, parameters); a reducer
//! reduces only when it holds `Done` from all `P` workers with equal fingerprints and exactly
//! one contribution per view; worker 0 assembles only when it holds the summary of all `P`
//! partitions and each partition's row counts (dense, mixture, record) match the rows received.
//! Process 0 then writes its files (each temporary file + rename) and `report.json` last, after
//! timely has shut down every connection cleanly, i.e. after every process completed.
//!
//! An error in any worker (bad image, model failure) is broadcast as an `Abort` record: every
//! process exits non-zero with that message and nothing is written. A process that dies
//! (`kill -9`, machine loss) closes its TCP connections; timely's network threads then panic with
//! "timely communication error"; [`encode_cluster`] turns that into an immediate exit with status
//! [`EXIT_PEER_LOST`] and a message naming the process that died and its address (each peer's
//! stream records its index when it fails, [`net::PeerStream`]), after removing its own spill
//! folder. timely has no fault tolerance: a job that lost a process is rerun, and the rerun
//! resumes from the partitions' checkpoints.
//!
//! # Checkpoints
//!
//! A partition takes its views in view order (those that arrive early wait), so its state always
//! covers views `0..n`; at most every [`ClusterConfig::checkpoint_every`] it writes that state
//! (`checkpoint.rs`: the fold, the record, `n`, a digest of the job) atomically. Before the map of
//! a rerun every worker reads its partition's checkpoint and tells every worker its `n`
//! (`resume.rs`); a view is mapped only when some partition lacks it and its parts go only to
//! those partitions, so each partition takes in every view exactly once, and its rows are those
//! of an uninterrupted run bit for bit. No checkpoint is written with `--dense`.
//!
//! # Connections
//!
//! The TCP connections are made by [`net::connect_peers`], not by timely: each starts with a
//! mutual HMAC challenge on the cluster secret ([`ClusterSecret`]; without one only on loopback,
//! [`ClusterConfig::check_secret`]), and only connections that pass it are handed to timely
//! (`initialize_networking_from_sockets`, `execute_from`).
//!
//! # Fault injection (tests only)
//!
//! `SLAG_FAULT_EXIT_AFTER_IMAGES=<n>` makes a process exit with status 137 (as if SIGKILLed, no
//! destructors, no connection shutdown) right after it has sent its n-th image.
//! `SLAG_TEST_MAP_DELAY_MS=<ms>` ([`MAP_DELAY_VAR`]) makes each front worker of a process wait
//! that long before each view it takes: a slow process, on one machine.

use std::cell::RefCell;
use std::path::{Path, PathBuf};
use std::rc::Rc;
use std::sync::Arc;
use std::time::Instant;

use slag_common::camera::View;
use slag_common::embeddings::Embeddings;
use slag_common::scene::Gaussians;
use slag_common::{Error, Result};
use timely::container::CapacityContainerBuilder;
use timely::dataflow::channels::pact::Exchange;
use timely::dataflow::operators::Operator;

use crate::aggregate::ContributionStore;
use crate::pipeline::finish::OutputFiles;
use crate::report::Report;

mod checkpoint;
mod config;
mod encoder;
mod gather;
mod handout;
mod inbox;
mod map;
pub mod net;
mod records;
mod reduce;
mod resume;
mod views;

pub use config::{
    ClusterConfig, ClusterJob, DEFAULT_CHECKPOINT_EVERY, SegmentFeed, StageFactory, Stages,
};
pub use encoder::ClusterEncoder;
use gather::{Assembled, Gathered, WorkerOutcome, assemble};
use handout::{Handout, HandoutEnds, build_handout_dataflows};
use map::{Input, job_key, map_side};
pub use net::ClusterSecret;
use net::{LostPeer, PeerStream};
use records::{JobKey, MapStats, ToGather, ToReducer};
use reduce::{Forms, PartitionReducer, Resume};
use resume::{Notes, ResumeInput, agree_on_resume, build_resume_dataflow};
use views::{Heard, ViewsInput, agree_on_views, build_views_dataflow, refuse_views};

/// Exit status of a process that lost a peer process (its TCP connection failed) or hit an
/// internal panic: the job failed, wrote no output, and is to be rerun.
pub const EXIT_PEER_LOST: i32 = 3;

/// Test-only: the environment variable whose value (milliseconds) a process waits before each
/// view it maps, as a slower GPU or a busier host would (the cluster tests and
/// `scripts/lab/cluster-loopback.sh` make one process slow with it). Not for production runs.
pub const MAP_DELAY_VAR: &str = "SLAG_TEST_MAP_DELAY_MS";

/// Exit status of the fault hook (`SLAG_FAULT_EXIT_AFTER_IMAGES`): 128 + SIGKILL.
pub const FAULT_EXIT_STATUS: i32 = slag_common::fault::FAULT_EXIT_STATUS;

/// The dataflows' ends on one worker ([`build_dataflows`]): the inputs it sends on and what it
/// hears.
struct Dataflows {
    views: ViewsInput,
    heard: Rc<RefCell<Heard>>,
    resume: ResumeInput,
    notes: Rc<RefCell<Notes>>,
    /// Where this worker puts its partition's [`Resume`] for its reducer.
    slot: Rc<RefCell<Option<Resume>>>,
    handout: HandoutEnds,
    input: Input,
    aborted: Rc<RefCell<Option<String>>>,
    gathered: Rc<RefCell<Gathered>>,
}

/// Builds the job's dataflows, identically on every worker and in the same order: the views'
/// choice, the partitions' notes of what their checkpoints hold, the views' hand-out, the map →
/// reduce → gather job.
fn build_dataflows(worker: &mut timely::worker::Worker, job: &ClusterJob) -> Dataflows {
    let (w, peers) = (worker.index(), worker.peers());
    let mut views = ViewsInput::new();
    let heard = Rc::new(RefCell::new(Heard::default()));
    build_views_dataflow(worker, &mut views, &heard);
    let mut resume = ResumeInput::new();
    let notes = Rc::new(RefCell::new(Notes::default()));
    build_resume_dataflow(worker, &mut resume, &notes);
    let mut d = Dataflows {
        views,
        heard,
        resume,
        notes,
        slot: Rc::new(RefCell::new(None)),
        handout: build_handout_dataflows(worker),
        input: Input::new(),
        aborted: Rc::new(RefCell::new(None)),
        gathered: Rc::new(RefCell::new(Gathered::default())),
    };
    let spill_dir = spill_dir(&job.params.out_dir, w);
    let reducer = PartitionReducer::new(
        w as u32,
        peers as u32,
        job.params.reduce,
        forms_of(&job.params),
        ContributionStore::new(job.params.contribution_budget_bytes, spill_dir),
        Rc::clone(&d.slot),
    );
    build_dataflow(worker, &mut d.input, reducer, &d.aborted, &d.gathered);
    d
}

/// Runs one worker: builds the dataflows (identically on every worker), the map side (with
/// checkpoints every `every`, `None`: off), then steps until the dataflow completed; worker 0
/// assembles the output.
fn run_worker(
    worker: &mut timely::worker::Worker,
    job: &ClusterJob,
    every: Option<std::time::Duration>,
) -> Result<WorkerOutcome> {
    let (w, peers) = (worker.index(), worker.peers());
    let Dataflows {
        views,
        heard,
        resume,
        notes,
        slot,
        handout,
        mut input,
        aborted,
        gathered,
    } = build_dataflows(worker, job);
    // Map side. Errors are broadcast as Abort so every process fails with the same message.
    let mut map = MapOutcome {
        stats: MapStats {
            worker: w as u32,
            ..Default::default()
        },
        ..Default::default()
    };
    let agree = Agreements {
        views: (views, &*heard),
        resume: (resume, &*notes, &*slot),
        every,
        handout,
    };
    let result = run_map(worker, &mut input, agree, job, &aborted, &mut map);
    let failed = result.as_ref().err().map(|e| format!("process {w}: {e}"));
    send_done(&mut input, peers, w, failed, &map);
    drop(input);
    while worker.has_dataflows() {
        worker.step_or_park(None);
    }
    result?;
    let gathered = std::mem::take(&mut *gathered.borrow_mut());
    let images = map.stats.work.images;
    if w != 0 {
        if let Some(m) = aborted.borrow_mut().take() {
            return Err(Error::Invalid(format!("the job was aborted: {m}")));
        }
        return Ok(WorkerOutcome {
            output: None,
            selection: None,
            models: map.models,
            images,
        });
    }
    let (gaussians, _, views_total) = map
        .scene
        .ok_or_else(|| Error::internal("worker 0 has no scene"))?;
    let forms = forms_of(&job.params);
    let output = assemble(
        gathered,
        peers,
        forms,
        &gaussians,
        views_total,
        map.load_scene_s,
    )?;
    Ok(WorkerOutcome {
        output: Some(output),
        selection: map.selection,
        models: map.models,
        images,
    })
}

/// What the workers agree on before the map starts: the views (worker 0's choice) and what each
/// partition's checkpoint holds; `every` is the checkpoints' interval (`None`: off); then the
/// views are handed out over `handout`.
struct Agreements<'a> {
    views: (ViewsInput, &'a RefCell<Heard>),
    resume: (ResumeInput, &'a RefCell<Notes>, &'a RefCell<Option<Resume>>),
    every: Option<std::time::Duration>,
    handout: HandoutEnds,
}

/// The outputs a partition reduces to for an encode of `params`.
fn forms_of(params: &crate::pipeline::EncodeParams) -> Forms {
    Forms {
        dense: params.dense,
        mixture_keep: params.mixture_keep,
        record_slots: params.mask_record_slots,
    }
}

/// Builds the dataflow (identically on every worker): the records of `input` go to their
/// partition's reducer, which reduces once its frontier is empty and sends its rows and
/// summary to worker 0's `gathered`; the message of an `Abort` a reducer sees is kept in
/// `aborted`.
fn build_dataflow(
    worker: &mut timely::worker::Worker,
    input: &mut Input,
    reducer: PartitionReducer,
    aborted: &Rc<RefCell<Option<String>>>,
    gathered: &Rc<RefCell<Gathered>>,
) {
    worker.dataflow::<u64, _, _>(|scope| {
        let aborted = Rc::clone(aborted);
        let gathered = Rc::clone(gathered);
        input
            .to_stream(scope)
            .unary_frontier::<CapacityContainerBuilder<Vec<ToGather>>, _, _, _>(
                Exchange::new(|r: &ToReducer| r.partition() as u64),
                "reduce",
                move |capability, _info| {
                    let mut capability = Some(capability);
                    let mut reducer = Some(reducer);
                    move |(input, frontier), output| {
                        input.for_each(|_time, data| {
                            for record in data.drain(..) {
                                if let ToReducer::Abort { message, .. } = &record {
                                    aborted.borrow_mut().get_or_insert_with(|| message.clone());
                                }
                                if let Some(r) = reducer.as_mut() {
                                    r.absorb(record);
                                }
                            }
                        });
                        if frontier.is_empty()
                            && let (Some(cap), Some(r)) = (capability.take(), reducer.take())
                        {
                            let mut session = output.session(&cap);
                            for record in r.finish() {
                                session.give(record);
                            }
                        }
                    }
                },
            )
            .sink(
                Exchange::new(|_: &ToGather| 0),
                "gather",
                move |(input, _)| {
                    input.for_each(|_time, data| {
                        for record in data.drain(..) {
                            gathered.borrow_mut().absorb(record);
                        }
                    });
                },
            );
    });
}

/// What the map side of one worker leaves for the end of the job, also when it failed.
#[derive(Default)]
struct MapOutcome {
    /// Seconds to load the scene and choose its views.
    load_scene_s: f64,
    /// The names of the rasterizer, the CLIP model and the mask source.
    models: [String; 3],
    /// The job's fingerprint, once the stages are built.
    key: Option<JobKey>,
    /// The scene (Gaussians, chosen views, training views in all), once the map side ran.
    scene: Option<(Arc<Gaussians>, Vec<View>, usize)>,
    /// Worker 0: what the report records of the view selection.
    selection: Option<crate::views::SelectionReport>,
    /// This worker's map figures.
    stats: MapStats,
    /// What each partition holds from its checkpoint and the parts this worker sent it.
    shares: map::Shares,
}

/// Loads the scene, builds the stages, agrees on the views with every worker (worker 0 chooses
/// them, [`agree_on_views`]) and on what each partition's checkpoint holds
/// ([`agree_on_checkpoints`]), and runs the map side of this worker, recording in `out` what the
/// end of the job needs. On process 0 the loaded Gaussians also go to the segments
/// ([`ClusterJob::segments`]).
///
/// Errors: the scene's or the stages' ([`Error`]), the views' choice, no views, a checkpoint of
/// another job (on any process), the map side's.
fn run_map(
    worker: &mut timely::worker::Worker,
    input: &mut Input,
    agree: Agreements<'_>,
    job: &ClusterJob,
    aborted: &RefCell<Option<String>>,
    out: &mut MapOutcome,
) -> Result<()> {
    let t_load = Instant::now();
    let prepared = job.scene.load().and_then(|(gaussians, training, total)| {
        let stages = (job.stages)(&gaussians)?;
        Ok((Arc::new(gaussians), training, total, stages))
    });
    let (views_input, heard) = agree.views;
    let (gaussians, training, total, mut stages) = match prepared {
        Ok(p) => p,
        Err(e) => {
            refuse_views(worker, views_input, &e.to_string());
            return Err(e);
        }
    };
    if let Some(feed) = &job.segments {
        feed.send_scene(&gaussians);
    }
    let (views, selection) = agree_on_views(
        worker,
        views_input,
        heard,
        &job.scene,
        (&gaussians, training),
        &mut stages.rasterizers,
    )?;
    out.selection = selection;
    let scene = (gaussians, views, total);
    out.load_scene_s = t_load.elapsed().as_secs_f64();
    if scene.1.is_empty() {
        return Err(crate::pipeline::no_views(&job.scene, scene.2));
    }
    let front = stages.first_front()?;
    out.models = [
        stages.rasterizer_name(),
        front.crops.model_id().to_string(),
        front.masks.name().to_string(),
    ];
    let k = job_key(job, scene.0.len(), &scene.1, front);
    out.key = Some(k.clone());
    let held = agree_on_checkpoints(
        worker,
        agree.resume,
        agree.every,
        job,
        (&scene.0, &scene.1),
        &k,
    );
    let mut ends = agree.handout;
    let r = held.and_then(|held| {
        // Worker 0 hands out the views some partition lacks.
        let mut handout =
            (worker.index() == 0).then(|| Handout::new(scene.1.len(), &held, worker.peers()));
        out.shares.held = held;
        let shares = (&mut out.stats, &mut out.shares);
        map_side(
            worker,
            input,
            job,
            aborted,
            &scene.1,
            &mut stages,
            &k,
            (&mut ends, handout.as_mut()),
            shares,
        )
    });
    out.scene = Some(scene);
    r
}

/// Reads this worker's partition's checkpoint of the job (`key` on `gaussians` and `views`,
/// [`resume::job_digest`]), hands it and the checkpoints' settings (interval `every`, off with
/// `--dense`) to the partition's reducer through `slot`, and agrees with every worker on what
/// each partition holds ([`agree_on_resume`]): `[P]` views `0..held[p]`.
///
/// Errors: a checkpoint of another job or unreadable, on this or another process.
fn agree_on_checkpoints(
    worker: &mut timely::worker::Worker,
    (input, notes, slot): (ResumeInput, &RefCell<Notes>, &RefCell<Option<Resume>>),
    every: Option<std::time::Duration>,
    job: &ClusterJob,
    (gaussians, views): (&Gaussians, &[View]),
    key: &JobKey,
) -> Result<Vec<u32>> {
    let (w, peers) = (worker.index(), worker.peers());
    let dense = job.params.dense;
    if dense && every.is_some() && w == 0 {
        tracing::info!("no checkpoints with --dense: they do not hold the dense contributions");
    }
    let every = every.filter(|_| !dense);
    let checkpoint = checkpoint::path(&job.params.out_dir, w as u32, peers as u32);
    let mine = if every.is_some() || checkpoint.exists() {
        let digest = resume::job_digest(job, key, views, gaussians, peers);
        resume::partition_resume(job, (w as u32, peers as u32), digest, every)
    } else {
        Ok((Resume::default(), 0))
    };
    let held = mine.map(|(resume, next)| {
        *slot.borrow_mut() = Some(resume);
        next
    });
    let held = agree_on_resume(worker, input, notes, held.map_err(|e| e.to_string()))?;
    let resumed = held.iter().copied().min().unwrap_or(0);
    if held.iter().any(|&h| h > 0) && w == 0 {
        tracing::info!(
            "resuming from the checkpoints: the partitions hold views {held:?}; the first \
             {resumed} views are not encoded again"
        );
    }
    Ok(held)
}

/// Ends this worker's map side at every partition: an `Abort` with the message of a failure,
/// then `Done` with the images sent and the job's fingerprint (partition 0 also gets the
/// worker's figures).
fn send_done(input: &mut Input, peers: usize, w: usize, failed: Option<String>, map: &MapOutcome) {
    for p in 0..peers as u32 {
        if let Some(m) = &failed {
            input.send(ToReducer::Abort {
                partition: p,
                message: m.clone(),
            });
        }
        input.send(ToReducer::Done {
            partition: p,
            worker: w as u32,
            images: map.shares.sent.get(p as usize).copied().unwrap_or(0),
            job: map.key.clone(),
            stats: (p == 0).then(|| map.stats.clone()),
        });
    }
}

/// The spill folder of process `process` under `out` (hidden, `.partial`: never mistaken for
/// output).
fn spill_dir(out: &Path, process: usize) -> PathBuf {
    out.join(format!(".cluster-{process}.partial"))
}

fn panic_text(info: &std::panic::PanicHookInfo<'_>) -> String {
    let payload = info.payload();
    let msg = payload
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "(no message)".into());
    match info.location() {
        Some(l) => format!("{msg} (at {}:{})", l.file(), l.line()),
        None => msg,
    }
}

/// Runs this process's part of a distributed encode and, on process 0, writes
/// `OUT/embeddings.safetensors` then `OUT/report.json` (each atomically, the report last) and
/// returns the report; other processes return `None` once the job completed.
///
/// Blocks until every process of `cluster` has connected and proved the cluster secret
/// ([`net::connect_peers`]; peers that fail are refused, logged and waited past) and the job has
/// completed. For its duration it installs a process-wide panic hook: a panic on any thread
/// (timely's network threads panic when a peer process dies) prints one line naming the cause
/// (the process whose connection failed, with its address), removes this process's spill folder
/// and exits the process with [`EXIT_PEER_LOST`] at once — a dead peer can never make a survivor
/// write anything.
///
/// Errors (returned on every process): no secret with an address off loopback
/// ([`ClusterConfig::check_secret`]); this process's address cannot be listened on (port in
/// use); not every process connected with the secret within `connect_timeout`
/// ([`Error::Network`] naming them); a worker's encode error (bad scene, model, image),
/// processes started with different arguments, an incomplete job, I/O on the outputs.
pub fn encode_cluster(job: ClusterJob, cluster: &ClusterConfig) -> Result<Option<Report>> {
    let t_total = Instant::now();
    cluster.check().map_err(Error::Invalid)?;
    cluster.check_secret()?;
    let process = cluster.process;
    let spill = fresh_spill_dir(&job.params.out_dir, process)?;

    let previous_hook = std::panic::take_hook();
    let lost = Arc::new(LostPeer::default());
    set_peer_lost_hook(process, spill, cluster.addresses.clone(), Arc::clone(&lost));
    let models_header = job.report.clone();
    let job = Arc::new(job);
    let outcome = net::connect_peers(
        &cluster.addresses,
        process,
        cluster.secret.as_ref(),
        net::HANDSHAKE_TIMEOUT,
        t_total + cluster.connect_timeout,
        &lost,
    )
    .and_then(|peers| run_job(&job, peers, process, cluster.checkpoint_every));
    // The job has ended one way or the other (joined) or never started: the hook may not act.
    std::panic::set_hook(previous_hook);

    let outcome = outcome?;
    let peers = cluster.addresses.len() as u32;
    let Some(output) = outcome.output else {
        tracing::info!(
            process,
            images = outcome.images,
            "job completed; process 0 writes the outputs"
        );
        checkpoint::remove(&job.params.out_dir, process as u32, peers);
        return Ok(None);
    };
    let report = write_outputs(
        &job,
        cluster,
        models_header,
        (outcome.models, outcome.selection),
        output,
        t_total,
    )?;
    checkpoint::remove(&job.params.out_dir, process as u32, peers);
    Ok(Some(report))
}

/// Creates the output folder `out` and removes a spill folder of process `process` left by an
/// earlier run; returns that spill folder's path.
///
/// Errors: I/O on either folder.
fn fresh_spill_dir(out: &Path, process: usize) -> Result<PathBuf> {
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    let spill = spill_dir(out, process);
    if spill.exists() {
        std::fs::remove_dir_all(&spill).map_err(|e| Error::io(&spill, e))?;
    }
    Ok(spill)
}

/// How long a process that lost a peer keeps its own connections open before it exits.
const PEER_LOST_GRACE: std::time::Duration = std::time::Duration::from_secs(1);

/// Installs the process-wide panic hook of [`encode_cluster`]: a panic on any thread prints one
/// line naming its cause (the peer process whose connection failed, from the panicking timely
/// network thread or else from `lost`, with its address in `addresses`; or an internal error),
/// removes `spill` and exits the process with [`EXIT_PEER_LOST`] ([`PEER_LOST_GRACE`] later when
/// a connection failed).
fn set_peer_lost_hook(process: usize, spill: PathBuf, addresses: Vec<String>, lost: Arc<LostPeer>) {
    std::panic::set_hook(Box::new(move |info| {
        let text = panic_text(info);
        let network =
            text.contains("timely communication error") || text.contains("MergeQueue poisoned");
        let cause = match network_thread_peer().or_else(|| lost.get()) {
            Some(peer) if network => {
                let address = addresses.get(peer).map_or("?", String::as_str);
                format!("process {peer} ({address}) died or its connection failed")
            }
            _ if network => "lost the connection to another process of the job (it died or \
                             the network failed)"
                .into(),
            _ => "internal error".into(),
        };
        eprintln!(
            "error: encode-cluster process {process}: {cause}: {text}\nerror: the job failed and \
             wrote no output; rerun every process"
        );
        let _ = std::fs::remove_dir_all(&spill);
        if network {
            // Keep this process's connections open a moment: the other survivors then see the
            // process that really died fail first, and name it rather than this one.
            std::thread::sleep(PEER_LOST_GRACE);
        }
        std::process::exit(EXIT_PEER_LOST);
    }));
}

/// The peer process of the current thread when it is one of timely's network threads
/// (`timely:send-N`, `timely:recv-N`, each serving the connection to process `N`).
fn network_thread_peer() -> Option<usize> {
    let current = std::thread::current();
    let name = current.name()?;
    name.strip_prefix("timely:recv-")
        .or_else(|| name.strip_prefix("timely:send-"))?
        .parse()
        .ok()
}

/// Runs `job` as this process's single timely worker over the connected `peers` (one stream per
/// process, `None` at `process`, as [`net::connect_peers`] returns them), its partition
/// checkpointed every `every` (`None`: never), and waits for it to end.
///
/// Errors: timely's network threads cannot start; the worker's own error or panic.
fn run_job(
    job: &Arc<ClusterJob>,
    peers: Vec<Option<PeerStream>>,
    process: usize,
    every: Option<std::time::Duration>,
) -> Result<WorkerOutcome> {
    use timely::communication::allocator::zero_copy::initialize::initialize_networking_from_sockets;
    use timely::communication::allocator::{AllocatorBuilder, ProcessBuilder};

    let hooks = timely::communication::Hooks::default();
    let local = ProcessBuilder::new_typed_vector(1, hooks.refill.clone(), hooks.spill.clone());
    let (builders, comms) = initialize_networking_from_sockets(local, peers, process, 1, hooks)
        .map_err(|e| {
            Error::internal(format!(
                "encode-cluster process {process}: cannot start the network threads: {e}"
            ))
        })?;
    let builders = builders.into_iter().map(AllocatorBuilder::Tcp).collect();
    let worker_job = Arc::clone(job);
    let guards = timely::execute::execute_from(
        builders,
        Box::new(comms),
        timely::WorkerConfig::default(),
        move |worker| run_worker(worker, &worker_job, every),
    )
    .map_err(|e| Error::internal(format!("encode-cluster process {process}: {e}")))?;
    guards
        .join()
        .into_iter()
        .next()
        .ok_or_else(|| Error::internal("timely started no worker"))?
        .map_err(|e| Error::internal(format!("worker thread failed: {e}")))?
}

/// Process 0's end of the job, in the order `encode` writes: `OUT/embeddings.safetensors` (with
/// `--dense`, else one of an earlier run removed), `OUT/mixture.safetensors` (with the mixture,
/// else likewise), then `OUT/report.json` from `report` (the models' header) completed with the
/// worker's models (rasterizer, CLIP model id, masks), the view selection, the cluster's
/// addresses and `output`'s counts and timings; returns the report. The masks' record goes to
/// the segments ([`ClusterJob::segments`]), which the caller writes.
///
/// Errors: views that observed no Gaussian or far fewer than they should
/// ([`crate::views::check_observed`]); the mixture's (inconsistent parts); I/O on the outputs.
fn write_outputs(
    job: &ClusterJob,
    cluster: &ClusterConfig,
    mut report: Report,
    (models, selection): ([String; 3], Option<crate::views::SelectionReport>),
    output: Assembled,
    t_total: Instant,
) -> Result<Report> {
    let Assembled {
        embeddings,
        mixture,
        record,
        counts,
        mut timings,
        cluster: cluster_stats,
    } = output;
    if let (Some(feed), Some(record)) = (&job.segments, record) {
        feed.send_record(record);
    }
    let t0 = Instant::now();
    // As `encode`: a report of an earlier run goes first, then a run whose views observed too
    // little fails with no dense file that could pass for this run's.
    let files = OutputFiles::begin(&job.params.out_dir)?;
    crate::views::check_observed(selection.as_ref(), counts.observed, counts.gaussians)
        .inspect_err(|_| drop(slag_common::io::remove_stale(&files.embeddings)))?;
    match embeddings {
        Some(e) => Embeddings {
            model: models[1].clone(),
            scene_gaussians: counts.gaussians as u64,
            source_ply: job.scene.ply.display().to_string(),
            ..e
        }
        .write(&files.embeddings, job.params.precision)?,
        None => slag_common::io::remove_stale(&files.embeddings)?,
    }
    let forms = write_mixture(&job.params.out_dir, mixture, &models[1])?;
    timings.write = t0.elapsed().as_secs_f64();
    timings.total = t_total.elapsed().as_secs_f64();
    let [rasterizer, clip_model_id, masks] = models;
    report.models.rasterizer = rasterizer;
    report.models.clip_model_id = clip_model_id;
    report.models.masks = masks;
    report.view_selection = selection;
    report.parameters.cluster_addresses = Some(cluster.addresses.clone());
    report.timings = timings;
    report.counts = counts;
    files.write_report(
        report,
        job.params.precision,
        Some(cluster_stats),
        Some(forms),
    )
}

/// Writes the mixture of `mixture`'s parts (of CLIP model `model_id`) to
/// `<out>/mixture.safetensors` atomically, or removes one of an earlier run when there is none;
/// returns the report's record of the forms written.
///
/// Errors: the mixture's (inconsistent parts), I/O.
fn write_mixture(
    out: &Path,
    mixture: Option<slag_common::mixture::SparseMixture>,
    model_id: &str,
) -> Result<crate::report::FormOutputs> {
    let t0 = Instant::now();
    let mixture = mixture
        .map(|mut m| {
            m.model_id = model_id.to_string();
            slag_common::mixture::MixtureEmbeddings::from_sparse(m)
        })
        .transpose()?;
    let path = out.join("mixture.safetensors");
    match &mixture {
        Some(m) => m.write(&path)?,
        None => slag_common::io::remove_stale(&path)?,
    }
    let seconds = t0.elapsed().as_secs_f64();
    Ok(crate::pipeline::finish::form_outputs(
        mixture.as_ref(),
        path,
        seconds,
        Vec::new(),
        0.0,
    ))
}

#[cfg(test)]
mod checkpoint_tests;

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use std::time::Duration;

    use slag_common::scene::Gaussians;

    use super::map::split;
    use super::records::JobKey;
    use super::*;
    use crate::aggregate::{self, Entry, ImageContribution, ReduceParams};
    use slag_common::mask_record::MaskRecord;

    #[test]
    fn hosts_file_is_parsed_and_checked() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("hosts");
        std::fs::write(&f, "# cluster\n127.0.0.1:4000\n\nnode2:4001\n").unwrap();
        let c = ClusterConfig::from_hosts_file(&f, 1, Duration::from_secs(1)).unwrap();
        assert_eq!(c.addresses, ["127.0.0.1:4000", "node2:4001"]);
        let err = ClusterConfig::from_hosts_file(&f, 2, Duration::from_secs(1)).unwrap_err();
        assert!(err.to_string().contains("process index 2"), "{err}");
        std::fs::write(&f, "127.0.0.1\n").unwrap();
        let err = ClusterConfig::from_hosts_file(&f, 0, Duration::from_secs(1)).unwrap_err();
        assert!(err.to_string().contains("host:port"), "{err}");
    }

    /// `images` pseudo-random image contributions (seeds 1, 2, …) of `masks` masks each over
    /// `n` Gaussians.
    pub(super) fn contributions(
        images: u64,
        n: usize,
        masks: u32,
        dim: usize,
    ) -> Vec<ImageContribution> {
        (1..=images)
            .map(|seed| contribution(seed, n as u32, masks, dim))
            .collect()
    }

    /// Pseudo-random contribution of one image: sorted unique (gaussian, mask) entries.
    fn contribution(seed: u64, n: u32, masks: u32, dim: usize) -> ImageContribution {
        let mut s = seed.wrapping_mul(0x9e3779b97f4a7c15) | 1;
        let mut next = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            s
        };
        let mut entries: Vec<Entry> = (0..n * 2)
            .map(|_| {
                let gaussian = (next() % n as u64) as u32;
                Entry {
                    gaussian,
                    mask: (next() % masks as u64) as u32,
                    // Every 11th Gaussian gets only tiny weights: below the threshold, unobserved.
                    weight: if gaussian.is_multiple_of(11) {
                        1e-9
                    } else {
                        (next() % 1000) as f32 / 100.0 + 0.01
                    },
                }
            })
            .collect();
        entries.sort_by_key(|e| (e.gaussian, e.mask));
        entries.dedup_by_key(|e| (e.gaussian, e.mask));
        let mask_embeddings = (0..masks as usize * dim)
            .map(|_| (next() % 2001) as f32 / 1000.0 - 1.0)
            .collect();
        ImageContribution {
            dim,
            mask_embeddings,
            entries,
        }
    }

    pub(super) fn key(n: usize, views: u64, dim: usize) -> JobKey {
        JobKey {
            gaussians: n as u64,
            views,
            dim: dim as u64,
            fingerprint: "test".into(),
        }
    }

    /// Every output form: the dense file, the mixture (3 kept pairs) and the masks' record.
    pub(super) const ALL_FORMS: Forms = Forms {
        dense: true,
        mixture_keep: Some(3),
        record_slots: Some(4),
    };

    /// The whole reduce/gather path in one process: `images` split over `peers` workers
    /// round-robin, each partition reduced to `forms`, worker 0 assembling. `tamper` edits the
    /// records (their order too: the order they reach the reducers).
    pub(super) fn distributed_forms(
        images: &[ImageContribution],
        n: usize,
        peers: usize,
        forms: Forms,
        tamper: impl Fn(&mut Vec<ToReducer>),
    ) -> Result<Assembled> {
        let dim = images[0].dim;
        let dir = tempfile::tempdir().unwrap();
        let mut records = Vec::new();
        let scene = (n as u64, images.len() as u32);
        for w in 0..peers {
            let mine: Vec<usize> = (w..images.len()).step_by(peers).collect();
            for &i in &mine {
                records.extend(
                    split(&images[i], i as u32, peers, scene, forms.dense)
                        .into_iter()
                        .map(ToReducer::Image),
                );
            }
            for p in 0..peers as u32 {
                records.push(ToReducer::Done {
                    partition: p,
                    worker: w as u32,
                    images: mine.len() as u64,
                    job: Some(key(n, images.len() as u64, dim)),
                    stats: (p == 0).then(|| MapStats {
                        worker: w as u32,
                        work: crate::report::ImageWork {
                            images: mine.len() as u64,
                            ..Default::default()
                        },
                        ..Default::default()
                    }),
                });
            }
        }
        tamper(&mut records);
        let reducers: Vec<PartitionReducer> = (0..peers as u32)
            .map(|p| {
                // Budget 0: every contribution is spilled, as on a scene larger than memory.
                let store = ContributionStore::new(0, dir.path().join(format!("p{p}")));
                let params = ReduceParams {
                    accumulator_budget_bytes: 1,
                    ..Default::default()
                };
                PartitionReducer::new(p, peers as u32, params, forms, store, Default::default())
            })
            .collect();
        reduce_and_assemble(reducers, records, n, forms, images.len())
    }

    /// `records` taken in by their partition's reducer of `reducers`, each reduced, worker 0
    /// assembling `forms` for a scene of `n` Gaussians at `(k, 0, 1)` and `views` views.
    pub(super) fn reduce_and_assemble(
        mut reducers: Vec<PartitionReducer>,
        records: Vec<ToReducer>,
        n: usize,
        forms: Forms,
        views: usize,
    ) -> Result<Assembled> {
        let peers = reducers.len();
        for r in records {
            reducers[r.partition() as usize].absorb(r);
        }
        let mut gathered = Gathered::default();
        for r in reducers {
            r.finish().into_iter().for_each(|g| gathered.absorb(g));
        }
        let gaussians = Gaussians {
            means: (0..n).map(|i| [i as f32, 0.0, 1.0]).collect(),
            ..Default::default()
        };
        assemble(gathered, peers, forms, &gaussians, views, 0.0)
    }

    /// [`distributed_forms`]'s dense embeddings.
    fn distributed(
        images: &[ImageContribution],
        n: usize,
        peers: usize,
        tamper: impl Fn(&mut Vec<ToReducer>),
    ) -> Result<Embeddings> {
        let a = distributed_forms(images, n, peers, ALL_FORMS, tamper)?;
        Ok(a.embeddings.unwrap())
    }

    /// Shuffles `records` with the seed `seed` (Fisher–Yates on an xorshift stream).
    pub(super) fn shuffle(records: &mut [ToReducer], seed: u64) {
        let mut s = seed | 1;
        for i in (1..records.len()).rev() {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            records.swap(i, (s % (i as u64 + 1)) as usize);
        }
    }

    /// The partitions' folds, assembled, are one fold over the whole scene bit for bit, and the
    /// partitions' masks' records one record: whatever the number of partitions (1 to 5, so
    /// that some partitions hold no observed Gaussian of some views) and the order in which the
    /// images' parts reach them.
    #[test]
    fn partitioned_fold_equals_one_fold_whatever_the_partitions_and_the_arrival() {
        let (n, dim) = (3000usize, 6);
        let images = contributions(9, n, 7, dim);
        let means: Vec<[f32; 3]> = (0..n).map(|i| [i as f32, 0.0, 1.0]).collect();
        let keep = ALL_FORMS.mixture_keep.unwrap();
        let mut fold = aggregate::MixtureFold::new(n, dim, keep, 1e-6).unwrap();
        let slots = ALL_FORMS.record_slots.unwrap();
        let mut record = MaskRecord::new(n, slots, images.len()).unwrap();
        for (v, c) in images.iter().enumerate() {
            record.add_view(v, crate::pipeline::sinks::dominant_masks(&c.entries));
            fold.push(v, aggregate::StoredImage::from_contribution(c.clone()))
                .unwrap();
        }
        let want = fold.finish(&means, "").unwrap();
        assert!(
            want.gaussian_ids.len() > n / 2,
            "{}",
            want.gaussian_ids.len()
        );
        let bits = |w: &[f32]| w.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        for peers in 1..=5 {
            for (seed, dense) in [(0, false), (7, true), (1234, false)] {
                let forms = Forms { dense, ..ALL_FORMS };
                let got = distributed_forms(&images, n, peers, forms, |r| {
                    if seed != 0 {
                        shuffle(r, seed);
                    }
                })
                .unwrap();
                let m = got.mixture.unwrap();
                let case = format!("{peers} partitions, arrival {seed}");
                assert_eq!(m.gaussian_ids, want.gaussian_ids, "{case}");
                assert_eq!(m.means, want.means, "{case}");
                assert_eq!(m.offsets, want.offsets, "{case}");
                assert_eq!(m.atoms, want.atoms, "{case}");
                assert_eq!(bits(&m.weights), bits(&want.weights), "{case}");
                assert_eq!(bits(&m.codebook), bits(&want.codebook), "{case}");
                assert_eq!(got.record.as_ref(), Some(&record), "{case}");
                assert_eq!(got.embeddings.is_some(), dense, "{case}");
                assert_eq!(got.counts.observed, want.gaussian_ids.len(), "{case}");
            }
        }
    }

    #[test]
    fn partitioned_reduction_equals_the_single_process_reduction() {
        let (n, dim) = (5000usize, 8);
        let images = contributions(7, n, 5, dim);
        let store = ContributionStore::in_memory(images.iter().cloned());
        let single = aggregate::reduce(&store, n, dim, ReduceParams::default()).unwrap();
        assert!(
            single.ids.len() > n / 2 && single.ids.len() < n,
            "{}",
            single.ids.len()
        );
        for peers in [1, 2, 3, 4] {
            let e = distributed(&images, n, peers, |_| {}).unwrap();
            assert_eq!(e.ids, single.ids, "{peers} partitions");
            // The same f64 sums, only the image order differs (round-robin): f32 rounding apart.
            for (a, b) in e.total_weights.iter().zip(&single.total_weights) {
                assert!((a - b).abs() <= 1e-6 * b.abs(), "{a} vs {b}");
            }
            for (a, b) in e.vectors.iter().zip(&single.vectors) {
                assert!((a - b).abs() <= 1e-6, "{a} vs {b}");
            }
            assert_eq!(e.means[0], [e.ids[0] as f32, 0.0, 1.0]);
        }
    }

    #[test]
    fn incomplete_or_inconsistent_jobs_are_refused() {
        let (n, dim) = (600usize, 4);
        let images = contributions(5, n, 3, dim);
        let err = |tamper: &dyn Fn(&mut Vec<ToReducer>)| {
            distributed(&images, n, 3, tamper).unwrap_err().to_string()
        };
        // A lost image part.
        let e = err(&|r| {
            let i = r
                .iter()
                .position(|x| matches!(x, ToReducer::Image(p) if p.partition == 1))
                .unwrap();
            r.remove(i);
        });
        assert!(e.contains("incomplete"), "{e}");
        // A worker whose end record never arrived.
        let e = err(&|r| {
            r.retain(|x| {
                !matches!(
                    x,
                    ToReducer::Done {
                        worker: 2,
                        partition: 0,
                        ..
                    }
                )
            })
        });
        assert!(e.contains("worker 2 ended without its end record"), "{e}");
        // A worker started with other arguments.
        let e = err(&|r| {
            for x in r.iter_mut() {
                if let ToReducer::Done {
                    worker: 1,
                    job: Some(j),
                    ..
                } = x
                {
                    j.fingerprint = "other".into();
                }
            }
        });
        assert!(e.contains("disagree"), "{e}");
        // A worker error broadcast to every partition.
        let e = err(&|r| {
            r.extend((0..3).map(|p| ToReducer::Abort {
                partition: p,
                message: "process 1: bad image".into(),
            }))
        });
        assert!(e.contains("aborted: process 1: bad image"), "{e}");
    }
}
