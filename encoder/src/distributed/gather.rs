//! The gather side: worker 0 collects every partition's rows and summaries ([`ToGather`]) and
//! assembles the outputs (the mixture, the masks' record, the dense embeddings) and the
//! report's figures.

use slag_common::embeddings::Embeddings;
use slag_common::mask_record::MaskRecord;
use slag_common::mixture::SparseMixture;
use slag_common::scene::Gaussians;
use slag_common::{Error, Result};

use super::records::{MapStats, MixtureRows, PartSummary, RecordRows, ToGather};
use super::reduce::Forms;
use crate::report::{ClusterOutputs, ClusterPartition, ClusterWorker, Counts, StageTimings};

/// What worker 0 receives.
#[derive(Default)]
pub(super) struct Gathered {
    pub(super) rows: Vec<(Vec<u32>, Vec<f32>, Vec<f32>)>,
    pub(super) rows_per_partition: Vec<u64>,
    pub(super) parts: Vec<PartSummary>,
    pub(super) mixture: Vec<MixtureRows>,
    pub(super) codebook: Option<Vec<f32>>,
    pub(super) record: Vec<RecordRows>,
    pub(super) stats: Vec<MapStats>,
    pub(super) aborts: Vec<String>,
}

impl Gathered {
    pub(super) fn absorb(&mut self, record: ToGather) {
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
            ToGather::Mixture(m) => self.mixture.push(m),
            ToGather::Codebook(c) => {
                if self.codebook.replace(c).is_some() {
                    self.aborts
                        .push("the mixture's codebook reached process 0 twice".into());
                }
            }
            ToGather::Record(r) => self.record.push(r),
            ToGather::Map(s) => self.stats.push(s),
            ToGather::Abort(m) => self.aborts.push(m),
        }
    }
}

/// `(id, block, row)` of every row of the `blocks` (each a block's Gaussian ids), sorted by id.
///
/// Errors ([`Error::Internal`]): an id twice or at or past `n`, the scene's Gaussians.
fn id_order<'a>(blocks: impl Iterator<Item = &'a [u32]>, n: usize) -> Result<Vec<(u32, u32, u32)>> {
    let mut order: Vec<(u32, u32, u32)> = blocks
        .enumerate()
        .flat_map(|(b, ids)| {
            ids.iter()
                .enumerate()
                .map(move |(i, &id)| (id, b as u32, i as u32))
        })
        .collect();
    order.sort_unstable();
    if order.windows(2).any(|w| w[0].0 == w[1].0) || order.last().is_some_and(|l| l.0 as usize >= n)
    {
        return Err(Error::internal(
            "partitions returned duplicate or out-of-range Gaussian ids",
        ));
    }
    Ok(order)
}

/// Whether the sorted `numbers` are exactly `0..peers`, each once (every partition or worker
/// reported).
fn numbers_each_once(numbers: impl ExactSizeIterator<Item = u32>, peers: usize) -> bool {
    numbers.len() == peers && numbers.enumerate().all(|(i, n)| n as usize == i)
}

/// What worker 0 assembles from every partition's rows ([`assemble`]).
pub(super) struct Assembled {
    /// The dense `E_k` (with [`Forms::dense`]).
    pub(super) embeddings: Option<Embeddings>,
    /// The mixture's parts, its model id left empty (with [`Forms::mixture_keep`]).
    pub(super) mixture: Option<SparseMixture>,
    /// The masks' record of every Gaussian (with [`Forms::record_slots`]).
    pub(super) record: Option<MaskRecord>,
    pub(super) counts: Counts,
    pub(super) timings: StageTimings,
    pub(super) cluster: ClusterOutputs,
}

/// What a worker hands back to its process's main thread.
pub(super) struct WorkerOutcome {
    /// Process 0 only: the assembled output and the run's counts.
    pub(super) output: Option<Assembled>,
    /// Process 0 only: what the report records of the view selection.
    pub(super) selection: Option<crate::views::SelectionReport>,
    pub(super) models: [String; 3],
    pub(super) images: u64,
}

impl Gathered {
    /// Checks that nothing aborted and that every partition and every map worker of `peers`
    /// reported, with all of its rows; sorts the summaries by partition and worker.
    ///
    /// Errors: the first abort ([`Error::Invalid`]); a missing summary, report or row
    /// ([`Error::Internal`]).
    fn check_complete(&mut self, peers: usize) -> Result<()> {
        if let Some(m) = self.aborts.first() {
            return Err(Error::Invalid(format!("the job was aborted: {m}")));
        }
        self.parts.sort_by_key(|s| s.partition);
        self.stats.sort_by_key(|s| s.worker);
        let parts_ok = numbers_each_once(self.parts.iter().map(|s| s.partition), peers);
        let stats_ok = numbers_each_once(self.stats.iter().map(|s| s.worker), peers);
        if !parts_ok || !stats_ok {
            return Err(Error::internal(format!(
                "incomplete job: {} of {peers} partition summaries and {} of {peers} worker \
                 reports reached process 0",
                self.parts.len(),
                self.stats.len()
            )));
        }
        self.rows_per_partition.resize(peers, 0);
        let mut mixture_rows = vec![0u64; peers];
        self.mixture
            .iter()
            .for_each(|m| mixture_rows[m.partition as usize % peers] += m.ids.len() as u64);
        let mut record_rows = vec![0u64; peers];
        self.record
            .iter()
            .for_each(|r| record_rows[r.partition as usize % peers] += r.ids.len() as u64);
        for s in &self.parts {
            let p = s.partition as usize;
            let received = [self.rows_per_partition[p], mixture_rows[p], record_rows[p]];
            if received != [s.rows, s.mixture_rows, s.record_rows] {
                return Err(Error::internal(format!(
                    "incomplete job: partition {} sent {:?} rows (dense, mixture, masks' record) \
                     but {received:?} reached process 0",
                    s.partition,
                    [s.rows, s.mixture_rows, s.record_rows]
                )));
            }
        }
        Ok(())
    }

    /// The mixture's parts from the partitions' rows, in ascending Gaussian id order, each with
    /// its mean from `gaussians`, and partition 0's codebook; the model id left empty.
    ///
    /// Errors ([`Error::Internal`]): no codebook, a Gaussian id twice or beyond the scene.
    fn merge_mixture(&mut self, gaussians: &Gaussians, dim: usize) -> Result<SparseMixture> {
        let codebook = self
            .codebook
            .take()
            .ok_or_else(|| Error::internal("the mixture's codebook did not reach process 0"))?;
        let order = id_order(
            self.mixture.iter().map(|m| m.ids.as_slice()),
            gaussians.len(),
        )?;
        // Where each block's row starts among its pairs.
        let starts: Vec<Vec<usize>> = self
            .mixture
            .iter()
            .map(|m| {
                let mut at = 0;
                m.lengths
                    .iter()
                    .map(|&l| {
                        let start = at;
                        at += l as usize;
                        start
                    })
                    .collect()
            })
            .collect();
        let mut parts = SparseMixture {
            dim,
            codebook,
            offsets: vec![0],
            ..Default::default()
        };
        for &(id, b, i) in &order {
            let (m, i) = (&self.mixture[b as usize], i as usize);
            let pairs = starts[b as usize][i]..starts[b as usize][i] + m.lengths[i] as usize;
            parts.gaussian_ids.push(id);
            parts.means.push(gaussians.means[id as usize]);
            parts.atoms.extend_from_slice(&m.atoms[pairs.clone()]);
            parts.weights.extend_from_slice(&m.weights[pairs]);
            parts.offsets.push(parts.atoms.len());
        }
        Ok(parts)
    }

    /// The masks' record of the scene's `n` Gaussians with `slots` slots for `views` views,
    /// every row from its partition.
    ///
    /// Errors ([`Error::Internal`]): a Gaussian's row missing, twice or beyond the scene, rows
    /// of another slot count; the record's ([`MaskRecord::new`]).
    fn merge_record(&self, n: usize, slots: usize, views: usize) -> Result<MaskRecord> {
        let order = id_order(self.record.iter().map(|r| r.ids.as_slice()), n)?;
        if order.len() != n {
            return Err(Error::internal(format!(
                "incomplete job: the masks' record of {} of {n} Gaussians reached process 0",
                order.len()
            )));
        }
        let mut record = MaskRecord::new(n, slots, views)?;
        for r in &self.record {
            if r.views.len() != r.ids.len() * slots
                || r.masks.len() != r.views.len()
                || r.weights.len() != r.views.len()
            {
                return Err(Error::internal("masks' record rows of another slot count"));
            }
            for (j, &id) in r.ids.iter().enumerate() {
                let (to, from) = (id as usize * slots, j * slots);
                record.views[to..to + slots].copy_from_slice(&r.views[from..from + slots]);
                record.masks[to..to + slots].copy_from_slice(&r.masks[from..from + slots]);
                record.weights[to..to + slots].copy_from_slice(&r.weights[from..from + slots]);
            }
        }
        Ok(record)
    }

    /// Merges the rows in ascending Gaussian id order, each with its mean from `gaussians`.
    ///
    /// Errors ([`Error::Internal`]): a Gaussian id twice or beyond the scene.
    fn merge_rows(&self, gaussians: &Gaussians, dim: usize) -> Result<Embeddings> {
        let order = id_order(
            self.rows.iter().map(|(ids, _, _)| ids.as_slice()),
            gaussians.len(),
        )?;
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
            let (_, vectors, weights) = &self.rows[r as usize];
            let i = i as usize;
            e.ids.push(id);
            e.means.push(gaussians.means[id as usize]);
            e.vectors
                .extend_from_slice(&vectors[i * dim..(i + 1) * dim]);
            e.total_weights.push(weights[i]);
        }
        Ok(e)
    }

    /// The report's per-partition and per-worker figures of a cluster of `peers` processes.
    fn cluster_outputs(&self, peers: usize) -> ClusterOutputs {
        ClusterOutputs {
            partitions: self
                .parts
                .iter()
                .map(|s| ClusterPartition {
                    entries: s.entries,
                    images: s.images,
                    // The dense rows, or the mixture's without the dense file (with both, the
                    // same Gaussians up to the mixture's observed rule).
                    observed: s.rows.max(s.mixture_rows),
                    partition: s.partition,
                    reduce_chunks: s.chunks,
                    reduce_s: s.reduce_s,
                    spilled_images: s.spilled,
                    views_restored: s.restored,
                    checkpoints: s.checkpoints.0,
                    checkpoint_s: s.checkpoints.1,
                    checkpoint_bytes: s.checkpoints.2,
                })
                .collect(),
            processes: peers,
            views_resumed: self.stats.iter().map(|s| s.resumed).sum(),
            reduce_timing: "slowest partition (partitions reduce in parallel)".into(),
            workers: self
                .stats
                .iter()
                .map(|s| ClusterWorker {
                    entries: s.work.entries,
                    images: s.work.images,
                    map_wall_s: s.wall_s,
                    masks: s.work.masks,
                    views: s.views.clone(),
                    worker: s.worker,
                })
                .collect(),
        }
    }
}

/// Worker 0: checks that every partition and every map worker reported, then merges the rows
/// of each of `forms` in ascending Gaussian id order over the scene's `gaussians`.
///
/// Errors: the job aborted or is incomplete ([`Gathered::check_complete`]), process 0 loaded
/// another scene than the job's, rows that do not merge.
pub(super) fn assemble(
    mut g: Gathered,
    peers: usize,
    forms: Forms,
    gaussians: &Gaussians,
    views_total: usize,
    load_scene_s: f64,
) -> Result<Assembled> {
    g.check_complete(peers)?;
    let job = g.parts[0].job.clone();
    let dim = job.dim as usize;
    if job.gaussians != gaussians.len() as u64 {
        return Err(Error::mismatch(
            slag_common::Mismatched::Scene,
            format!(
                "process 0 loaded {} Gaussians, the job has {}: give every process the same scene",
                gaussians.len(),
                job.gaussians
            ),
        ));
    }
    let images: u64 = g.stats.iter().map(|s| s.work.images).sum();
    let resumed: u64 = g.stats.iter().map(|s| s.resumed).sum();
    if images + resumed != job.views {
        return Err(Error::internal(format!(
            "incomplete job: {images} of {} views encoded, {resumed} resumed from checkpoints",
            job.views
        )));
    }
    let embeddings = forms
        .dense
        .then(|| g.merge_rows(gaussians, dim))
        .transpose()?;
    let mixture = forms
        .mixture_keep
        .map(|_| g.merge_mixture(gaussians, dim))
        .transpose()?;
    let record = forms
        .record_slots
        .map(|slots| g.merge_record(gaussians.len(), slots, job.views as usize))
        .transpose()?;
    let observed = match (&embeddings, &mixture) {
        (Some(e), _) => e.ids.len(),
        (None, Some(m)) => m.gaussian_ids.len(),
        (None, None) => 0,
    };
    let (counts, timings) = figures(
        &g,
        gaussians.len(),
        job.views,
        observed,
        (views_total, load_scene_s),
    );
    Ok(Assembled {
        embeddings,
        mixture,
        record,
        counts,
        timings,
        cluster: g.cluster_outputs(peers),
    })
}

/// The report's counts and timings of the job: the map workers' work summed, the slowest
/// partition's reduction, `observed` of the scene's `n` Gaussians over `views` views (of
/// `views_total` training views; the scene loaded in `load_scene_s`).
fn figures(
    g: &Gathered,
    n: usize,
    views: u64,
    observed: usize,
    (views_total, load_scene_s): (usize, f64),
) -> (Counts, StageTimings) {
    let mut work = crate::report::ImageWork::default();
    g.stats.iter().for_each(|s| work.add(&s.work));
    let mut timings = StageTimings {
        load_scene: load_scene_s,
        reduce: g.parts.iter().map(|s| s.reduce_s).fold(0.0, f64::max),
        ..Default::default()
    };
    let mut counts = Counts {
        views_total,
        views_used: views as usize,
        gaussians: n,
        observed,
        observed_fraction: observed as f64 / n.max(1) as f64,
        spilled_images: g.parts.iter().map(|s| s.spilled).sum::<u64>() as usize,
        reduce_chunks: g.parts.iter().map(|s| s.chunks).sum::<u64>() as usize,
        // Process 0's own peak (it assembles the output); the others report none.
        peak_rss_bytes: slag_common::util::peak_rss_bytes(),
        ..Default::default()
    };
    work.fill(&mut timings, &mut counts);
    if g.parts.iter().any(|s| s.restored > 0) {
        // A resumed job mapped only some views: the partitions count every view's masks and
        // entries (those of their checkpoints too).
        counts.masks = g.parts.first().map_or(0, |s| s.masks) as usize;
        counts.entries = g.parts.iter().map(|s| s.entries).sum::<u64>() as usize;
    }
    (counts, timings)
}
