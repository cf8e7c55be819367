//! The encode as a map/reduce job over several processes (and machines), on timely dataflow's
//! multi-process TCP cluster (`slag-encoder encode-cluster`).
//!
//! ```text
//!   map    (worker w, images i ≡ w mod P):  masks → CLIP crops → weight raster → a_kj
//!          (aggregate::image_contribution), split by partition p = k mod P
//!   exchange (timely Exchange pact, key p): the image's a_kj of partition p with local ids k / P,
//!          and the image's mask table E_j
//!   reduce (worker p):  E_k = Σ a_kj E_j / Σ a_kj for k ≡ p mod P, exactly aggregate::reduce
//!          (f64, chunked accumulator, spilling contribution store, same unobserved rule)
//!   gather (worker 0):  rows of every partition + per-partition counts → embeddings.safetensors,
//!          then report.json, written by process 0 only after every process has finished
//! ```
//!
//! One timely worker per process (each process owns its ONNX Runtime sessions and its GPU
//! rasterizer; `--threads` goes to ONNX Runtime and rayon). Every process receives the same encode
//! arguments and the same host list; process `I` listens on line `I` of the list.
//!
//! # What the map emits
//!
//! An image's per-Gaussian partial sum `Σ_j a_kj·E_j` factorises through its mask table, so the map
//! side ships the sparse `a_kj` (12 bytes each) plus the image's `M × D` mask embeddings per
//! partition instead of dense f64 `[D]` partial sums (4 KiB per Gaussian at D = 512): on snowmiku
//! ~35 non-zero `a_kj` per Gaussian over 49 views, about 30× less traffic and no `N × D` f64
//! accumulator on any map worker. The reducer of partition `p` rebuilds an
//! [`ImageContribution`] over its local ids and runs [`aggregate::reduce`] unchanged, so
//! the distributed result uses the single-process reduction code and rule.
//!
//! # Memory
//!
//! A map worker holds one image at a time. A reducer holds its partition's contributions up to
//! `contribution_budget_bytes` and spills the rest to `OUT/.cluster-<process>.partial/`; its f64
//! accumulator covers `N / P` Gaussians and is chunked to `reduce.accumulator_budget_bytes`
//! ([`aggregate::reduce`]). Process 0 holds the final rows (observed × D f32), as `encode` does.
//!
//! # Completeness and failure
//!
//! Every map worker ends with a `Done` record to every partition carrying the number of images it
//! sent and a fingerprint of the job (Gaussians, views, embedding width, parameters); a reducer
//! reduces only when it holds `Done` from all `P` workers with equal fingerprints and exactly
//! one contribution per view; worker 0 assembles only when it holds the summary of all `P`
//! partitions and each partition's row count matches the rows received. Process 0 then writes
//! `embeddings.safetensors` (temporary file + rename) and `report.json` last, after timely has shut
//! down every connection cleanly, i.e. after every process completed.
//!
//! An error in any worker (bad image, model failure) is broadcast as an `Abort` record: every
//! process exits non-zero with that message and nothing is written. A process that dies
//! (`kill -9`, machine loss) closes its TCP connections; timely's network threads then panic with
//! "timely communication error"; [`encode_cluster`] turns that into an immediate exit with status
//! [`EXIT_PEER_LOST`] and a message saying which process lost a peer, after removing its own spill
//! folder. timely has no fault tolerance: a job that lost a process is rerun as a whole.
//!
//! # Fault injection (tests only)
//!
//! `SLAG_FAULT_EXIT_AFTER_IMAGES=<n>` makes a process exit with status 137 (as if SIGKILLed, no
//! destructors, no connection shutdown) right after it has sent its n-th image.

use std::cell::RefCell;
use std::path::{Path, PathBuf};
use std::rc::Rc;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use slag_common::embeddings::{Embeddings, write_atomic};
use slag_common::scene::Gaussians;
use slag_common::{Error, Result};
use timely::container::CapacityContainerBuilder;
use timely::dataflow::InputHandle;
use timely::dataflow::channels::pact::Exchange;
use timely::dataflow::operators::Operator;

use crate::aggregate::{self, ContributionStore, Entry, ImageContribution, ReduceParams};
use crate::masks::MaskGenerator;
use crate::pipeline::{CropEmbedder, EncodeParams, SceneInput, back_stage, front_stage};
use crate::raster::WeightRasterizer;
use crate::report::{Counts, Report, StageTimings};

/// Exit status of a process that lost a peer process (its TCP connection failed) or hit an
/// internal panic: the job failed, wrote no output, and is to be rerun.
pub const EXIT_PEER_LOST: i32 = 3;

/// Exit status of the fault hook (`SLAG_FAULT_EXIT_AFTER_IMAGES`): 128 + SIGKILL.
pub const FAULT_EXIT_STATUS: i32 = 137;

/// Rows per gather record (worker 0 receives each partition in chunks of this many Gaussians).
const ROWS_PER_RECORD: usize = 4096;

/// The per-image stage implementations of one worker process.
pub struct Stages {
    /// Mask source (SAM automatic masks or the graph segmenter).
    pub masks: Box<dyn MaskGenerator>,
    /// CLIP visual tower over mask crops.
    pub crops: Box<dyn CropEmbedder>,
    /// Weight rasterizer over the scene's Gaussians.
    pub rasterizer: Box<dyn WeightRasterizer>,
}

/// Builds a worker's [`Stages`] from the scene's Gaussians; called once in every process, on its
/// worker thread (ONNX sessions and the GPU device live there).
pub type StageFactory = Arc<dyn Fn(&Gaussians) -> Result<Stages> + Send + Sync>;

/// Where this process sits in the cluster.
#[derive(Debug, Clone)]
pub struct ClusterConfig {
    /// This process's index, `0..addresses.len()`; process 0 writes the outputs.
    pub process: usize,
    /// `host:port` of every process, the same list in every process; process `i` listens on
    /// `addresses[i]`, the others connect to it.
    pub addresses: Vec<String>,
    /// How long to wait for every process to connect before giving up.
    pub connect_timeout: Duration,
}

impl ClusterConfig {
    /// Reads a host file: one `host:port` per line, line `i` for process `i`; blank lines and
    /// lines starting with `#` are ignored.
    ///
    /// Errors: unreadable file, no address, a line that is not `host:port`, `process` out of range.
    pub fn from_hosts_file(path: &Path, process: usize, connect_timeout: Duration) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let addresses: Vec<String> = text
            .lines()
            .map(str::trim)
            .filter(|l| !l.is_empty() && !l.starts_with('#'))
            .map(str::to_string)
            .collect();
        if let Some(bad) = addresses.iter().find(|a| {
            a.rsplit_once(':')
                .is_none_or(|(_, p)| p.parse::<u16>().is_err())
        }) {
            return Err(Error::format(
                path,
                format!(
                    "{bad:?} is not host:port; write one host:port per line, one line per process"
                ),
            ));
        }
        let config = Self {
            process,
            addresses,
            connect_timeout,
        };
        config.check().map_err(|m| Error::format(path, m))?;
        Ok(config)
    }

    fn check(&self) -> std::result::Result<(), String> {
        if self.addresses.is_empty() {
            return Err("no process address; write one host:port per line".into());
        }
        if self.process >= self.addresses.len() {
            return Err(format!(
                "--process {} but the host list names {} processes (0..{})",
                self.process,
                self.addresses.len(),
                self.addresses.len()
            ));
        }
        Ok(())
    }
}

/// What every process runs: the same scene, parameters and stage factory.
pub struct ClusterJob {
    /// Scene folder, `.ply` and view selection (identical on every process).
    pub scene: SceneInput,
    /// Encode parameters; `out_dir` is where process 0 writes and where every process spills.
    pub params: EncodeParams,
    /// Builds the per-image stages on each worker.
    pub stages: StageFactory,
    /// The report header (inputs, models, parameters) process 0 completes and writes.
    pub report: Report,
}

/// Timings and counts of one map worker, summed over its images.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
struct MapStats {
    worker: u32,
    images: u64,
    decode_s: f64,
    masks_s: f64,
    clip_s: f64,
    raster_s: f64,
    image_aggregate_s: f64,
    wall_s: f64,
    masks: u64,
    entries: u64,
    raster_pixels: u64,
    raster_entries: u64,
    /// Views whose `a_kj` were summed on the GPU.
    #[serde(default)]
    device_sum_views: u64,
}

/// What a job must agree on across processes (a mismatch means processes got other arguments).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct JobKey {
    gaussians: u64,
    views: u64,
    dim: u64,
    fingerprint: String,
}

/// One image's share of partition `partition`: `a_kj` over local ids `k / P`.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct ImagePart {
    partition: u32,
    image: u32,
    dim: u32,
    /// `[M * dim]` the image's mask embeddings `E_j`.
    mask_embeddings: Vec<f32>,
    /// Local Gaussian ids (global id / P), ascending.
    local_ids: Vec<u32>,
    masks: Vec<u32>,
    weights: Vec<f32>,
}

/// Map → reduce records, routed by `partition`.
#[derive(Debug, Clone, Serialize, Deserialize)]
enum ToReducer {
    Image(ImagePart),
    Done {
        partition: u32,
        worker: u32,
        images: u64,
        job: Option<JobKey>,
        stats: Option<MapStats>,
    },
    Abort {
        partition: u32,
        message: String,
    },
}

impl ToReducer {
    fn partition(&self) -> u32 {
        match self {
            ToReducer::Image(p) => p.partition,
            ToReducer::Done { partition, .. } | ToReducer::Abort { partition, .. } => *partition,
        }
    }
}

/// What one partition reports when it has reduced.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct PartSummary {
    partition: u32,
    rows: u64,
    images: u64,
    entries: u64,
    chunks: u64,
    spilled: u64,
    reduce_s: f64,
    job: JobKey,
}

/// Reduce → gather records, all routed to worker 0.
#[derive(Debug, Clone, Serialize, Deserialize)]
enum ToGather {
    Rows {
        partition: u32,
        ids: Vec<u32>,
        vectors: Vec<f32>,
        total_weights: Vec<f32>,
    },
    Part(PartSummary),
    Map(MapStats),
    Abort(String),
}

/// The reduce side of one partition.
struct PartitionReducer {
    partition: u32,
    peers: u32,
    params: ReduceParams,
    store: ContributionStore,
    dim: Option<usize>,
    images: u64,
    entries: u64,
    done: Vec<Option<(u64, Option<JobKey>)>>,
    stats: Vec<MapStats>,
    abort: Option<String>,
}

impl PartitionReducer {
    fn new(partition: u32, peers: u32, params: ReduceParams, store: ContributionStore) -> Self {
        Self {
            partition,
            peers,
            params,
            store,
            dim: None,
            images: 0,
            entries: 0,
            done: vec![None; peers as usize],
            stats: Vec::new(),
            abort: None,
        }
    }

    fn fail(&mut self, message: String) {
        self.abort.get_or_insert(message);
    }

    fn absorb(&mut self, record: ToReducer) {
        match record {
            ToReducer::Image(part) => {
                if self.abort.is_some() {
                    return;
                }
                let dim = part.dim as usize;
                if *self.dim.get_or_insert(dim) != dim
                    || part.mask_embeddings.len() % dim.max(1) != 0
                    || part.local_ids.len() != part.masks.len()
                    || part.local_ids.len() != part.weights.len()
                {
                    return self.fail(format!(
                        "partition {}: malformed contribution of image {}",
                        self.partition, part.image
                    ));
                }
                self.images += 1;
                self.entries += part.local_ids.len() as u64;
                let entries = part
                    .local_ids
                    .iter()
                    .zip(&part.masks)
                    .zip(&part.weights)
                    .map(|((&gaussian, &mask), &weight)| Entry {
                        gaussian,
                        mask,
                        weight,
                    })
                    .collect();
                let c = ImageContribution {
                    dim,
                    mask_embeddings: part.mask_embeddings,
                    entries,
                };
                if let Err(e) = self.store.push(c) {
                    self.fail(format!("partition {}: {e}", self.partition));
                }
            }
            ToReducer::Done {
                worker,
                images,
                job,
                stats,
                ..
            } => {
                match self.done.get_mut(worker as usize) {
                    Some(slot) if slot.is_none() => *slot = Some((images, job)),
                    _ => self.fail(format!(
                        "partition {}: unexpected end record from worker {worker}",
                        self.partition
                    )),
                }
                self.stats.extend(stats);
            }
            ToReducer::Abort { message, .. } => self.fail(message),
        }
    }

    /// Reduces the partition; the records for worker 0 (or one `Abort`).
    fn finish(mut self) -> Vec<ToGather> {
        match self.reduce() {
            Ok(records) => records,
            Err(message) => vec![ToGather::Abort(message)],
        }
    }

    fn reduce(&mut self) -> std::result::Result<Vec<ToGather>, String> {
        if let Some(m) = self.abort.take() {
            return Err(m);
        }
        let p = self.partition;
        let mut job: Option<JobKey> = None;
        let mut sent = 0;
        for (w, d) in self.done.iter().enumerate() {
            let Some((images, key)) = d else {
                return Err(format!(
                    "partition {p}: worker {w} ended without its end record; the job is incomplete"
                ));
            };
            sent += images;
            // A worker that failed before loading the scene has no key but also sent an Abort.
            let Some(key) = key else {
                return Err(format!("partition {p}: worker {w} did not load the scene"));
            };
            match &job {
                None => job = Some(key.clone()),
                Some(j) if j != key => {
                    return Err(format!(
                        "processes disagree on the job (worker {w}: {:?}, worker 0: {:?}); start \
                         every process with the same encode arguments and inputs",
                        key.fingerprint, j.fingerprint
                    ));
                }
                Some(_) => {}
            }
        }
        let job = job.ok_or_else(|| format!("partition {p}: no worker"))?;
        if sent != job.views || self.images != job.views {
            return Err(format!(
                "partition {p}: {} contributions received, {sent} sent, {} views; the job is \
                 incomplete",
                self.images, job.views
            ));
        }
        let dim = job.dim as usize;
        if self.dim.is_some_and(|d| d != dim) {
            return Err(format!(
                "partition {p}: contributions of width {:?}, job width {dim}",
                self.dim
            ));
        }
        let (n, peers) = (job.gaussians, self.peers as u64);
        let n_local = if (p as u64) < n {
            (n - p as u64).div_ceil(peers) as usize
        } else {
            0
        };
        let t0 = Instant::now();
        let reduced = aggregate::reduce(&self.store, n_local, dim, self.params)
            .map_err(|e| format!("partition {p}: {e}"))?;
        let reduce_s = t0.elapsed().as_secs_f64();
        let mut out: Vec<ToGather> = std::mem::take(&mut self.stats)
            .into_iter()
            .map(ToGather::Map)
            .collect();
        let rows = reduced.ids.len();
        for start in (0..rows).step_by(ROWS_PER_RECORD) {
            let end = (start + ROWS_PER_RECORD).min(rows);
            out.push(ToGather::Rows {
                partition: p,
                ids: reduced.ids[start..end]
                    .iter()
                    .map(|&l| l * self.peers + p)
                    .collect(),
                vectors: reduced.vectors[start * dim..end * dim].to_vec(),
                total_weights: reduced.total_weights[start..end].to_vec(),
            });
        }
        out.push(ToGather::Part(PartSummary {
            partition: p,
            rows: rows as u64,
            images: self.images,
            entries: self.entries,
            chunks: reduced.chunks as u64,
            spilled: self.store.spilled() as u64,
            reduce_s,
            job,
        }));
        Ok(out)
    }
}

/// What worker 0 receives.
#[derive(Default)]
struct Gathered {
    rows: Vec<(Vec<u32>, Vec<f32>, Vec<f32>)>,
    rows_per_partition: Vec<u64>,
    parts: Vec<PartSummary>,
    stats: Vec<MapStats>,
    aborts: Vec<String>,
}

impl Gathered {
    fn absorb(&mut self, record: ToGather) {
        match record {
            ToGather::Rows {
                partition,
                ids,
                vectors,
                total_weights,
            } => {
                let p = partition as usize;
                if self.rows_per_partition.len() <= p {
                    self.rows_per_partition.resize(p + 1, 0);
                }
                self.rows_per_partition[p] += ids.len() as u64;
                self.rows.push((ids, vectors, total_weights));
            }
            ToGather::Part(s) => self.parts.push(s),
            ToGather::Map(s) => self.stats.push(s),
            ToGather::Abort(m) => self.aborts.push(m),
        }
    }
}

/// What a worker hands back to its process's main thread.
struct WorkerOutcome {
    /// Process 0 only: the assembled output and the run's counts.
    output: Option<(Embeddings, Counts, StageTimings, serde_json::Value)>,
    models: [String; 3],
    images: u64,
}

/// The fingerprint of the parameters every process must share.
fn job_key(
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
            "views {:?}..{:?} every {} raster_scale {} image_stage {:?} masks {} clip {} min_weight {}",
            views.first().map(|v| &v.name),
            views.last().map(|v| &v.name),
            job.scene.every,
            p.raster_scale,
            p.image_stage,
            stages.masks.name(),
            stages.crops.model_id(),
            p.reduce.min_total_weight,
        ),
    }
}

/// Splits one image's contribution into the `peers` partitions (`k mod peers`), with local ids
/// `k / peers` (ascending, as [`aggregate::reduce`] requires) and the image's mask table in each.
fn split(c: &ImageContribution, image: u32, peers: usize) -> Vec<ImagePart> {
    let mut parts: Vec<ImagePart> = (0..peers as u32)
        .map(|p| ImagePart {
            partition: p,
            image,
            dim: c.dim as u32,
            mask_embeddings: c.mask_embeddings.clone(),
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

type Input = InputHandle<u64, CapacityContainerBuilder<Vec<ToReducer>>>;

/// The map side of worker `w`: images `w, w + P, …`; sends each image's partitions and advances
/// the input's time so they leave at once. Returns the worker's stats and the job key.
#[allow(clippy::too_many_arguments)]
fn map_side(
    worker: &mut timely::worker::Worker,
    input: &mut Input,
    job: &ClusterJob,
    aborted: &RefCell<Option<String>>,
    scene: &(Gaussians, Vec<slag_common::camera::View>, usize),
    stages: &mut Stages,
    key: &JobKey,
    stats: &mut MapStats,
) -> Result<()> {
    let (w, peers) = (worker.index(), worker.peers());
    let (_, views, _) = scene;
    let dim = key.dim as usize;
    let fault_after: Option<u64> = std::env::var("SLAG_FAULT_EXIT_AFTER_IMAGES")
        .ok()
        .and_then(|v| v.trim().parse().ok());
    let raster_intrinsics = views
        .iter()
        .map(|v| crate::raster::raster_intrinsics(&v.intrinsics, job.params.raster_scale))
        .collect::<Result<Vec<_>>>()?;
    let t_map = Instant::now();
    for (round, i) in (w..views.len()).step_by(peers).enumerate() {
        if aborted.borrow().is_some() {
            break;
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
        let c = out.contribution;
        stats.decode_s += decode_s;
        stats.masks_s += masks_s;
        stats.clip_s += clip_s;
        stats.raster_s += out.raster_s;
        stats.image_aggregate_s += out.contribution_s;
        stats.masks += n_masks as u64;
        stats.entries += c.entries.len() as u64;
        stats.raster_pixels += out.pixels;
        stats.raster_entries += out.raster_entries;
        stats.device_sum_views += u64::from(out.device_sums);
        stats.images += 1;
        let parts = split(&c, i as u32, peers);
        for part in parts {
            input.send(ToReducer::Image(part));
        }
        input.advance_to(round as u64 + 1);
        worker.step();
        tracing::info!(
            worker = w,
            image = i,
            views = views.len(),
            masks = n_masks,
            "image sent"
        );
        if fault_after == Some(stats.images) {
            eprintln!(
                "SLAG_FAULT_EXIT_AFTER_IMAGES={}: process exits after image {i}",
                stats.images
            );
            std::process::exit(FAULT_EXIT_STATUS);
        }
    }
    stats.wall_s = t_map.elapsed().as_secs_f64();
    Ok(())
}

/// Runs one worker: builds the dataflow (identically on every worker), the map side, then steps
/// until the dataflow completed; worker 0 assembles the output.
fn run_worker(worker: &mut timely::worker::Worker, job: &ClusterJob) -> Result<WorkerOutcome> {
    let (w, peers) = (worker.index(), worker.peers());
    let mut input = Input::new();
    let aborted: Rc<RefCell<Option<String>>> = Rc::new(RefCell::new(None));
    let gathered = Rc::new(RefCell::new(Gathered::default()));
    let spill_dir = spill_dir(&job.params.out_dir, w);
    let reducer = PartitionReducer::new(
        w as u32,
        peers as u32,
        job.params.reduce,
        ContributionStore::new(job.params.contribution_budget_bytes, spill_dir),
    );
    worker.dataflow::<u64, _, _>(|scope| {
        let aborted = Rc::clone(&aborted);
        let gathered = Rc::clone(&gathered);
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

    // Map side. Errors are broadcast as Abort so every process fails with the same message.
    let mut load_scene_s = 0.0;
    let mut stats = MapStats {
        worker: w as u32,
        ..Default::default()
    };
    let mut models = [String::new(), String::new(), String::new()];
    let mut key = None;
    let mut scene_kept = None;
    let result = (|| -> Result<()> {
        let t_load = Instant::now();
        let scene = job.scene.load()?;
        load_scene_s = t_load.elapsed().as_secs_f64();
        if scene.1.is_empty() {
            return Err(Error::Invalid(format!(
                "{}: no views to encode (check --every)",
                job.scene.dir.display()
            )));
        }
        let mut stages = (job.stages)(&scene.0)?;
        models = [
            stages.rasterizer.name().to_string(),
            stages.crops.model_id().to_string(),
            stages.masks.name().to_string(),
        ];
        let k = job_key(job, scene.0.len(), &scene.1, stages.crops.dim(), &stages);
        key = Some(k.clone());
        let r = map_side(
            worker,
            &mut input,
            job,
            &aborted,
            &scene,
            &mut stages,
            &k,
            &mut stats,
        );
        scene_kept = Some(scene);
        r
    })();
    let failed = result.as_ref().err().map(|e| format!("process {w}: {e}"));
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
            images: stats.images,
            job: key.clone(),
            stats: (p == 0).then(|| stats.clone()),
        });
    }
    drop(input);
    while worker.has_dataflows() {
        worker.step_or_park(None);
    }
    result?;
    let gathered = std::mem::take(&mut *gathered.borrow_mut());
    if w != 0 {
        if let Some(m) = aborted.borrow_mut().take() {
            return Err(Error::Invalid(format!("the job was aborted: {m}")));
        }
        return Ok(WorkerOutcome {
            output: None,
            models,
            images: stats.images,
        });
    }
    let (gaussians, _, views_total) =
        scene_kept.ok_or_else(|| Error::Invalid("worker 0 has no scene".into()))?;
    let output = assemble(gathered, peers, &gaussians, views_total, load_scene_s)?;
    Ok(WorkerOutcome {
        output: Some(output),
        models,
        images: stats.images,
    })
}

/// Worker 0: checks that every partition and every map worker reported, then merges the rows in
/// ascending Gaussian id order.
fn assemble(
    mut g: Gathered,
    peers: usize,
    gaussians: &Gaussians,
    views_total: usize,
    load_scene_s: f64,
) -> Result<(Embeddings, Counts, StageTimings, serde_json::Value)> {
    if let Some(m) = g.aborts.first() {
        return Err(Error::Invalid(format!("the job was aborted: {m}")));
    }
    g.parts.sort_by_key(|s| s.partition);
    g.stats.sort_by_key(|s| s.worker);
    let parts_ok = g.parts.len() == peers
        && g.parts
            .iter()
            .enumerate()
            .all(|(i, s)| s.partition as usize == i);
    let stats_ok = g.stats.len() == peers
        && g.stats
            .iter()
            .enumerate()
            .all(|(i, s)| s.worker as usize == i);
    if !parts_ok || !stats_ok {
        return Err(Error::Invalid(format!(
            "incomplete job: {} of {peers} partition summaries and {} of {peers} worker reports \
             reached process 0",
            g.parts.len(),
            g.stats.len()
        )));
    }
    g.rows_per_partition.resize(peers, 0);
    for s in &g.parts {
        if g.rows_per_partition[s.partition as usize] != s.rows {
            return Err(Error::Invalid(format!(
                "incomplete job: partition {} reduced {} Gaussians but {} reached process 0",
                s.partition, s.rows, g.rows_per_partition[s.partition as usize]
            )));
        }
    }
    let job = g.parts[0].job.clone();
    let dim = job.dim as usize;
    if job.gaussians != gaussians.len() as u64 {
        return Err(Error::Invalid(format!(
            "process 0 loaded {} Gaussians, the job has {}",
            gaussians.len(),
            job.gaussians
        )));
    }
    let images: u64 = g.stats.iter().map(|s| s.images).sum();
    if images != job.views {
        return Err(Error::Invalid(format!(
            "incomplete job: {images} of {} views encoded",
            job.views
        )));
    }
    // Merge: (id, record, row) sorted by id.
    let mut order: Vec<(u32, u32, u32)> = g
        .rows
        .iter()
        .enumerate()
        .flat_map(|(r, (ids, _, _))| {
            ids.iter()
                .enumerate()
                .map(move |(i, &id)| (id, r as u32, i as u32))
        })
        .collect();
    order.sort_unstable();
    if order.windows(2).any(|w| w[0].0 == w[1].0)
        || order
            .last()
            .is_some_and(|l| l.0 as usize >= gaussians.len())
    {
        return Err(Error::Invalid(
            "partitions returned duplicate or out-of-range Gaussian ids".into(),
        ));
    }
    let n = order.len();
    let mut e = Embeddings {
        ids: Vec::with_capacity(n),
        means: Vec::with_capacity(n),
        dim,
        vectors: Vec::with_capacity(n * dim),
        total_weights: Vec::with_capacity(n),
        ..Default::default()
    };
    for &(id, r, i) in &order {
        let (_, vectors, weights) = &g.rows[r as usize];
        let i = i as usize;
        e.ids.push(id);
        e.means.push(gaussians.means[id as usize]);
        e.vectors
            .extend_from_slice(&vectors[i * dim..(i + 1) * dim]);
        e.total_weights.push(weights[i]);
    }
    let sum = |f: fn(&MapStats) -> f64| g.stats.iter().map(f).sum::<f64>();
    let timings = StageTimings {
        load_scene: load_scene_s,
        decode: sum(|s| s.decode_s),
        masks: sum(|s| s.masks_s),
        clip: sum(|s| s.clip_s),
        raster: sum(|s| s.raster_s),
        image_aggregate: sum(|s| s.image_aggregate_s),
        reduce: g.parts.iter().map(|s| s.reduce_s).fold(0.0, f64::max),
        ..Default::default()
    };
    let pixels: u64 = g.stats.iter().map(|s| s.raster_pixels).sum();
    let counts = Counts {
        views_total,
        views_used: job.views as usize,
        gaussians: gaussians.len(),
        observed: n,
        observed_fraction: n as f64 / gaussians.len().max(1) as f64,
        masks: g.stats.iter().map(|s| s.masks).sum::<u64>() as usize,
        entries: g.stats.iter().map(|s| s.entries).sum::<u64>() as usize,
        contributors_per_pixel: g.stats.iter().map(|s| s.raster_entries).sum::<u64>() as f64
            / pixels.max(1) as f64,
        spilled_images: g.parts.iter().map(|s| s.spilled).sum::<u64>() as usize,
        reduce_chunks: g.parts.iter().map(|s| s.chunks).sum::<u64>() as usize,
        device_sum_views: g.stats.iter().map(|s| s.device_sum_views).sum::<u64>() as usize,
        // Process 0's own peak (it assembles the output); the others report none.
        peak_rss_bytes: crate::report::peak_rss_bytes(),
    };
    let cluster = serde_json::json!({
        "processes": peers,
        "workers": g.stats.iter().map(|s| serde_json::json!({
            "worker": s.worker, "images": s.images, "map_wall_s": s.wall_s,
            "masks": s.masks, "entries": s.entries,
        })).collect::<Vec<_>>(),
        "partitions": g.parts.iter().map(|s| serde_json::json!({
            "partition": s.partition, "observed": s.rows, "images": s.images,
            "entries": s.entries, "reduce_s": s.reduce_s, "reduce_chunks": s.chunks,
            "spilled_images": s.spilled,
        })).collect::<Vec<_>>(),
        "reduce_timing": "slowest partition (partitions reduce in parallel)",
    });
    Ok((e, counts, timings, cluster))
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
/// Blocks until every process of `cluster` has connected (at most `connect_timeout`, then the
/// process exits with [`EXIT_PEER_LOST`]) and the job has completed. For its duration it installs a
/// process-wide panic hook: a panic on any thread (timely's network threads panic when a peer
/// process dies) prints one line naming the cause, removes this process's spill folder and exits
/// the process with [`EXIT_PEER_LOST`] at once — a dead peer can never make a survivor write
/// anything.
///
/// Errors (returned on every process): a worker's encode error (bad scene, model, image), processes
/// started with different arguments, an incomplete job, I/O on the outputs; the address of this
/// process cannot be bound (port in use).
pub fn encode_cluster(job: ClusterJob, cluster: &ClusterConfig) -> Result<Option<Report>> {
    let t_total = Instant::now();
    cluster.check().map_err(Error::Invalid)?;
    let process = cluster.process;
    let out = job.params.out_dir.clone();
    std::fs::create_dir_all(&out).map_err(|e| Error::io(&out, e))?;
    let spill = spill_dir(&out, process);
    if spill.exists() {
        std::fs::remove_dir_all(&spill).map_err(|e| Error::io(&spill, e))?;
    }

    let previous_hook = std::panic::take_hook();
    let hook_spill = spill.clone();
    std::panic::set_hook(Box::new(move |info| {
        let text = panic_text(info);
        let cause = if text.contains("timely communication error")
            || text.contains("MergeQueue poisoned")
        {
            "lost the connection to another process of the job (it died or the network failed)"
        } else {
            "internal error"
        };
        eprintln!(
            "error: encode-cluster process {process}: {cause}: {text}\nerror: the job failed and \
             wrote no output; rerun every process"
        );
        let _ = std::fs::remove_dir_all(&hook_spill);
        std::process::exit(EXIT_PEER_LOST);
    }));

    let connected = Arc::new(AtomicBool::new(false));
    {
        let (connected, timeout, n) = (
            Arc::clone(&connected),
            cluster.connect_timeout,
            cluster.addresses.len(),
        );
        std::thread::spawn(move || {
            std::thread::sleep(timeout);
            if !connected.load(Ordering::SeqCst) {
                eprintln!(
                    "error: encode-cluster process {process}: not all {n} processes connected \
                     within {} s; start every process with the same --hosts file (and check the \
                     addresses and firewalls)",
                    timeout.as_secs()
                );
                std::process::exit(EXIT_PEER_LOST);
            }
        });
    }

    let config = timely::Config {
        communication: timely::CommunicationConfig::Cluster {
            threads: 1,
            process,
            addresses: cluster.addresses.clone(),
            report: false,
            zerocopy: false,
        },
        worker: timely::WorkerConfig::default(),
    };
    let models_header = job.report.clone();
    let job = Arc::new(job);
    let worker_job = Arc::clone(&job);
    let worker_connected = Arc::clone(&connected);
    let started = timely::execute(config, move |worker| {
        worker_connected.store(true, Ordering::SeqCst);
        run_worker(worker, &worker_job)
    });
    // Past this point neither the watchdog nor the hook may act: the job has ended one way or the
    // other (joined) or never started.
    let results = started.map(|guards| guards.join());
    connected.store(true, Ordering::SeqCst);
    std::panic::set_hook(previous_hook);
    let results = results.map_err(|e| {
        Error::Invalid(format!(
            "encode-cluster process {process}: cannot start the cluster on {}: {e}",
            cluster.addresses[process]
        ))
    })?;

    let outcome = results
        .into_iter()
        .next()
        .ok_or_else(|| Error::Invalid("timely started no worker".into()))?
        .map_err(|e| Error::Invalid(format!("worker thread failed: {e}")))??;
    let Some((embeddings, counts, mut timings, cluster_stats)) = outcome.output else {
        tracing::info!(
            process,
            images = outcome.images,
            "job completed; process 0 writes the outputs"
        );
        return Ok(None);
    };
    let t0 = Instant::now();
    let embeddings = Embeddings {
        model: outcome.models[1].clone(),
        scene_gaussians: counts.gaussians as u64,
        source_ply: job.scene.ply.display().to_string(),
        ..embeddings
    };
    let emb_path = out.join("embeddings.safetensors");
    let report_path = out.join("report.json");
    // A stale report must not vouch for embeddings being replaced.
    if report_path.exists() {
        std::fs::remove_file(&report_path).map_err(|e| Error::io(&report_path, e))?;
    }
    embeddings.write(&emb_path, job.params.precision)?;
    timings.write = t0.elapsed().as_secs_f64();
    timings.total = t_total.elapsed().as_secs_f64();
    let mut report = models_header;
    if let Some(models) = report.models.as_object_mut() {
        models.insert("rasterizer".into(), outcome.models[0].clone().into());
        models.insert("clip_model_id".into(), outcome.models[1].clone().into());
        models.insert("masks".into(), outcome.models[2].clone().into());
    }
    if let Some(params) = report.parameters.as_object_mut() {
        params.insert("cluster_addresses".into(), cluster.addresses.clone().into());
    }
    let emb_bytes = std::fs::metadata(&emb_path).map(|m| m.len()).unwrap_or(0);
    report.timings = timings;
    report.counts = counts;
    report.outputs = serde_json::json!({
        "embeddings": emb_path, "embeddings_bytes": emb_bytes,
        "precision": job.params.precision, "report": report_path,
        "cluster": cluster_stats,
    });
    let json =
        serde_json::to_vec_pretty(&report).map_err(|e| Error::Invalid(format!("report: {e}")))?;
    write_atomic(&report_path, &json)?;
    Ok(Some(report))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn hosts_file_is_parsed_and_checked() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("hosts");
        std::fs::write(&f, "# cluster\n127.0.0.1:4000\n\nnode2:4001\n").unwrap();
        let c = ClusterConfig::from_hosts_file(&f, 1, Duration::from_secs(1)).unwrap();
        assert_eq!(c.addresses, ["127.0.0.1:4000", "node2:4001"]);
        let err = ClusterConfig::from_hosts_file(&f, 2, Duration::from_secs(1)).unwrap_err();
        assert!(err.to_string().contains("--process 2"), "{err}");
        std::fs::write(&f, "127.0.0.1\n").unwrap();
        let err = ClusterConfig::from_hosts_file(&f, 0, Duration::from_secs(1)).unwrap_err();
        assert!(err.to_string().contains("host:port"), "{err}");
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

    fn key(n: usize, views: u64, dim: usize) -> JobKey {
        JobKey {
            gaussians: n as u64,
            views,
            dim: dim as u64,
            fingerprint: "test".into(),
        }
    }

    /// The whole reduce/gather path in one process: `images` split over `peers` workers
    /// round-robin, each partition reduced, worker 0 assembling. `tamper` edits the records.
    fn distributed(
        images: &[ImageContribution],
        n: usize,
        peers: usize,
        tamper: impl Fn(&mut Vec<ToReducer>),
    ) -> Result<Embeddings> {
        let dim = images[0].dim;
        let dir = tempfile::tempdir().unwrap();
        let mut records = Vec::new();
        for w in 0..peers {
            let mine: Vec<usize> = (w..images.len()).step_by(peers).collect();
            for &i in &mine {
                records.extend(
                    split(&images[i], i as u32, peers)
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
                        images: mine.len() as u64,
                        ..Default::default()
                    }),
                });
            }
        }
        tamper(&mut records);
        let mut reducers: Vec<PartitionReducer> = (0..peers as u32)
            .map(|p| {
                // Budget 0: every contribution is spilled, as on a scene larger than memory.
                let store = ContributionStore::new(0, dir.path().join(format!("p{p}")));
                let params = ReduceParams {
                    accumulator_budget_bytes: 1,
                    ..Default::default()
                };
                PartitionReducer::new(p, peers as u32, params, store)
            })
            .collect();
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
        assemble(gathered, peers, &gaussians, images.len(), 0.0).map(|r| r.0)
    }

    #[test]
    fn partitioned_reduction_equals_the_single_process_reduction() {
        let (n, dim) = (5000usize, 8);
        let images: Vec<ImageContribution> = (0..7)
            .map(|i| contribution(i + 1, n as u32, 5, dim))
            .collect();
        let mut store = ContributionStore::new(usize::MAX, std::env::temp_dir().join("unused"));
        for c in &images {
            store.push(c.clone()).unwrap();
        }
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
        let images: Vec<ImageContribution> = (0..5)
            .map(|i| contribution(i + 1, n as u32, 3, dim))
            .collect();
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
