//! The JSON run report written beside the embeddings (`report.json`): inputs, models, parameters,
//! per-stage timings and counts, so a run can be audited and compared.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};
use slag_common::embeddings::StoredPrecision;
use slag_common::onnx::ExecutionProvider;

/// Wall-clock seconds spent in each stage, summed over images (stages of different images overlap
/// in the pipeline, so the sum of stages can exceed `total`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct StageTimings {
    /// Setting up the front workers' models before the encode starts (ONNX Runtime sessions,
    /// weights to the devices, CLIP's warm-up run; each GPU's side by side), wall clock. Not
    /// within [`StageTimings::total`]: the process's wall is about this plus `total`. 0 where
    /// it is not timed: `encode-cluster`'s reports, and reports written before it was recorded.
    #[serde(default)]
    pub models: f64,
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
    /// With the mixture form, the same pass also selects each Gaussian's kept `a_kj` (counted
    /// here); the moving of them into the mixture's rows is in `outputs.mixture_reduce_s`.
    /// With the device reduction on several GPUs, the moving of the kept records between them
    /// counts here too.
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

/// Why and where the device reduction gave way to the host's ([`Counts::device_reduce_fallback`]).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct DeviceReduceFallback {
    /// The device memory limit the kept label sums met (the first rasterizer's error: the
    /// budget `--device-reduce-memory-mb`, or the device full).
    pub reason: String,
    /// Views whose label sums had been kept on the devices and were brought back to the host.
    pub views_brought_back: usize,
}

/// Counts describing the run.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Counts {
    /// Views in the camera source.
    pub views_total: usize,
    /// Views encoded (after `--every`, `--hold-out-every` and the view selection).
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
    /// Chunks the reduction used (tiles of Gaussians on the device).
    pub reduce_chunks: usize,
    /// Times the device reduction reduced kept views: 1 when every view was kept to the end,
    /// else the streamed reduction's waves (each folds the views kept so far into a running
    /// state per Gaussian and frees them); 0 when the host reduced.
    #[serde(default)]
    pub device_reduce_waves: usize,
    /// The most bytes the device reduction held on one device at once: the streamed
    /// reduction's running state plus the most label sums kept at once (0 when the host
    /// reduced).
    #[serde(default)]
    pub device_reduce_peak_bytes: u64,
    /// When the host reduced and only the mixture was written: the most bytes of the host's
    /// streamed reduction at once (each Gaussian's Σ a_kj and kept pairs, the codebook, and the
    /// views that waited for an earlier one); 0 otherwise. It does not grow with the views
    /// beyond the codebook.
    #[serde(default)]
    pub host_fold_peak_bytes: u64,
    /// With `--dense`: the host's dense fold (f64 accumulators tiled by Gaussian ids, the
    /// views folded as they came): its tiles, the tiles spilled to disk, the sweeps of a batch
    /// of views over them and the bytes written to its spill files.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub dense_fold: Option<crate::aggregate::DenseFoldStats>,
    /// The reduction ran on the GPU ([`crate::config::ReduceOn`]): the `a_kj` never reached the
    /// host, so `entries` counts none.
    pub device_reduce: bool,
    /// GPUs the device reduction ran on at once: one per GPU that kept views when they split
    /// the Gaussians between them (the default outputs on several GPUs), else 1; 0 when the
    /// host reduced.
    pub device_reduce_gpus: usize,
    /// The device reduction (`--reduce auto`) gave way to the host's during the run: the views
    /// kept on the devices were brought back as the host's `a_kj` and the host reduced
    /// (`device_reduce` false); `None`: it did not.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub device_reduce_fallback: Option<DeviceReduceFallback>,
    /// Views whose `a_kj` were summed on the GPU per (Gaussian, mask-set label)
    /// ([`crate::pipeline::view_contribution`]); the others went through per-pixel lists.
    pub device_sum_views: usize,
    /// Peak resident memory of the process (`VmHWM` of /proc/self/status), bytes; `None` where
    /// the platform does not report it.
    pub peak_rss_bytes: Option<u64>,
    /// The queues between the front stages (decode, masks, CLIP) and the back stage (raster,
    /// `a_kj`): their slots and high-water marks (`encode` only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub queue: Option<QueueStats>,
}

/// The queues between the front and the back stages of one `encode` run. An image waits there
/// with its masks run-length encoded and its mask embeddings, so the memory between the stages
/// is at most `high_water_items` of them (`high_water_bytes` measured).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct QueueStats {
    /// Slots of all queues together (images a queue holds before a front waits).
    pub capacity_items: usize,
    /// Most bytes held at once by images handed to a queue and not yet taken.
    pub high_water_bytes: u64,
    /// Most images handed to a queue and not yet taken at once; a front waiting for a free slot
    /// holds its image and counts, so this may reach `capacity_items` + the front workers.
    pub high_water_items: usize,
    /// Bytes of the largest image handed over (run-length encoded masks + embeddings).
    pub largest_item_bytes: u64,
}

/// The whole report.
///
/// Every section is a struct; fields are declared in alphabetical order, the order in which
/// `report.json` has always listed them. Fields marked "`encode` only" or "`encode-cluster`
/// only" are left out of the file (not written as `null`) by the other command.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Report {
    /// slag version.
    pub slag_version: String,
    /// Input paths and selection.
    pub inputs: Inputs,
    /// Models and their execution providers.
    pub models: Models,
    /// Parameters that change the result.
    pub parameters: Parameters,
    /// Per-stage timings, seconds.
    pub timings: StageTimings,
    /// Counts.
    pub counts: Counts,
    /// Output files and sizes.
    pub outputs: Outputs,
    /// The geometric segments computed beside the encode: where their time went and how long
    /// the run waited for them after the embeddings were written; `encode` with segments only.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub segments: Option<SegmentsOutput>,
    /// Each worker thread's share (images, busy seconds), fronts first, then one per rasterizer.
    pub workers: Vec<WorkerShare>,
    /// Which views were encoded and what choosing them cost; `encode` only.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub view_selection: Option<crate::views::SelectionReport>,
}

/// The report's `segments`: the geometric segments `encode` computes beside the encode
/// (`Encoder::run`), written to `segments.safetensors` after the embeddings.
/// `report.json` is written again once they are, so that it stays the run's last file.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SegmentsOutput {
    /// The masks' record they were weighed with (`mask-record.safetensors`); `None`: geometry
    /// only.
    pub mask_record: Option<PathBuf>,
    /// The segments file.
    pub path: PathBuf,
    /// The segmentation's own figures: segments, edges, wall seconds beside the encode, and
    /// its stages (k-NN, weights, sort, criterion, waiting for the masks' record).
    pub stats: crate::segments::SegmentStats,
    /// Threads of its pool while the encode ran.
    pub threads: usize,
    /// Seconds the run waited for the segments after the embeddings were written: what they
    /// add to the process's wall time (0 when they were done by then).
    pub waited_s: f64,
    /// Threads it was given when it outlasted the encode; `None`: it was done by then.
    pub widened_to: Option<usize>,
}

/// The report's `inputs`: what was encoded.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct Inputs {
    /// Keep every N-th view ([`crate::config::SceneConfig::every`]).
    pub every: usize,
    /// The held-out step ([`crate::config::SceneConfig::hold_out_every`]); absent: none.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub hold_out_every: Option<usize>,
    /// The `.ply` read.
    pub ply: PathBuf,
    /// The scene folder.
    pub scene: PathBuf,
}

/// The report's `models`: the model files, the mask source and rasterizer that ran, and where
/// each model ran.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct Models {
    /// The CLIP model id recorded in the embeddings (the visual tower's file stem).
    pub clip_model_id: String,
    /// The CLIP visual tower file.
    pub clip_visual: PathBuf,
    /// The provider that actually ran CLIP (and SAM); `encode` only.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub execution_provider: Option<ExecutionProvider>,
    /// The provider asked for ([`crate::config::ExecutionConfig::ep`]).
    pub execution_provider_requested: ExecutionProvider,
    /// Per GPU (or one entry for the CPU): where each model ran; `encode` only.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub execution_providers: Option<Vec<ModelPlacement>>,
    /// Front workers that ran; `encode` only.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub front_workers: Option<usize>,
    /// The mask generator's name (e.g. `sam-automatic`, `graph`).
    pub masks: String,
    /// The first (or only) rasterizer's name.
    pub rasterizer: String,
    /// Every rasterizer's name, one per GPU; `encode` only.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rasterizers: Option<Vec<String>>,
    /// The SAM prompt decoder file (`null` without SAM masks).
    pub sam_decoder: Option<PathBuf>,
    /// The SAM image encoder file (`null` without SAM masks).
    pub sam_encoder: Option<PathBuf>,
}

/// Where the models of one GPU (or of the CPU) ran: an entry of [`Models::execution_providers`].
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ModelPlacement {
    /// Crops per CLIP batch.
    pub clip_batch: usize,
    /// Provider running CLIP.
    pub clip_visual: ExecutionProvider,
    /// The device's label (`cpu`, or the GPU's name).
    pub device: String,
    /// GPU index; absent for the CPU entry.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gpu: Option<usize>,
    /// Provider running the SAM decoder (`null` without SAM masks).
    pub sam_decoder: Option<ExecutionProvider>,
    /// Provider running the SAM encoder (`null` without SAM masks).
    pub sam_encoder: Option<ExecutionProvider>,
}

/// The report's `parameters`: the settings of the run, as [`crate::config::EncodeConfig`]
/// holds them (flat, with the command line's names). The f32 settings are written widened to
/// f64 (0.88 as 0.8799999952316284), as `report.json` has always had them.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct Parameters {
    /// [`crate::config::ClipConfig::batch`] (`null`: the provider's default).
    pub clip_batch: Option<usize>,
    /// `host:port` of every process; `encode-cluster` only.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cluster_addresses: Option<Vec<String>>,
    /// Processes of the cluster; `encode-cluster` only.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cluster_processes: Option<usize>,
    /// [`crate::config::ClipConfig::crop_fill`].
    pub crop_fill: crate::clip::CropFill,
    /// The device reduction's memory budget and where it came from (given, or sized from the
    /// GPUs' free memory at the start, [`crate::pipeline::budget`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub device_reduce_budget: Option<crate::pipeline::budget::DeviceBudget>,
    /// [`crate::config::ExecutionConfig::front_workers`] as asked (`null`: the default).
    pub front_workers: Option<usize>,
    /// [`crate::config::ExecutionConfig::gpus`] in its `Debug` form: `Count(N)` or `All`.
    pub gpus: String,
    /// [`crate::config::GraphConfig::k`] (widened to f64, as are the other f32 settings).
    pub graph_k: Option<f64>,
    /// [`crate::config::GraphConfig::min_size`].
    pub graph_min_size: Option<u32>,
    /// [`crate::config::AggregateConfig::levels`].
    pub levels: bool,
    /// [`crate::config::AggregateConfig::mask_erode`].
    pub mask_erode: u32,
    /// [`crate::config::AggregateConfig::mask_weighting`].
    pub mask_weighting: crate::aggregate::MaskWeighting,
    /// [`crate::config::AggregateConfig::min_weight`].
    pub min_weight: f64,
    /// [`crate::config::AggregateConfig::mixture_keep`].
    pub mixture_keep: Option<usize>,
    /// [`crate::config::AggregateConfig::overlap`].
    pub overlap: crate::aggregate::MaskOverlap,
    /// [`crate::config::RasterConfig::scale`].
    pub raster_scale: f64,
    /// [`crate::config::SamConfig::box_nms_thresh`].
    pub sam_box_nms_thresh: f64,
    /// [`crate::config::SamConfig::points_per_batch`].
    pub sam_points_per_batch: Option<usize>,
    /// [`crate::config::SamConfig::points_per_side`].
    pub sam_points_per_side: u32,
    /// [`crate::config::SamConfig::pred_iou_thresh`].
    pub sam_pred_iou_thresh: f64,
    /// [`crate::config::SamConfig::stability_score_thresh`].
    pub sam_stability_score_thresh: f64,
    /// Worker threads the run used (resolved: never `null`).
    pub threads: usize,
    /// [`crate::config::AggregateConfig::top_k_per_pixel`].
    pub top_k_per_pixel: Option<usize>,
}

/// The report's `outputs`: the files written and their sizes.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct Outputs {
    /// The cluster's per-worker and per-partition shares; `encode-cluster` only.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cluster: Option<ClusterOutputs>,
    /// The dense embeddings file; `null` when not written (`encode` writes it only with
    /// [`crate::config::OutputConfig::dense`]; the mixture is then the embeddings output).
    pub embeddings: Option<PathBuf>,
    /// Its size, bytes (0 when not written).
    pub embeddings_bytes: u64,
    /// The optional forms (mixture, levels), each `null` when not written; `encode` only.
    #[serde(flatten)]
    pub forms: Option<FormOutputs>,
    /// Stored precision of the embeddings.
    pub precision: StoredPrecision,
    /// This report's path.
    pub report: PathBuf,
}

/// The optional forms `encode` writes beside the embeddings ([`Outputs::forms`]).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct FormOutputs {
    /// One embeddings file per SAM granularity level (with `levels`).
    pub levels: Option<Vec<LevelOutput>>,
    /// Seconds reducing the levels.
    pub levels_reduce_s: Option<f64>,
    /// The mixture file (with `mixture_keep`).
    pub mixture: Option<PathBuf>,
    /// Stored bytes per Gaussian of the mixture form.
    pub mixture_bytes_per_gaussian: Option<f64>,
    /// Rows of the mixture's codebook (mask embeddings kept).
    pub mixture_codebook_rows: Option<usize>,
    /// Slots per Gaussian of the mixture.
    pub mixture_keep: Option<usize>,
    /// Seconds of the tail that only the mixture costs, disjoint from `timings.reduce`: moving
    /// each chunk's kept `a_kj` into the sparse rows during the reduction (which computes the
    /// sums once for both forms; the per-entry top-`keep` selection runs inside it and is
    /// counted in `timings.reduce`), then freeing the contributions and building the stored
    /// form (codebook and weights rounded to f16).
    pub mixture_reduce_s: Option<f64>,
}

/// One per-level embeddings file ([`FormOutputs::levels`]).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LevelOutput {
    /// File size, bytes.
    pub bytes: u64,
    /// Granularity level (0 subpart, 1 part, 2 whole).
    pub level: usize,
    /// Gaussians with an embedding at this level.
    pub observed: usize,
    /// The file.
    pub path: PathBuf,
}

/// How a cluster encode's work was shared ([`Outputs::cluster`]).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct ClusterOutputs {
    /// One entry per reduce partition.
    pub partitions: Vec<ClusterPartition>,
    /// Processes (= partitions = map workers).
    pub processes: usize,
    /// How [`StageTimings::reduce`] is measured for a cluster.
    pub reduce_timing: String,
    /// Views no process encoded because every partition's checkpoint held them (a resumed
    /// job; 0 otherwise).
    pub views_resumed: u64,
    /// One entry per map worker.
    pub workers: Vec<ClusterWorker>,
}

/// One reduce partition of a cluster encode.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ClusterPartition {
    /// Bytes of the largest checkpoint it wrote.
    pub checkpoint_bytes: u64,
    /// Seconds writing its checkpoints, in all.
    pub checkpoint_s: f64,
    /// Checkpoints it wrote during this run.
    pub checkpoints: u64,
    /// Non-zero `a_kj` it reduced.
    pub entries: u64,
    /// Image parts it received.
    pub images: u64,
    /// Gaussians of the partition with an embedding.
    pub observed: u64,
    /// Partition index (Gaussians `k ≡ partition mod processes`).
    pub partition: u32,
    /// Chunks of its reduction.
    pub reduce_chunks: u64,
    /// Seconds of its reduction.
    pub reduce_s: f64,
    /// Image parts spilled to disk.
    pub spilled_images: u64,
    /// Views restored from its checkpoint (`0..views_restored`; 0 for a fresh partition).
    pub views_restored: u64,
}

/// One map worker of a cluster encode.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ClusterWorker {
    /// Non-zero `a_kj` of its images.
    pub entries: u64,
    /// Images it mapped.
    pub images: u64,
    /// Wall-clock seconds of its map loop.
    pub map_wall_s: f64,
    /// Masks of its images.
    pub masks: u64,
    /// The views it mapped (indices into the chosen views), in the order it mapped them: each
    /// process takes the next view nobody has taken when it finishes one.
    pub views: Vec<u32>,
    /// Worker (= process) index.
    pub worker: u32,
}

/// A markdown table of per-stage times from a run report (`slag-encoder bench`'s output).
pub fn timing_table(r: &Report) -> String {
    let t = &r.timings;
    let n = r.counts.views_used.max(1) as f64;
    let rows = [
        ("models set up (before the total)", t.models, false),
        ("load scene", t.load_scene, false),
        ("decode", t.decode, true),
        ("masks", t.masks, true),
        ("CLIP crops", t.clip, true),
        ("raster", t.raster, true),
        ("a_kj (image stage)", t.image_aggregate, true),
        ("reduce (E_k)", t.reduce, false),
        ("write", t.write, false),
        ("total (wall)", t.total, false),
    ];
    let mut s = String::from("| stage | seconds | ms / image |\n|---|---:|---:|\n");
    for (name, secs, per_image) in rows {
        let per = if per_image {
            format!("{:.1}", 1000.0 * secs / n)
        } else {
            "".into()
        };
        s += &format!("| {name} | {secs:.3} | {per} |\n");
    }
    let or_unknown = |s: &str| {
        if s.is_empty() {
            "?".to_string()
        } else {
            s.to_string()
        }
    };
    s += &format!(
        "\nviews {} | Gaussians {} | observed {} ({:.1}%) | masks {} ({:.1} / image) | a_kj entries {} | contributors/pixel {:.1} | rasterizer {} | masks {}\n",
        r.counts.views_used,
        r.counts.gaussians,
        r.counts.observed,
        100.0 * r.counts.observed_fraction,
        r.counts.masks,
        r.counts.masks as f64 / r.counts.views_used.max(1) as f64,
        r.counts.entries,
        r.counts.contributors_per_pixel,
        or_unknown(&r.models.rasterizer),
        or_unknown(&r.models.masks),
    );
    if let Some(b) = r.counts.peak_rss_bytes {
        s += &format!(
            "peak resident memory {:.2} GiB\n",
            b as f64 / (1u64 << 30) as f64
        );
    }
    if let Some(q) = &r.counts.queue {
        s += &format!(
            "between the stages: at most {} images ({:.1} MiB) of {} slots, largest image {:.2} MiB\n",
            q.high_water_items,
            q.high_water_bytes as f64 / (1u64 << 20) as f64,
            q.capacity_items,
            q.largest_item_bytes as f64 / (1u64 << 20) as f64
        );
    }
    if r.workers.len() > 2 {
        s += "\n| worker | images | busy s | busy % of wall |\n|---|---:|---:|---:|\n";
        for w in &r.workers {
            s += &format!(
                "| {} | {} | {:.1} | {:.0} |\n",
                w.name,
                w.images,
                w.busy_s,
                100.0 * w.busy_s / t.total.max(1e-9)
            );
        }
    }
    s
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
    /// front workers): where its per-image time goes (project, binning and sort on the GPU,
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

    /// `report.json` keeps the layout of the `serde_json::Value` sections it was built from
    /// before they were typed: the same keys and values, in the same (alphabetical) order, with
    /// the mode-specific keys absent (not `null`) in the other mode.
    #[test]
    fn sections_serialise_as_the_untyped_report_did() {
        use slag_common::onnx::ExecutionProvider as Ep;
        let header = |cluster: bool| Report {
            slag_version: "0.1.0".into(),
            inputs: Inputs {
                every: 2,
                hold_out_every: None,
                ply: "s/point_cloud.ply".into(),
                scene: "s".into(),
            },
            models: Models {
                clip_model_id: "color-clip-visual".into(),
                clip_visual: "c.onnx".into(),
                execution_provider: (!cluster).then_some(Ep::Cpu),
                execution_provider_requested: Ep::Auto,
                execution_providers: (!cluster).then(|| {
                    vec![ModelPlacement {
                        clip_batch: 32,
                        clip_visual: Ep::Cpu,
                        device: "cpu".into(),
                        gpu: None,
                        sam_decoder: None,
                        sam_encoder: None,
                    }]
                }),
                front_workers: (!cluster).then_some(2),
                masks: "graph".into(),
                rasterizer: "wgpu".into(),
                rasterizers: (!cluster).then(|| vec!["wgpu".into()]),
                sam_decoder: None,
                sam_encoder: None,
            },
            parameters: Parameters {
                cluster_addresses: cluster.then(|| vec!["h:1".into()]),
                cluster_processes: cluster.then_some(1),
                gpus: "Count(1)".into(),
                graph_k: Some(700.0),
                sam_pred_iou_thresh: f64::from(0.88f32),
                mask_weighting: crate::aggregate::MaskWeighting::None,
                min_weight: 1e-6,
                overlap: crate::aggregate::MaskOverlap::Finest,
                raster_scale: 0.5,
                threads: 2,
                ..Default::default()
            },
            outputs: Outputs {
                cluster: cluster.then(|| ClusterOutputs {
                    partitions: vec![ClusterPartition {
                        entries: 5,
                        images: 3,
                        observed: 4,
                        partition: 0,
                        reduce_chunks: 1,
                        reduce_s: 0.25,
                        spilled_images: 0,
                        views_restored: 2,
                        checkpoints: 1,
                        checkpoint_s: 0.5,
                        checkpoint_bytes: 4096,
                    }],
                    processes: 1,
                    reduce_timing: "slowest".into(),
                    views_resumed: 1,
                    workers: vec![ClusterWorker {
                        entries: 5,
                        images: 3,
                        map_wall_s: 1.5,
                        masks: 7,
                        views: vec![1, 2, 4],
                        worker: 0,
                    }],
                }),
                embeddings: Some("o/embeddings.safetensors".into()),
                embeddings_bytes: 1000,
                forms: (!cluster).then(|| FormOutputs {
                    levels: Some(vec![LevelOutput {
                        bytes: 10,
                        level: 1,
                        observed: 3,
                        path: "o/embeddings-level1.safetensors".into(),
                    }]),
                    levels_reduce_s: Some(0.5),
                    ..Default::default()
                }),
                precision: StoredPrecision::F16,
                report: "o/report.json".into(),
            },
            ..Default::default()
        };
        // The sections as the untyped code built them (`serde_json::json!`: sorted keys).
        let untyped = |cluster: bool| {
            let mut models = serde_json::json!({
                "sam_encoder": null, "sam_decoder": null, "clip_visual": "c.onnx",
                "execution_provider_requested": "auto",
                "rasterizer": "wgpu", "clip_model_id": "color-clip-visual", "masks": "graph",
            });
            let mut parameters = serde_json::json!({
                "raster_scale": 0.5, "sam_points_per_side": 0, "sam_points_per_batch": null,
                "sam_pred_iou_thresh": 0.88f32, "sam_stability_score_thresh": 0.0,
                "sam_box_nms_thresh": 0.0, "graph_k": 700.0f32, "graph_min_size": null,
                "clip_batch": null, "crop_fill": "before-resize", "top_k_per_pixel": null,
                "mask_weighting": "none",
                "overlap": "finest", "mask_erode": 0, "levels": false, "min_weight": 1e-6, "mixture_keep": null,
                "threads": 2, "gpus": "Count(1)", "front_workers": null,
            });
            let outputs = if cluster {
                let p = parameters.as_object_mut().unwrap();
                p.insert("cluster_processes".into(), 1.into());
                p.insert("cluster_addresses".into(), vec!["h:1"].into());
                serde_json::json!({
                    "embeddings": "o/embeddings.safetensors", "embeddings_bytes": 1000,
                    "precision": "f16", "report": "o/report.json",
                    "cluster": {
                        "processes": 1,
                        "workers": [{"worker": 0, "images": 3, "map_wall_s": 1.5, "masks": 7,
                                     "entries": 5, "views": [1, 2, 4]}],
                        "partitions": [{"partition": 0, "observed": 4, "images": 3,
                                        "entries": 5, "reduce_s": 0.25, "reduce_chunks": 1,
                                        "spilled_images": 0, "views_restored": 2,
                                        "checkpoints": 1, "checkpoint_s": 0.5,
                                        "checkpoint_bytes": 4096}],
                        "reduce_timing": "slowest",
                        "views_resumed": 1,
                    },
                })
            } else {
                let m = models.as_object_mut().unwrap();
                m.insert("execution_provider".into(), "cpu".into());
                m.insert(
                    "execution_providers".into(),
                    serde_json::json!([{"device": "cpu", "sam_encoder": null,
                        "sam_decoder": null, "clip_visual": "cpu", "clip_batch": 32}]),
                );
                m.insert("rasterizers".into(), vec!["wgpu"].into());
                m.insert("front_workers".into(), 2.into());
                serde_json::json!({
                    "embeddings": "o/embeddings.safetensors", "embeddings_bytes": 1000,
                    "precision": "f16", "report": "o/report.json",
                    "mixture": null, "mixture_keep": null, "mixture_codebook_rows": null,
                    "mixture_bytes_per_gaussian": null, "mixture_reduce_s": null,
                    "levels": [{"level": 1, "path": "o/embeddings-level1.safetensors",
                                "observed": 3, "bytes": 10}],
                    "levels_reduce_s": 0.5,
                })
            };
            (
                serde_json::json!({"scene": "s", "ply": "s/point_cloud.ply", "every": 2}),
                models,
                parameters,
                outputs,
            )
        };
        for cluster in [false, true] {
            let r = header(cluster);
            let (inputs, models, parameters, outputs) = untyped(cluster);
            for (name, typed, old) in [
                ("inputs", serde_json::to_string(&r.inputs), inputs),
                ("models", serde_json::to_string(&r.models), models),
                (
                    "parameters",
                    serde_json::to_string(&r.parameters),
                    parameters,
                ),
                ("outputs", serde_json::to_string(&r.outputs), outputs),
            ] {
                assert_eq!(
                    typed.unwrap(),
                    serde_json::to_string(&old).unwrap(),
                    "{name}, cluster {cluster}"
                );
            }
        }
    }
}
