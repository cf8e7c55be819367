//! The gather side: worker 0 collects every partition's rows and summaries ([`ToGather`]) and
//! assembles `embeddings.safetensors` and the report.

use slag_common::embeddings::Embeddings;
use slag_common::scene::Gaussians;
use slag_common::{Error, Result};

use super::records::{MapStats, PartSummary, ToGather};
use crate::report::{ClusterOutputs, ClusterPartition, ClusterWorker, Counts, StageTimings};

/// What worker 0 receives.
#[derive(Default)]
pub(super) struct Gathered {
    pub(super) rows: Vec<(Vec<u32>, Vec<f32>, Vec<f32>)>,
    pub(super) rows_per_partition: Vec<u64>,
    pub(super) parts: Vec<PartSummary>,
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
            ToGather::Map(s) => self.stats.push(s),
            ToGather::Abort(m) => self.aborts.push(m),
        }
    }
}

/// Whether the sorted `numbers` are exactly `0..peers`, each once (every partition or worker
/// reported).
fn numbers_each_once(numbers: impl ExactSizeIterator<Item = u32>, peers: usize) -> bool {
    numbers.len() == peers && numbers.enumerate().all(|(i, n)| n as usize == i)
}

/// What a worker hands back to its process's main thread.
pub(super) struct WorkerOutcome {
    /// Process 0 only: the assembled output and the run's counts.
    pub(super) output: Option<(Embeddings, Counts, StageTimings, ClusterOutputs)>,
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
        for s in &self.parts {
            if self.rows_per_partition[s.partition as usize] != s.rows {
                return Err(Error::internal(format!(
                    "incomplete job: partition {} reduced {} Gaussians but {} reached process 0",
                    s.partition, s.rows, self.rows_per_partition[s.partition as usize]
                )));
            }
        }
        Ok(())
    }

    /// Merges the rows in ascending Gaussian id order, each with its mean from `gaussians`.
    ///
    /// Errors ([`Error::Internal`]): a Gaussian id twice or beyond the scene.
    fn merge_rows(&self, gaussians: &Gaussians, dim: usize) -> Result<Embeddings> {
        // (id, record, row) sorted by id.
        let mut order: Vec<(u32, u32, u32)> = self
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
            return Err(Error::internal(
                "partitions returned duplicate or out-of-range Gaussian ids",
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
                    observed: s.rows,
                    partition: s.partition,
                    reduce_chunks: s.chunks,
                    reduce_s: s.reduce_s,
                    spilled_images: s.spilled,
                })
                .collect(),
            processes: peers,
            reduce_timing: "slowest partition (partitions reduce in parallel)".into(),
            workers: self
                .stats
                .iter()
                .map(|s| ClusterWorker {
                    entries: s.work.entries,
                    images: s.work.images,
                    map_wall_s: s.wall_s,
                    masks: s.work.masks,
                    worker: s.worker,
                })
                .collect(),
        }
    }
}

/// Worker 0: checks that every partition and every map worker reported, then merges the rows in
/// ascending Gaussian id order.
pub(super) fn assemble(
    mut g: Gathered,
    peers: usize,
    gaussians: &Gaussians,
    views_total: usize,
    load_scene_s: f64,
) -> Result<(Embeddings, Counts, StageTimings, ClusterOutputs)> {
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
    if images != job.views {
        return Err(Error::internal(format!(
            "incomplete job: {images} of {} views encoded",
            job.views
        )));
    }
    let e = g.merge_rows(gaussians, dim)?;
    let n = e.ids.len();
    let mut work = crate::report::ImageWork::default();
    g.stats.iter().for_each(|s| work.add(&s.work));
    let mut timings = StageTimings {
        load_scene: load_scene_s,
        reduce: g.parts.iter().map(|s| s.reduce_s).fold(0.0, f64::max),
        ..Default::default()
    };
    let mut counts = Counts {
        views_total,
        views_used: job.views as usize,
        gaussians: gaussians.len(),
        observed: n,
        observed_fraction: n as f64 / gaussians.len().max(1) as f64,
        spilled_images: g.parts.iter().map(|s| s.spilled).sum::<u64>() as usize,
        reduce_chunks: g.parts.iter().map(|s| s.chunks).sum::<u64>() as usize,
        // Process 0's own peak (it assembles the output); the others report none.
        peak_rss_bytes: slag_common::util::peak_rss_bytes(),
        ..Default::default()
    };
    work.fill(&mut timings, &mut counts);
    let cluster = g.cluster_outputs(peers);
    Ok((e, counts, timings, cluster))
}
