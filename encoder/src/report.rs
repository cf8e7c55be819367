//! The JSON run report written beside the embeddings (`report.json`): inputs, models, parameters,
//! per-stage timings and counts, so a run can be audited and compared.

use serde::Serialize;

/// Wall-clock seconds spent in each stage, summed over images (stages of different images overlap
/// in the pipeline, so the sum of stages can exceed `total`).
#[derive(Debug, Clone, Default, Serialize)]
pub struct StageTimings {
    /// Reading the `.ply` and the cameras.
    pub load_scene: f64,
    /// Decoding image files.
    pub decode: f64,
    /// Mask generation (SAM encoder + decoder + filters, or graph segmentation).
    pub masks: f64,
    /// CLIP crop preparation + visual tower.
    pub clip: f64,
    /// Weight rasterization (projection, tiles, blending, readback).
    pub raster: f64,
    /// Image stage of the aggregation (`a_kj`).
    pub image_aggregate: f64,
    /// Reduction over images (`E_k`), wall clock until its last chunk was handed to the writer
    /// (the writer thread converts and writes each chunk while the next one is accumulated).
    pub reduce: f64,
    /// Writing the output files, wall clock after the reduction: the last chunk's write, the
    /// mixture file and the embeddings file's assembly and fsync (what the overlap left).
    pub write: f64,
    /// Whole run, wall clock.
    pub total: f64,
}

/// Counts describing the run.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Counts {
    /// Views in the camera source.
    pub views_total: usize,
    /// Views encoded (after `--every`).
    pub views_used: usize,
    /// Gaussians in the `.ply`.
    pub gaussians: usize,
    /// Gaussians that received an embedding.
    pub observed: usize,
    /// `observed / gaussians`.
    pub observed_fraction: f64,
    /// Masks over all images.
    pub masks: usize,
    /// Non-zero `a_kj` over all images.
    pub entries: usize,
    /// Mean contributors per raster pixel over all images.
    pub contributors_per_pixel: f64,
    /// Image contributions spilled to disk (memory budget exceeded).
    pub spilled_images: usize,
    /// Chunks the reduction used.
    pub reduce_chunks: usize,
    /// Views whose `a_kj` were summed on the GPU per (Gaussian, mask-set label)
    /// ([`crate::pipeline::view_contribution`]); the others went through per-pixel lists.
    pub device_sum_views: usize,
    /// Peak resident memory of the process (`VmHWM` of /proc/self/status), bytes; `None` where
    /// the platform does not report it.
    pub peak_rss_bytes: Option<u64>,
}

/// The process's peak resident set size (`VmHWM`), bytes, on Linux; `None` elsewhere.
pub fn peak_rss_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// The whole report.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Report {
    /// slag version.
    pub slag_version: String,
    /// Input paths and selection.
    pub inputs: serde_json::Value,
    /// Models and their execution providers.
    pub models: serde_json::Value,
    /// Parameters that change the result.
    pub parameters: serde_json::Value,
    /// Per-stage timings, seconds.
    pub timings: StageTimings,
    /// Counts.
    pub counts: Counts,
    /// Output files and sizes.
    pub outputs: serde_json::Value,
    /// Each worker thread's share (images, busy seconds), fronts first, then one per rasterizer.
    pub workers: Vec<WorkerShare>,
}

/// How one worker thread's share of the run went (the balance report: with dynamic scheduling
/// a slow image delays only its own worker, and the shares show how even the split was).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct WorkerShare {
    /// `"front-<i>"` or the rasterizer's name with its index, e.g. `"raster-1 wgpu-vulkan H200"`.
    pub name: String,
    /// Images this worker processed.
    pub images: usize,
    /// Seconds it spent working (excluding waits for input or for a free queue slot).
    pub busy_s: f64,
    /// Seconds from the start of the run's wall clock ([`StageTimings::total`]) to the start of
    /// this worker's first image (0 when it processed none): the pipeline's fill time.
    pub first_s: f64,
    /// Seconds from the start of the wall clock to the end of this worker's last image: the
    /// drain shows as the spread of these over the workers, and the serial tail (reduction,
    /// write) as `total` minus their maximum.
    pub last_s: f64,
}
