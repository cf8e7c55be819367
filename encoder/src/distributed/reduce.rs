//! The reduce side: [`PartitionReducer`] takes in its partition's `a_kj` from every worker as
//! they come and keeps the running state of its own Gaussians only: the mixture's fold
//! ([`MixtureFold`], views folded in view order), the masks' record of its Gaussians, and, for the
//! dense file, its contributions (spilled beyond a budget) for `aggregate::reduce`. Once every
//! worker's contributions are in, it checks completeness and sends its rows to worker 0.

use std::cell::RefCell;
use std::collections::BTreeMap;
use std::rc::Rc;
use std::time::Instant;

use slag_common::mask_record::MaskRecord;

use super::checkpoint::{Progress, Saved};
use super::records::{
    ImagePart, JobKey, MapStats, MixtureRows, PartSummary, RecordRows, ToGather, ToReducer,
    local_gaussians,
};
use crate::aggregate::{
    self, ContributionStore, Entry, ImageContribution, MixtureFold, ReduceParams, StoredImage,
};

/// Rows per gather record (worker 0 receives each partition in chunks of this many Gaussians).
pub(super) const ROWS_PER_RECORD: usize = 4096;

/// The outputs a partition reduces to (the encode's [`crate::pipeline::EncodeParams`]).
#[derive(Debug, Clone, Copy)]
pub(super) struct Forms {
    /// The dense `E_k` ([`aggregate::reduce`] over the kept contributions).
    pub(super) dense: bool,
    /// The mixture's kept pairs per Gaussian ([`MixtureFold`]), when written.
    pub(super) mixture_keep: Option<usize>,
    /// The masks' record's slots per Gaussian, when kept.
    pub(super) record_slots: Option<usize>,
}

/// The streamed state of one partition's Gaussians, made at its first view.
struct PartitionState {
    /// The scene's Gaussians and the job's views, as the first view named them.
    scene: (u64, u32),
    fold: Option<MixtureFold>,
    record: Option<MaskRecord>,
}

/// How a partition checkpoints its state ([`super::checkpoint`]), and what it wrote so far.
pub(super) struct Checkpointer {
    /// The partition's checkpoint file.
    pub(super) path: std::path::PathBuf,
    /// The job's digest written in it ([`super::resume::job_digest`]).
    pub(super) job: [u8; 32],
    /// The least time between two checkpoints.
    pub(super) every: std::time::Duration,
    /// When the last one was written (or the partition started).
    pub(super) last: Instant,
    /// Views the last one covers.
    pub(super) written: u32,
    /// Checkpoints written, their seconds in all and the largest one's bytes.
    pub(super) count: u64,
    pub(super) seconds: f64,
    pub(super) bytes: u64,
}

/// What a partition starts from, set by its worker once the job's views are agreed and before
/// any image is sent ([`PartitionReducer::adopt`]): the state of a checkpoint, and how to write
/// the next ones.
#[derive(Default)]
pub(super) struct Resume {
    pub(super) saved: Option<Saved<'static>>,
    pub(super) checkpoints: Option<Checkpointer>,
}

/// The reduce side of one partition.
pub(super) struct PartitionReducer {
    pub(super) partition: u32,
    pub(super) peers: u32,
    pub(super) params: ReduceParams,
    pub(super) forms: Forms,
    /// The contributions kept for the dense reduction (used with [`Forms::dense`] only).
    pub(super) store: ContributionStore,
    state: Option<PartitionState>,
    pub(super) dim: Option<usize>,
    pub(super) images: u64,
    pub(super) entries: u64,
    pub(super) done: Vec<Option<(u64, Option<JobKey>)>>,
    pub(super) stats: Vec<MapStats>,
    pub(super) abort: Option<String>,
    /// Views taken in, in view order: `0..next` (restored or received).
    next: u32,
    /// Views received before an earlier one, by view index.
    waiting: BTreeMap<u32, ImagePart>,
    /// Masks of the views taken in.
    masks: u64,
    /// Views restored from a checkpoint.
    restored: u32,
    /// Where the worker puts the partition's [`Resume`] (taken at the first record).
    resume: Rc<RefCell<Option<Resume>>>,
    checkpoints: Option<Checkpointer>,
}

impl PartitionReducer {
    pub(super) fn new(
        partition: u32,
        peers: u32,
        params: ReduceParams,
        forms: Forms,
        store: ContributionStore,
        resume: Rc<RefCell<Option<Resume>>>,
    ) -> Self {
        Self {
            partition,
            peers,
            params,
            forms,
            store,
            state: None,
            dim: None,
            images: 0,
            entries: 0,
            done: vec![None; peers as usize],
            stats: Vec::new(),
            abort: None,
            next: 0,
            waiting: BTreeMap::new(),
            masks: 0,
            restored: 0,
            resume,
            checkpoints: None,
        }
    }

    /// Takes the partition's [`Resume`] once its worker has set it: the checkpoint's state
    /// (views `0..next`, their counts, the fold and the record) and the checkpoint settings.
    fn adopt(&mut self) {
        let Some(resume) = self.resume.borrow_mut().take() else {
            return;
        };
        self.checkpoints = resume.checkpoints;
        if let Some(saved) = resume.saved
            && let Err(m) = self.restore(saved)
        {
            self.fail(format!("partition {}: {m}", self.partition));
        }
    }

    /// The state of checkpoint `saved`, views `0..saved.progress.next` taken in.
    ///
    /// Errors: a fold or a record where this job's outputs have none (or none where they have
    /// one), the fold's ([`MixtureFold::from_state`]).
    fn restore(&mut self, saved: Saved<'static>) -> std::result::Result<(), String> {
        let p = saved.progress;
        if saved.fold.is_some() != self.forms.mixture_keep.is_some()
            || saved.record.is_some() != self.forms.record_slots.is_some()
            || saved
                .fold
                .as_ref()
                .is_some_and(|f| f.keeps_codebook != (self.partition == 0))
        {
            return Err("its checkpoint holds other outputs than the job's".into());
        }
        let fold = saved
            .fold
            .map(MixtureFold::from_state)
            .transpose()
            .map_err(|e| e.to_string())?;
        self.state = Some(PartitionState {
            scene: p.scene,
            fold,
            record: saved.record.map(std::borrow::Cow::into_owned),
        });
        self.dim = Some(p.dim as usize);
        (self.next, self.restored, self.images) = (p.next, p.next, p.next as u64);
        (self.entries, self.masks) = (p.entries, p.masks);
        tracing::info!(
            partition = self.partition,
            views = p.next,
            "resumed from the partition's checkpoint"
        );
        Ok(())
    }

    /// Takes in image `part` and every view waiting behind it, in view order, then writes a
    /// checkpoint when one is due.
    fn absorb_in_order(&mut self, part: ImagePart) {
        let image = part.image;
        if image < self.next || self.waiting.contains_key(&image) {
            let p = self.partition;
            self.fail(format!("partition {p}: view {image} reached it twice"));
            return;
        }
        self.waiting.insert(image, part);
        while let Some(part) = self.waiting.remove(&self.next) {
            if let Err(m) = self.absorb_image(part) {
                self.fail(format!("partition {}: {m}", self.partition));
                return;
            }
            self.next += 1;
        }
        self.checkpoint_if_due();
    }

    /// Writes the partition's state to its checkpoint when checkpoints are on, views were taken
    /// in since the last one and the interval has passed. A failed write is logged and the job
    /// goes on (the previous checkpoint stays whole).
    fn checkpoint_if_due(&mut self) {
        let Some(mut c) = self.checkpoints.take() else {
            return;
        };
        if self.next > c.written && c.last.elapsed() >= c.every {
            let t0 = Instant::now();
            let written = self
                .saved(c.job)
                .and_then(|s| super::checkpoint::write(&c.path, &s).map_err(|e| e.to_string()));
            let seconds = t0.elapsed().as_secs_f64();
            match written {
                Ok(bytes) => {
                    (c.count, c.seconds, c.bytes) =
                        (c.count + 1, c.seconds + seconds, c.bytes.max(bytes));
                    c.written = self.next;
                    tracing::info!(
                        partition = self.partition,
                        views = self.next,
                        bytes,
                        seconds,
                        "checkpoint written"
                    );
                }
                Err(e) => tracing::warn!(
                    partition = self.partition,
                    "checkpoint not written, the previous one stays: {e}"
                ),
            }
            c.last = Instant::now();
        }
        self.checkpoints = Some(c);
    }

    /// The partition's state after views `0..next` for a checkpoint of job `job`, its arrays
    /// borrowed.
    ///
    /// Errors: no state yet; the fold's ([`MixtureFold::state`]).
    fn saved(&self, job: [u8; 32]) -> std::result::Result<Saved<'_>, String> {
        let state = self.state.as_ref().ok_or("no state to checkpoint")?;
        let fold = state
            .fold
            .as_ref()
            .map(MixtureFold::state)
            .transpose()
            .map_err(|e| e.to_string())?;
        Ok(Saved {
            progress: Progress {
                job,
                partition: self.partition,
                peers: self.peers,
                scene: state.scene,
                dim: self.dim.unwrap_or(0) as u64,
                next: self.next,
                entries: self.entries,
                masks: self.masks,
            },
            fold,
            record: state.record.as_ref().map(std::borrow::Cow::Borrowed),
        })
    }

    pub(super) fn fail(&mut self, message: String) {
        self.abort.get_or_insert(message);
    }

    /// Takes in one record: an image's share (folded in view order, [`Self::absorb_in_order`]),
    /// a worker's end record, an abort.
    pub(super) fn absorb(&mut self, record: ToReducer) {
        self.adopt();
        match record {
            ToReducer::Image(part) => {
                if self.abort.is_none() {
                    self.absorb_in_order(part);
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

    /// Takes in one image's share: its entries into the fold and the record of this
    /// partition's Gaussians (made at the first image), and into the store for the dense
    /// reduction.
    ///
    /// Errors: a malformed share, one naming another scene than the first, the fold's, the
    /// store's (spill I/O).
    fn absorb_image(&mut self, part: ImagePart) -> std::result::Result<(), String> {
        let dim = part.dim as usize;
        let (masks, held) = (part.mask_count as usize, part.mask_embeddings.len());
        if *self.dim.get_or_insert(dim) != dim
            || (held != 0 && held != masks * dim)
            || part.local_ids.len() != part.masks.len()
            || part.local_ids.len() != part.weights.len()
        {
            return Err(format!("malformed contribution of image {}", part.image));
        }
        self.images += 1;
        self.entries += part.local_ids.len() as u64;
        self.masks += masks as u64;
        let entries: Vec<Entry> = part
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
        let image = part.image as usize;
        let (dense, partition) = (self.forms.dense, self.partition);
        let state = self.state_for(part.scene, dim)?;
        if let Some(record) = state.record.as_mut() {
            record.add_view(image, crate::pipeline::sinks::dominant_masks(&entries));
        }
        let stored = StoredImage::from_contribution(ImageContribution {
            dim,
            mask_embeddings: part.mask_embeddings,
            entries,
        });
        // The dense reduction keeps the image; the fold only reads it before its turn.
        let (folded, kept) = match (state.fold.is_some(), dense) {
            (true, true) => (Some(stored.clone()), Some(stored)),
            (true, false) => (Some(stored), None),
            (false, _) => (None, Some(stored)),
        };
        if let (Some(fold), Some(mut folded)) = (state.fold.as_mut(), folded) {
            if partition != 0 {
                // A counting fold: the codebook is partition 0's.
                folded.mask_embeddings = Vec::new();
            }
            fold.push_counted(image, folded, masks)
                .map_err(|e| e.to_string())?;
        }
        if let Some(kept) = kept.filter(|_| dense) {
            self.store
                .push_stored_as(image, kept)
                .map_err(|e| e.to_string())?;
        }
        Ok(())
    }

    /// The partition's streamed state for a job of `scene` (Gaussians, views) and embedding
    /// width `dim`: made at the first image, then checked against each image.
    ///
    /// Errors: a scene other than the first image's; the fold's or the record's parameters.
    fn state_for(
        &mut self,
        scene: (u64, u32),
        dim: usize,
    ) -> std::result::Result<&mut PartitionState, String> {
        let n_local = local_gaussians(self.partition as u64, scene.0, self.peers as u64);
        let state = match self.state.take() {
            Some(s) => s,
            None => PartitionState {
                scene,
                fold: self
                    .forms
                    .mixture_keep
                    .map(|keep| {
                        let min = self.params.min_total_weight;
                        if self.partition == 0 {
                            MixtureFold::new(n_local, dim, keep, min)
                        } else {
                            MixtureFold::counting(n_local, dim, keep, min)
                        }
                    })
                    .transpose()
                    .map_err(|e| e.to_string())?,
                record: self
                    .forms
                    .record_slots
                    .map(|slots| MaskRecord::new(n_local, slots, scene.1 as usize))
                    .transpose()
                    .map_err(|e| e.to_string())?,
            },
        };
        if state.scene != scene {
            return Err(format!(
                "images of scenes of {:?} and {scene:?} (Gaussians, views): give every process \
                 the same scene and arguments",
                state.scene
            ));
        }
        Ok(self.state.insert(state))
    }

    /// Reduces the partition; the records for worker 0 (or one `Abort`).
    pub(super) fn finish(mut self) -> Vec<ToGather> {
        match self.reduce() {
            Ok(records) => records,
            Err(message) => vec![ToGather::Abort(message)],
        }
    }

    /// Reduces the partition's local ids once every worker's contributions are in: the map
    /// statistics; the dense rows with [`Forms::dense`], the mixture's rows (and, from
    /// partition 0, the codebook) with [`Forms::mixture_keep`], the masks' record's rows with
    /// [`Forms::record_slots`], each in records of [`ROWS_PER_RECORD`] Gaussians (global ids);
    /// then the partition's summary.
    ///
    /// Errors: an abort received, an incomplete or inconsistent job
    /// ([`PartitionReducer::complete_job`]), a failed reduction.
    pub(super) fn reduce(&mut self) -> std::result::Result<Vec<ToGather>, String> {
        self.adopt();
        if let Some(m) = self.abort.take() {
            return Err(m);
        }
        let p = self.partition;
        let job = self.complete_job()?;
        let dim = job.dim as usize;
        let t0 = Instant::now();
        let mut out: Vec<ToGather> = std::mem::take(&mut self.stats)
            .into_iter()
            .map(ToGather::Map)
            .collect();
        let (mut rows, mut chunks) = (0, 0);
        if self.forms.dense {
            let n_local = local_gaussians(p as u64, job.gaussians, self.peers as u64);
            let reduced = aggregate::reduce(&self.store, n_local, dim, self.params)
                .map_err(|e| format!("partition {p}: {e}"))?;
            self.push_rows(&mut out, &reduced, dim);
            (rows, chunks) = (reduced.ids.len() as u64, reduced.chunks as u64);
        }
        let state = self.state.take();
        let (fold, record) = state.map(|s| (s.fold, s.record)).unwrap_or_default();
        let mixture_rows = match fold {
            Some(fold) => {
                let rows = fold
                    .finish_rows()
                    .map_err(|e| format!("partition {p}: {e}"))?;
                self.push_mixture(&mut out, rows)
            }
            None => 0,
        };
        let record_rows = record.map_or(0, |r| self.push_record(&mut out, &r));
        out.push(ToGather::Part(PartSummary {
            partition: p,
            rows,
            images: self.images,
            entries: self.entries,
            chunks,
            spilled: self.store.spilled() as u64,
            reduce_s: t0.elapsed().as_secs_f64(),
            job,
            mixture_rows,
            record_rows,
            masks: self.masks,
            restored: self.restored as u64,
            checkpoints: self
                .checkpoints
                .as_ref()
                .map_or((0, 0.0, 0), |c| (c.count, c.seconds, c.bytes)),
        }));
        Ok(out)
    }

    /// The global id of local id `l` of this partition: `l · peers + p`.
    fn global(&self, l: u32) -> u32 {
        l * self.peers + self.partition
    }

    /// Appends the fold's `rows` to `out` in records of [`ROWS_PER_RECORD`] Gaussians (global
    /// ids), and from partition 0 its codebook; returns the rows sent.
    fn push_mixture(
        &self,
        out: &mut Vec<ToGather>,
        rows: slag_common::mixture::SparseMixture,
    ) -> u64 {
        let n = rows.gaussian_ids.len();
        for start in (0..n).step_by(ROWS_PER_RECORD) {
            let end = (start + ROWS_PER_RECORD).min(n);
            let pairs = rows.offsets[start]..rows.offsets[end];
            out.push(ToGather::Mixture(MixtureRows {
                partition: self.partition,
                ids: rows.gaussian_ids[start..end]
                    .iter()
                    .map(|&l| self.global(l))
                    .collect(),
                lengths: rows.offsets[start..=end]
                    .windows(2)
                    .map(|w| (w[1] - w[0]) as u8)
                    .collect(),
                atoms: rows.atoms[pairs.clone()].to_vec(),
                weights: rows.weights[pairs].to_vec(),
            }));
        }
        if self.partition == 0 {
            out.push(ToGather::Codebook(rows.codebook));
        }
        n as u64
    }

    /// Appends the partition's masks' record to `out` in records of [`ROWS_PER_RECORD`]
    /// Gaussians (global ids); returns the rows sent.
    fn push_record(&self, out: &mut Vec<ToGather>, r: &MaskRecord) -> u64 {
        let (n, s) = (r.len(), r.slots);
        for start in (0..n).step_by(ROWS_PER_RECORD) {
            let end = (start + ROWS_PER_RECORD).min(n);
            let slots = start * s..end * s;
            out.push(ToGather::Record(RecordRows {
                partition: self.partition,
                ids: (start as u32..end as u32).map(|l| self.global(l)).collect(),
                views: r.views[slots.clone()].to_vec(),
                masks: r.masks[slots.clone()].to_vec(),
                weights: r.weights[slots].to_vec(),
            }));
        }
        n as u64
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
        let restored = self.restored as u64;
        if sent + restored != job.views || self.images != job.views {
            return Err(format!(
                "partition {p}: {} contributions taken in ({restored} of them from its \
                 checkpoint), {sent} sent, {} views; the job is incomplete",
                self.images, job.views
            ));
        }
        if let Some(state) = &self.state
            && state.scene != (job.gaussians, job.views as u32)
        {
            return Err(format!(
                "partition {p}: images of a scene of {:?} (Gaussians, views), the job's {:?}",
                state.scene,
                (job.gaussians, job.views)
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
                    .map(|&l| self.global(l))
                    .collect(),
                vectors: reduced.vectors[start * dim..end * dim].to_vec(),
                total_weights: reduced.total_weights[start..end].to_vec(),
            });
        }
    }
}
