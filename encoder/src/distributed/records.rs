//! The records the dataflow exchanges (map → reduce: [`ToReducer`]; reduce → gather:
//! [`ToGather`]) and what they carry. A leaf: the map, reduce and gather sides all read it, and
//! it reads none of them.

use serde::{Deserialize, Serialize};

/// Timings and counts of one map worker, summed over its images.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub(super) struct MapStats {
    pub(super) worker: u32,
    /// Wall-clock seconds of the map loop.
    pub(super) wall_s: f64,
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
    /// `[M * dim]` the image's mask embeddings `E_j`.
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
    Map(MapStats),
    Abort(String),
}
