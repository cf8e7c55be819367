//! The JSON run report written beside the embeddings (`report.json`): inputs, models, parameters,
//! per-stage timings and counts, so a run can be audited and compared.

use serde::{Deserialize, Serialize};

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

/// The per-image work of some images, summed: what every image adds to [`StageTimings`] and
/// [`Counts`]. One struct for the back workers of `encode` ([`crate::pipeline::encode_pool`]) and
/// the map workers of `encode-cluster` (sent between processes), so that both fill the report the
/// same way ([`ImageWork::fill`]).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ImageWork {
    /// Images done.
    pub images: u64,
    /// Seconds decoding image files.
    pub decode_s: f64,
    /// Seconds generating masks.
    pub masks_s: f64,
    /// Seconds embedding the mask crops with CLIP.
    pub clip_s: f64,
    /// Seconds in the rasterizer (with GPU label sums: the pass and its readback).
    pub raster_s: f64,
    /// Seconds of the host side of the image stage (`a_kj`), and, in `encode`, the hand-over to
    /// the contribution store.
    pub image_aggregate_s: f64,
    /// Masks over the images.
    pub masks: u64,
    /// Non-zero `a_kj` over the images.
    pub entries: u64,
    /// Raster pixels the contributions were counted over.
    pub raster_pixels: u64,
    /// `(pixel, Gaussian)` contributions over those pixels.
    pub raster_entries: u64,
    /// Images whose `a_kj` were summed on the GPU.
    #[serde(default)]
    pub device_sum_views: u64,
}

impl ImageWork {
    /// Adds another share (another worker's, or one image's).
    pub fn add(&mut self, o: &ImageWork) {
        self.images += o.images;
        self.decode_s += o.decode_s;
        self.masks_s += o.masks_s;
        self.clip_s += o.clip_s;
        self.raster_s += o.raster_s;
        self.image_aggregate_s += o.image_aggregate_s;
        self.masks += o.masks;
        self.entries += o.entries;
        self.raster_pixels += o.raster_pixels;
        self.raster_entries += o.raster_entries;
        self.device_sum_views += o.device_sum_views;
    }

    /// Writes the per-image stage times into `t` and the per-image counts into `c` (masks,
    /// entries, contributors per pixel, GPU-summed views); the other fields are left as they are.
    pub fn fill(&self, t: &mut StageTimings, c: &mut Counts) {
        t.decode = self.decode_s;
        t.masks = self.masks_s;
        t.clip = self.clip_s;
        t.raster = self.raster_s;
        t.image_aggregate = self.image_aggregate_s;
        c.masks = self.masks as usize;
        c.entries = self.entries as usize;
        c.contributors_per_pixel = self.raster_entries as f64 / self.raster_pixels.max(1) as f64;
        c.device_sum_views = self.device_sum_views as usize;
    }
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
    /// A rasterizer's phases summed over its images, in ms (GPU rasterizer only; `None` for
    /// front workers): where its per-image time goes (project, host binning and sort,
    /// count/scan, write or label sums, each with its readback).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub raster_phases_ms: Option<crate::raster::PhaseTimings>,
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn image_work_adds_every_field_and_fills_timings_and_counts() {
        let one = |k: f64| ImageWork {
            images: 1,
            decode_s: k,
            masks_s: 2.0 * k,
            clip_s: 3.0 * k,
            raster_s: 4.0 * k,
            image_aggregate_s: 5.0 * k,
            masks: 6,
            entries: 70,
            raster_pixels: 100,
            raster_entries: 250,
            device_sum_views: 1,
        };
        let mut w = ImageWork::default();
        w.add(&one(1.0));
        w.add(&one(0.5));
        assert_eq!(w.images, 2);
        assert_eq!((w.masks, w.entries, w.device_sum_views), (12, 140, 2));
        let (mut t, mut c) = (
            StageTimings {
                total: 9.0,
                reduce: 1.0,
                ..Default::default()
            },
            Counts {
                views_used: 2,
                ..Default::default()
            },
        );
        w.fill(&mut t, &mut c);
        assert_eq!(
            (t.decode, t.masks, t.clip, t.raster, t.image_aggregate),
            (1.5, 3.0, 4.5, 6.0, 7.5)
        );
        // Untouched: the whole-run fields.
        assert_eq!((t.total, t.reduce, c.views_used), (9.0, 1.0, 2));
        assert_eq!((c.masks, c.entries, c.device_sum_views), (12, 140, 2));
        assert_eq!(c.contributors_per_pixel, 2.5);
        // Across processes (encode-cluster) the struct travels serialised.
        let back: ImageWork = serde_json::from_str(&serde_json::to_string(&w).unwrap()).unwrap();
        assert_eq!(back, w);
    }
}
