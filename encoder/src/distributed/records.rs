//! The records the dataflow exchanges (map → reduce: [`ToReducer`]; reduce → gather:
//! [`ToGather`]) and what they carry. A leaf: the map, reduce and gather sides all read it, and
//! it reads none of them.

use serde::{Deserialize, Serialize};

/// How many of a scene's `n` Gaussians fall in partition `p` of `peers`: global ids
/// `p, p + peers, …` below `n`, numbered locally from 0.
pub(super) fn local_gaussians(p: u64, n: u64, peers: u64) -> usize {
    if p < n {
        (n - p).div_ceil(peers) as usize
    } else {
        0
    }
}

/// Timings and counts of one map worker, summed over its images.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub(super) struct MapStats {
    pub(super) worker: u32,
    /// Wall-clock seconds of the map loop.
    pub(super) wall_s: f64,
    /// Views no worker mapped because every partition's checkpoint held them (worker 0, which
    /// hands out the views, counts them; 0 on the others).
    pub(super) resumed: u64,
    /// The views this worker mapped, in the order it mapped them.
    pub(super) views: Vec<u32>,
    /// The images' work (the same struct `encode`'s back workers sum). Not `#[serde(flatten)]`:
    /// timely's exchange uses bincode, which cannot decode flattened structs.
    pub(super) work: crate::report::ImageWork,
}

/// What a job must agree on across processes (a mismatch means processes got other arguments).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(super) struct JobKey {
    pub(super) gaussians: u64,
    pub(super) views: u64,
    pub(super) dim: u64,
    pub(super) fingerprint: String,
}

/// One image's share of partition `partition`: `a_kj` over local ids `k / P`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub(super) struct ImagePart {
    pub(super) partition: u32,
    pub(super) image: u32,
    pub(super) dim: u32,
    /// The scene's Gaussians N and the job's views (each partition sizes its state from them).
    pub(super) scene: (u64, u32),
    /// M, the image's masks (each partition numbers the codebook's atoms from the counts).
    pub(super) mask_count: u32,
    /// `[M * dim]` the image's mask embeddings `E_j`: sent to the partitions that need them
    /// (partition 0, which keeps the mixture's codebook; every partition for the dense
    /// reduction), empty for the others.
    pub(super) mask_embeddings: Vec<f32>,
    /// Local Gaussian ids (global id / P), ascending.
    pub(super) local_ids: Vec<u32>,
    pub(super) masks: Vec<u32>,
    pub(super) weights: Vec<f32>,
}

/// Map → reduce records, routed by `partition`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub(super) enum ToReducer {
    Image(ImagePart),
    Done {
        partition: u32,
        worker: u32,
        /// Images the worker sent to this partition.
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
    pub(super) fn partition(&self) -> u32 {
        match self {
            ToReducer::Image(p) => p.partition,
            ToReducer::Done { partition, .. } | ToReducer::Abort { partition, .. } => *partition,
        }
    }
}

/// What one partition reports when it has reduced.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub(super) struct PartSummary {
    pub(super) partition: u32,
    pub(super) rows: u64,
    pub(super) images: u64,
    pub(super) entries: u64,
    pub(super) chunks: u64,
    pub(super) spilled: u64,
    pub(super) reduce_s: f64,
    pub(super) job: JobKey,
    /// Observed Gaussians of the mixture's rows sent (0 without the mixture).
    pub(super) mixture_rows: u64,
    /// Rows of the masks' record sent (the partition's Gaussians; 0 without the record).
    pub(super) record_rows: u64,
    /// Masks of the views taken in (every view's, once the job is complete).
    pub(super) masks: u64,
    /// Views restored from the partition's checkpoint.
    pub(super) restored: u64,
    /// Checkpoints written, their seconds in all, the largest one's bytes.
    pub(super) checkpoints: (u64, f64, u64),
}

/// A block of a partition's mixture rows ([`crate::aggregate::MixtureFold::finish_rows`]),
/// global Gaussian ids ascending.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub(super) struct MixtureRows {
    pub(super) partition: u32,
    pub(super) ids: Vec<u32>,
    /// `[ids.len()]` kept pairs per row.
    pub(super) lengths: Vec<u8>,
    /// The rows' kept pairs in row order: codebook atoms (global) and `a_kj`.
    pub(super) atoms: Vec<u32>,
    pub(super) weights: Vec<f32>,
}

/// A block of a partition's masks' record ([`slag_common::mask_record::MaskRecord`]): `S`
/// slots of each of `ids` (global Gaussian ids).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub(super) struct RecordRows {
    pub(super) partition: u32,
    pub(super) ids: Vec<u32>,
    pub(super) views: Vec<u16>,
    pub(super) masks: Vec<u16>,
    pub(super) weights: Vec<f32>,
}

/// Reduce → gather records, all routed to worker 0.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub(super) enum ToGather {
    Rows {
        partition: u32,
        ids: Vec<u32>,
        vectors: Vec<f32>,
        total_weights: Vec<f32>,
    },
    Part(PartSummary),
    Mixture(MixtureRows),
    /// Partition 0's codebook: every view's mask embeddings in view order, `[M * D]`.
    Codebook(Vec<f32>),
    Record(RecordRows),
    Map(MapStats),
    Abort(String),
}
