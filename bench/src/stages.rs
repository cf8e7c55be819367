//! `slag-bench stages`: each encoder stage's measured time per image against its floor,
//! on the machine it runs on.
//!
//! The run: one `slag-encoder encode` with the given arguments (in process), then the GPU weight
//! rasterizer alone over `--raster-views` views for the phase breakdown of its per-pixel-list
//! path
//! ([`slag_encoder::raster::PhaseTimings`]). The floors come from a facts file measured on the same
//! machine by `scripts/lab/device_facts.py` (matrix rate, copy bandwidths, each ONNX model's FLOPs)
//! and, optionally, the torch timing of the same CLIP model from `scripts/lab/device_clip_vs_torch.py`.
//!
//! A stage's floor is its work at the machine's measured ceiling: FLOPs at the fp16 matrix rate
//! (SAM, CLIP: what the model would take on the GPU with perfect kernels), bytes at a measured
//! bandwidth (raster: GPU memory traffic plus what is read back over PCIe — the per-pixel lists
//! with top-K, only the per-(Gaussian, label) sums otherwise, whose size is approximated by the
//! `a_kj` count; `a_kj` and the reduction: host memory). Stages without a work model (JPEG decode, the
//! graph segmenter) show their time only. Times are busy seconds summed over workers divided by
//! images (the report's convention), so a stage's "ms / image" is its cost, not the wall clock.

use std::path::{Path, PathBuf};

use anyhow::Context;
use slag_common::table::Table;
use slag_encoder::config::{EncodeConfig, MaskSource};
use slag_encoder::pipeline::Encoder;
use slag_encoder::raster::{GpuRasterizer, WeightRasterizer, raster_intrinsics};
use slag_encoder::report::Report;

use slag_encoder::args::EncodeArgs;

/// Arguments of `slag-bench stages`: the encode arguments plus where the floors come from.
#[derive(Debug, Clone, clap::Args)]
pub struct StagesArgs {
    /// The encode run that is timed (same flags as `slag-encoder encode`).
    #[command(flatten)]
    pub encode: EncodeArgs,
    /// Facts of this machine (JSON from `scripts/lab/device_facts.py`: rates and model FLOPs).
    #[arg(long)]
    pub facts: PathBuf,
    /// torch timing of the CLIP model (JSON from `scripts/lab/device_clip_vs_torch.py`), if measured.
    #[arg(long)]
    pub torch: Option<PathBuf>,
    /// Views rasterized alone (evenly spaced) for the raster phase breakdown; 0 skips it.
    #[arg(long, default_value_t = 8)]
    pub raster_views: usize,
    /// Markdown file the tables are written to.
    #[arg(long)]
    pub table: PathBuf,
}

/// Rates and model sizes measured on the machine (`scripts/lab/device_facts.py`'s output).
#[derive(Debug, Clone, serde::Deserialize)]
pub struct Facts {
    /// GPU name (torch).
    pub gpu: String,
    /// Host cores.
    pub host_cores: usize,
    /// Dense fp16 matrix product rate, TFLOP/s (2 FLOP per multiply-add).
    pub matmul_tflops_fp16: f64,
    /// Dense fp32 (TF32 off) matrix product rate, TFLOP/s.
    pub matmul_tflops_fp32: f64,
    /// Device-to-device copy, GB/s counting bytes read and written.
    pub gpu_copy_gbps: f64,
    /// GPU to pinned host memory, GB/s.
    pub d2h_gbps: f64,
    /// Host-to-host copy on all cores, GB/s counting bytes read and written.
    pub host_copy_gbps: f64,
    /// Host-to-host copy on one thread, GB/s counting bytes read and written.
    pub host_copy_1t_gbps: f64,
    /// FLOPs of one batch-1 inference per ONNX model, keyed by file name.
    #[serde(default)]
    pub models: std::collections::BTreeMap<String, ModelFacts>,
}

/// One ONNX model's size in FLOPs.
#[derive(Debug, Clone, serde::Deserialize)]
pub struct ModelFacts {
    /// GFLOP of one inference at batch 1 (SAM decoder: one point prompt).
    pub gflop: f64,
}

/// torch timing of a CLIP visual tower (`scripts/lab/device_clip_vs_torch.py`'s JSON).
#[derive(Debug, Clone, serde::Deserialize)]
pub struct TorchClip {
    /// File name of the ONNX export of the same model.
    pub model: String,
    /// Batch size timed.
    pub batch: usize,
    /// torch fp16, ms per batch.
    pub fp16_ms: f64,
    /// torch fp32, ms per batch.
    pub fp32_ms: f64,
    /// ONNX Runtime (CPU EP, all cores), ms per batch.
    pub ort_cpu_ms: f64,
}

/// Mean phase times of the GPU rasterizer, ms per view, and the entries it wrote.
#[derive(Debug, Clone, Default)]
pub struct RasterPhases {
    /// Views timed.
    pub views: usize,
    /// Projection kernel, tile-count scan and the total's readback.
    pub project_ms: f64,
    /// Tile binning and depth sort, host side (sort depths, recording the GPU passes).
    pub bin_sort_ms: f64,
    /// Count pass, prefix sum, offsets readback.
    pub count_scan_ms: f64,
    /// Write pass(es) + weights readback.
    pub write_ms: f64,
    /// Whole `rasterize` call.
    pub total_ms: f64,
    /// Mean (Gaussian, weight) entries per view.
    pub entries: f64,
    /// Mean pixels per view.
    pub pixels: f64,
}

/// One row of the stage table.
#[derive(Debug, Clone)]
pub struct StageRow {
    /// Stage name.
    pub stage: String,
    /// Where it ran (CPU/GPU, runtime).
    pub runs_on: String,
    /// Measured busy ms per image.
    pub ms_per_image: f64,
    /// The work model, human readable (e.g. "57 crops × 35.1 GFLOP").
    pub work: String,
    /// The ceiling the floor uses, human readable.
    pub ceiling: String,
    /// Floor, ms per image (None: no work model).
    pub floor_ms: Option<f64>,
}

fn read_json<T: serde::de::DeserializeOwned>(p: &Path, what: &str) -> anyhow::Result<T> {
    let bytes = std::fs::read(p).with_context(|| format!("reading the {what} {}", p.display()))?;
    serde_json::from_slice(&bytes).with_context(|| {
        format!(
            "{} is not a {what} JSON (make it with the script named in `slag-bench stages --help`)",
            p.display()
        )
    })
}

fn file_name(p: &Path) -> String {
    p.file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default()
}

/// Rasterizes `n` evenly spaced views of the encode's scene alone and averages the phases.
///
/// Errors: no GPU adapter, unreadable scene.
pub fn raster_phases(a: &EncodeConfig, n: usize) -> anyhow::Result<RasterPhases> {
    let g = slag_common::scene::load_ply(&a.ply(), Default::default())?;
    let views = slag_common::camera::subsample(
        slag_common::camera::load_views(&a.scene.dir)?,
        a.scene.every,
    );
    if views.is_empty() || n == 0 {
        return Ok(RasterPhases::default());
    }
    let mut r = GpuRasterizer::new(&g)?;
    let k0 = raster_intrinsics(&views[0].intrinsics, a.raster.scale)?;
    r.rasterize(&k0, &views[0].world_to_camera)?; // warm-up: pipelines, allocations
    let mut p = RasterPhases::default();
    let n = n.min(views.len());
    for i in 0..n {
        let v = &views[i * views.len() / n];
        let k = raster_intrinsics(&v.intrinsics, a.raster.scale)?;
        let t = std::time::Instant::now();
        let w = r.rasterize(&k, &v.world_to_camera)?;
        p.total_ms += t.elapsed().as_secs_f64() * 1e3;
        let ph = r.last_timings();
        p.project_ms += ph.project_ms;
        p.bin_sort_ms += ph.bin_sort_ms;
        p.count_scan_ms += ph.count_scan_ms;
        p.write_ms += ph.write_ms;
        p.entries += w.ids.len() as f64;
        p.pixels += f64::from(w.width) * f64::from(w.height);
    }
    let nf = n as f64;
    for x in [
        &mut p.project_ms,
        &mut p.bin_sort_ms,
        &mut p.count_scan_ms,
        &mut p.write_ms,
        &mut p.total_ms,
        &mut p.entries,
        &mut p.pixels,
    ] {
        *x /= nf;
    }
    p.views = n;
    Ok(p)
}

/// Bytes per Gaussian the projection kernel reads (mean + opacity 16, scales 12, rotation 16)
/// and writes (2D mean, conic, opacity, depth, tile rect: 32) — see `raster/weights.wgsl`.
const PROJECT_BYTES_PER_GAUSSIAN: f64 = 16.0 + 12.0 + 16.0 + 32.0;
/// Bytes per (Gaussian, weight) entry written by the blend pass and read back (u32 id + f32).
const ENTRY_BYTES: f64 = 8.0;
/// Bytes per slot of the GPU label-sum table (Gaussian, label, 64-bit sum), read back per sum.
const LABEL_SLOT_BYTES: f64 = 16.0;
/// Bytes per sparse `a_kj` record handed to the reduction (u32 Gaussian, u32 mask, f32 weight).
const AKJ_BYTES: f64 = 12.0;

/// What every stage row of one encode reads: its settings, its report, the machine's facts.
struct StageInputs<'a> {
    a: &'a EncodeConfig,
    r: &'a Report,
    facts: &'a Facts,
    /// Views used (at least 1).
    n: f64,
    /// Where the models ran (the report's resolved provider, not the request).
    ort: String,
}

impl StageInputs<'_> {
    /// Seconds over the run → ms per image.
    fn per(&self, s: f64) -> f64 {
        1e3 * s / self.n
    }

    /// GFLOP per run of the model file `p`, when the facts file has it.
    fn gflop(&self, p: &Option<PathBuf>) -> Option<f64> {
        p.as_ref()
            .and_then(|p| self.facts.models.get(&file_name(p)))
            .map(|m| m.gflop)
    }

    /// The fp16 matmul ceiling, as text.
    fn fp16_ceiling(&self) -> String {
        format!(
            "GPU fp16 matmul {:.0} TFLOP/s",
            self.facts.matmul_tflops_fp16
        )
    }

    /// ms for `gflop` GFLOP at the fp16 matmul ceiling.
    fn fp16_floor_ms(&self, gflop: f64) -> f64 {
        gflop * 1e9 / (self.facts.matmul_tflops_fp16 * 1e12) * 1e3
    }
}

/// The stage rows of a finished encode: measured ms per image and floors from `facts`.
///
/// `phases` gives the entries and pixels per view (from [`raster_phases`] at the same raster
/// scale); with `phases.views == 0` they are estimated from the report's contributors per pixel.
pub fn stage_rows(
    a: &EncodeConfig,
    r: &Report,
    facts: &Facts,
    phases: &RasterPhases,
    image_pixels: f64,
) -> Vec<StageRow> {
    let ort = match r.models.execution_provider {
        Some(ep) if ep != slag_common::onnx::ExecutionProvider::Cpu => {
            let fronts = r.models.front_workers.unwrap_or(1);
            format!("ORT {ep} EP, one session per GPU shared by {fronts} front workers")
        }
        _ => format!("ORT CPU EP, {} cores", facts.host_cores),
    };
    let x = StageInputs {
        a,
        r,
        facts,
        n: r.counts.views_used.max(1) as f64,
        ort,
    };
    let decode = StageRow {
        stage: "decode".into(),
        runs_on: "CPU (image crate), one image per worker".into(),
        ms_per_image: x.per(r.timings.decode),
        work: format!("{:.1} MB RGB8 written", image_pixels * 3.0 / 1e6),
        ceiling: format!("host copy 1 thread {:.1} GB/s", facts.host_copy_1t_gbps),
        floor_ms: Some(image_pixels * 3.0 / (facts.host_copy_1t_gbps * 1e9) * 1e3),
    };
    let [raster, akj] = raster_rows(&x, phases, image_pixels);
    vec![
        decode,
        masks_row(&x),
        clip_row(&x),
        raster,
        akj,
        reduce_row(&x),
    ]
}

/// The masks row: SAM's FLOP floor when the facts file has both its models, else no floor.
fn masks_row(x: &StageInputs<'_>) -> StageRow {
    let (a, r) = (x.a, x.r);
    let sam = a.masks.source == MaskSource::Sam;
    match (x.gflop(&a.masks.sam.encoder), x.gflop(&a.masks.sam.decoder)) {
        (Some(enc), Some(dec)) if sam => {
            let points = f64::from(a.masks.sam.points_per_side).powi(2);
            let work = enc + dec * points;
            StageRow {
                stage: "masks (SAM)".into(),
                runs_on: x.ort.clone(),
                ms_per_image: x.per(r.timings.masks),
                work: format!(
                    "encoder {enc:.2} + {points:.0} points × {dec:.3} GFLOP = {work:.1} GFLOP"
                ),
                ceiling: x.fp16_ceiling(),
                floor_ms: Some(x.fp16_floor_ms(work)),
            }
        }
        _ => StageRow {
            stage: format!(
                "masks ({})",
                if r.models.masks.is_empty() {
                    "graph"
                } else {
                    &r.models.masks
                }
            ),
            runs_on: if sam { x.ort.clone() } else { "CPU".into() },
            ms_per_image: x.per(r.timings.masks),
            work: if sam {
                "SAM model not in the facts file: no FLOP count".into()
            } else {
                "no FLOP model (graph segmentation)".into()
            },
            ceiling: "-".into(),
            floor_ms: None,
        },
    }
}

/// The CLIP row: crops per image × the visual tower's GFLOP at the fp16 ceiling.
fn clip_row(x: &StageInputs<'_>) -> StageRow {
    let crops = x.r.counts.masks as f64 / x.n;
    let ms_per_image = x.per(x.r.timings.clip);
    match x.gflop(&Some(x.a.clip.visual.clone())) {
        Some(g) => StageRow {
            stage: "CLIP crops".into(),
            runs_on: x.ort.clone(),
            ms_per_image,
            work: format!("{crops:.1} crops × {g:.3} GFLOP"),
            ceiling: x.fp16_ceiling(),
            floor_ms: Some(x.fp16_floor_ms(crops * g)),
        },
        None => StageRow {
            stage: "CLIP crops".into(),
            runs_on: x.ort.clone(),
            ms_per_image,
            work: format!("{crops:.1} crops (model not in the facts file)"),
            ceiling: "-".into(),
            floor_ms: None,
        },
    }
}

/// The raster row (GPU traffic and readback) and the host side of the image stage, on the path
/// the report says the views took: GPU sums per (Gaussian, label), or per-pixel lists read back.
fn raster_rows(x: &StageInputs<'_>, phases: &RasterPhases, image_pixels: f64) -> [StageRow; 2] {
    let (a, r, facts) = (x.a, x.r, x.facts);
    let c = &r.counts;
    let (entries, pixels) = if phases.views > 0 {
        (phases.entries, phases.pixels)
    } else {
        let px = image_pixels * a.raster.scale * a.raster.scale;
        (px * c.contributors_per_pixel, px)
    };
    // The report says whether the GPU summed per (Gaussian, label) (only the sums come back) or
    // the per-pixel lists were read back (top-K, or a view the GPU declined).
    let label_path = c.device_sum_views * 2 > c.views_used;
    let akj_per_image = c.entries as f64 / x.n;
    let (raster_stage, raster_work, gpu_bytes, readback, akj_stage, akj_work, akj_bytes) =
        if label_path {
            let readback = akj_per_image * LABEL_SLOT_BYTES;
            let host_bytes = pixels * 4.0 + akj_per_image * AKJ_BYTES;
            (
                "raster + a_kj sums (GPU)",
                format!(
                    "{:.1} M contributions summed on the GPU; ≈{:.1} MB of sums read back",
                    entries / 1e6,
                    readback / 1e6
                ),
                c.gaussians as f64 * PROJECT_BYTES_PER_GAUSSIAN + pixels * 4.0,
                readback,
                "a_kj host side (labels, expansion)",
                format!("{:.1} MB of labels and a_kj written", host_bytes / 1e6),
                host_bytes,
            )
        } else {
            let gpu_bytes = c.gaussians as f64 * PROJECT_BYTES_PER_GAUSSIAN + entries * ENTRY_BYTES;
            let readback = entries * ENTRY_BYTES + (pixels + 1.0) * 4.0;
            let akj_bytes = entries * ENTRY_BYTES;
            (
                "raster (weights)",
                format!(
                    "{:.1} MB GPU traffic + {:.1} MB read back ({:.1} M entries)",
                    gpu_bytes / 1e6,
                    readback / 1e6,
                    entries / 1e6
                ),
                gpu_bytes,
                readback,
                "a_kj (image stage)",
                format!("{:.1} MB of weights read", akj_bytes / 1e6),
                akj_bytes,
            )
        };
    let raster = StageRow {
        stage: format!(
            "{raster_stage} [GPU sums on {} of {} views]",
            c.device_sum_views, c.views_used
        ),
        runs_on: if r.models.rasterizer.is_empty() {
            "wgpu".to_string()
        } else {
            r.models.rasterizer.clone()
        },
        ms_per_image: x.per(r.timings.raster),
        work: raster_work,
        ceiling: format!(
            "GPU copy {:.0} GB/s + D2H {:.1} GB/s",
            facts.gpu_copy_gbps, facts.d2h_gbps
        ),
        floor_ms: Some(
            (gpu_bytes / (facts.gpu_copy_gbps * 1e9) + readback / (facts.d2h_gbps * 1e9)) * 1e3,
        ),
    };
    let akj = StageRow {
        stage: akj_stage.into(),
        runs_on: "CPU (rayon)".into(),
        ms_per_image: x.per(r.timings.image_aggregate),
        work: akj_work,
        ceiling: format!("host copy {:.1} GB/s", facts.host_copy_gbps),
        floor_ms: Some(akj_bytes / (facts.host_copy_gbps * 1e9) * 1e3),
    };
    [raster, akj]
}

/// The reduction row: a_kj records and f64 accumulators touched once, over the whole run.
fn reduce_row(x: &StageInputs<'_>) -> StageRow {
    let (r, facts, n) = (x.r, x.facts, x.n);
    let c = &r.counts;
    let dim = embedding_dim(r);
    let reduce_bytes = c.entries as f64 * AKJ_BYTES + c.observed as f64 * dim * 8.0 * 2.0;
    StageRow {
        stage: "reduce (E_k), whole run / images".into(),
        runs_on: "CPU (rayon)".into(),
        ms_per_image: x.per(r.timings.reduce),
        work: format!(
            "{:.1} MB per image: a_kj records + f64 accumulators touched once",
            reduce_bytes / n / 1e6
        ),
        ceiling: format!("host copy {:.1} GB/s", facts.host_copy_gbps),
        floor_ms: Some(reduce_bytes / n / (facts.host_copy_gbps * 1e9) * 1e3),
    }
}

/// The stage table: one row per [`StageRow`], with its floor and measured / floor.
fn stage_table(rows: &[StageRow]) -> Table {
    let mut t = Table::with_header("stage | runs on | ms / image | work / image | ceiling | floor ms / image | measured / floor")
    .right([2, 5, 6]);
    for row in rows {
        let (floor, frac) = match row.floor_ms {
            Some(f) => (
                format!("{f:.3}"),
                format!("{:.1}", row.ms_per_image / f.max(1e-12)),
            ),
            None => ("-".into(), "-".into()),
        };
        t.row([
            row.stage.clone(),
            row.runs_on.clone(),
            format!("{:.1}", row.ms_per_image),
            row.work.clone(),
            row.ceiling.clone(),
            floor,
            frac,
        ]);
    }
    t
}

/// Markdown of the stage table, the raster phases and the torch comparison.
pub fn markdown(
    a: &EncodeConfig,
    r: &Report,
    facts: &Facts,
    rows: &[StageRow],
    phases: &RasterPhases,
    torch: Option<&TorchClip>,
    command: &str,
) -> String {
    let mut s = format!(
        "# Encoder stages against their floors\n\n`{command}`\n\nMachine: {} ({} host cores); \
         measured there: fp16 matmul {:.0} TFLOP/s, fp32 {:.1} TFLOP/s, GPU copy {:.0} GB/s, \
         D2H {:.1} GB/s, host copy {:.1} GB/s ({:.1} on one thread).\n\n\
         Scene: {} views of {} used, {} Gaussians ({} observed), {} masks, raster scale {}, \
         {} front workers; wall {:.1} s.\n\n",
        facts.gpu,
        facts.host_cores,
        facts.matmul_tflops_fp16,
        facts.matmul_tflops_fp32,
        facts.gpu_copy_gbps,
        facts.d2h_gbps,
        facts.host_copy_gbps,
        facts.host_copy_1t_gbps,
        r.counts.views_used,
        r.counts.views_total,
        r.counts.gaussians,
        r.counts.observed,
        r.counts.masks,
        a.raster.scale,
        r.models
            .front_workers
            .map_or_else(|| "?".to_string(), |f| f.to_string()),
        r.timings.total,
    );
    s += &stage_table(rows).markdown();
    if phases.views > 0 {
        s += &format!(
            "\nRaster phases of the per-pixel-list path (top-K), the rasterizer alone over {} views (ms / view): projection {:.1}, \
             binning + depth sort (host side) {:.1}, count + prefix sum {:.1}, write + readback \
             {:.1}; whole call {:.1}. {:.2} M entries and {:.0} pixels per view.\n",
            phases.views,
            phases.project_ms,
            phases.bin_sort_ms,
            phases.count_scan_ms,
            phases.write_ms,
            phases.total_ms,
            phases.entries / 1e6,
            phases.pixels
        );
    }
    if let Some(tc) = torch {
        let crops = r.counts.masks as f64 / r.counts.views_used.max(1) as f64;
        let per_crop = |ms: f64| ms / tc.batch as f64;
        s += &format!(
            "\nCLIP model `{}` on this machine, ms per crop (batch {}): torch fp16 {:.3}, torch \
             fp32 {:.3}, ONNX Runtime CPU {:.3}; at {:.1} crops per image that is {:.1} / {:.1} / \
             {:.1} ms per image (slag measured {:.1}: ORT has no GPU execution provider on this \
             machine).\n",
            tc.model,
            tc.batch,
            per_crop(tc.fp16_ms),
            per_crop(tc.fp32_ms),
            per_crop(tc.ort_cpu_ms),
            crops,
            crops * per_crop(tc.fp16_ms),
            crops * per_crop(tc.fp32_ms),
            crops * per_crop(tc.ort_cpu_ms),
            rows.iter()
                .find(|r| r.stage == "CLIP crops")
                .map_or(0.0, |r| r.ms_per_image),
        );
    }
    s
}

/// Runs `slag-bench stages`: the encode, the raster phases, the floors; writes `--table`.
///
/// Errors: encode errors, an unreadable facts/torch file, no GPU for the raster phases.
pub fn run(a: &StagesArgs) -> anyhow::Result<String> {
    let facts: Facts = read_json(&a.facts, "device facts")?;
    let torch: Option<TorchClip> = match &a.torch {
        Some(p) => Some(read_json(p, "torch CLIP timing")?),
        None => None,
    };
    let config = EncodeConfig::from(&a.encode);
    let report = Encoder::new(config.clone())?.run()?;
    let phases = raster_phases(&config, a.raster_views)?;
    let views = slag_common::camera::load_views(&config.scene.dir)?;
    let image_pixels = views.first().map_or(0.0, |v| {
        f64::from(v.intrinsics.width) * f64::from(v.intrinsics.height)
    });
    let rows = stage_rows(&config, &report, &facts, &phases, image_pixels);
    let command = std::iter::once("slag-bench".to_string())
        .chain(std::env::args().skip(1))
        .collect::<Vec<_>>()
        .join(" ");
    let md = markdown(
        &config,
        &report,
        &facts,
        &rows,
        &phases,
        torch.as_ref(),
        &command,
    );
    slag_common::io::write_atomic(&a.table, md.as_bytes())?;
    Ok(md)
}

/// The embedding width D of `r`'s run: from the dense file's size (f16 rows) when it was written,
/// else from the mixture file's header; 0 when neither can be read.
fn embedding_dim(r: &Report) -> f64 {
    if r.outputs.embeddings_bytes > 0 {
        let rows = r.counts.observed.max(1) as f64;
        return (r.outputs.embeddings_bytes as f64 / (rows * 2.0)).round();
    }
    r.outputs
        .forms
        .as_ref()
        .and_then(|f| f.mixture.as_ref())
        .and_then(|p| slag_common::mixture::MixtureEmbeddings::read(p).ok())
        .map_or(0.0, |m| m.dim as f64)
}
