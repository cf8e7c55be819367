//! The reduce side: [`PartitionReducer`] collects its partition's `a_kj` from every worker,
//! checks completeness, and runs `aggregate::reduce` over its local ids.

use std::time::Instant;

use super::records::{JobKey, MapStats, PartSummary, ToGather, ToReducer};
use crate::aggregate::{self, ContributionStore, Entry, ImageContribution, ReduceParams};

/// Rows per gather record (worker 0 receives each partition in chunks of this many Gaussians).
pub(super) const ROWS_PER_RECORD: usize = 4096;

/// The reduce side of one partition.
pub(super) struct PartitionReducer {
    pub(super) partition: u32,
    pub(super) peers: u32,
    pub(super) params: ReduceParams,
    pub(super) store: ContributionStore,
    pub(super) dim: Option<usize>,
    pub(super) images: u64,
    pub(super) entries: u64,
    pub(super) done: Vec<Option<(u64, Option<JobKey>)>>,
    pub(super) stats: Vec<MapStats>,
    pub(super) abort: Option<String>,
}

impl PartitionReducer {
    pub(super) fn new(
        partition: u32,
        peers: u32,
        params: ReduceParams,
        store: ContributionStore,
    ) -> Self {
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

    pub(super) fn fail(&mut self, message: String) {
        self.abort.get_or_insert(message);
    }

    pub(super) fn absorb(&mut self, record: ToReducer) {
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
                let stored = aggregate::StoredImage::from_contribution(c);
                if let Err(e) = self.store.push_stored_as(part.image as usize, stored) {
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
    pub(super) fn finish(mut self) -> Vec<ToGather> {
        match self.reduce() {
            Ok(records) => records,
            Err(message) => vec![ToGather::Abort(message)],
        }
    }

    /// Reduces the partition's local ids once every worker's contributions are in: the map
    /// statistics, the rows in records of [`ROWS_PER_RECORD`] (global ids), then the partition's
    /// summary. Errors: an abort received, an incomplete or inconsistent job
    /// ([`PartitionReducer::complete_job`]), a failed reduction.
    pub(super) fn reduce(&mut self) -> std::result::Result<Vec<ToGather>, String> {
        if let Some(m) = self.abort.take() {
            return Err(m);
        }
        let p = self.partition;
        let job = self.complete_job()?;
        let dim = job.dim as usize;
        let t0 = Instant::now();
        let reduced = aggregate::reduce(&self.store, self.local_gaussians(&job), dim, self.params)
            .map_err(|e| format!("partition {p}: {e}"))?;
        let reduce_s = t0.elapsed().as_secs_f64();
        let mut out: Vec<ToGather> = std::mem::take(&mut self.stats)
            .into_iter()
            .map(ToGather::Map)
            .collect();
        self.push_rows(&mut out, &reduced, dim);
        out.push(ToGather::Part(PartSummary {
            partition: p,
            rows: reduced.ids.len() as u64,
            images: self.images,
            entries: self.entries,
            chunks: reduced.chunks as u64,
            spilled: self.store.spilled() as u64,
            reduce_s,
            job,
        }));
        Ok(out)
    }

    /// The job every worker's end record names, once the partition holds all of it: every
    /// worker ended and loaded the scene, all name the same job, every view's contribution was
    /// sent and received, and the contributions have the job's width.
    fn complete_job(&self) -> std::result::Result<JobKey, String> {
        let p = self.partition;
        let mut job: Option<&JobKey> = None;
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
            match job {
                None => job = Some(key),
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
        Ok(job.clone())
    }

    /// How many of the job's Gaussians fall in this partition: global ids `p, p + peers, …`
    /// below the scene's count, numbered locally from 0.
    fn local_gaussians(&self, job: &JobKey) -> usize {
        let (p, n, peers) = (self.partition as u64, job.gaussians, self.peers as u64);
        if p < n {
            (n - p).div_ceil(peers) as usize
        } else {
            0
        }
    }

    /// Appends the reduced rows to `out` in records of [`ROWS_PER_RECORD`], local ids mapped back
    /// to global ones (`l · peers + p`).
    fn push_rows(&self, out: &mut Vec<ToGather>, reduced: &aggregate::Reduced, dim: usize) {
        let p = self.partition;
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
    }
}
