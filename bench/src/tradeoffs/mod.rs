//! The speed/accuracy trade study (`slag-bench tradeoffs`).
//!
//! On a real scene with color-clip (whose ground truth is known: a Gaussian's colour class is the
//! prototype nearest its SH-DC colour, [`slag_eval`]; a photo pixel's class is the
//! prototype nearest its colour), the study sweeps, one factor at a time around a baseline (graph
//! masks, every 4th image, raster scale 0.5, all contributors per pixel):
//!
//! - **encode**: mask source (graph vs color-sam on an 8/16/32 grid, compared at every 8th
//!   image), image subsampling (`--every` 1…20), raster scale (0.25…1.0), contributors kept per
//!   pixel (top-K 1…8 vs all), the `a_kj` rule on color-sam. Each point records encode wall time
//!   and per-stage times, observed Gaussians, its **held-out 2D mIoU** (the accuracy axis: the
//!   protocol of `eval-colors --held-out` on the views no point of the plan encodes, the same
//!   pixels for every point, [`heldout`]), the 3D colour mIoU beside it, the f32 scan latency of
//!   its embeddings, and its agreement with the **reference** run (graph, every image, raster
//!   0.5, all contributors: the costliest graph-mask configuration of the sweep): for each of
//!   color-clip's 12 colour prompts the set of Gaussians with cosine `>= 0.28`, IoU against the
//!   reference's set, averaged over the prompts whose union is non-empty (a prompt empty in both
//!   runs is left out; the count of prompts averaged is reported). The Pareto front of (encode
//!   seconds, held-out mIoU) is marked;
//! - **storage** (the baseline run's embeddings): f32, f16, int8 rows quantised exactly as the
//!   shards store them (`slag_edge::scan::VectorStore::push_f32_rows` = the shard codec), with
//!   bytes per Gaussian, exact-scan latency (median over prompts × repeats), colour mIoU from the
//!   dequantised rows, and IoU of the `>= 0.28` sets against the exact f32 answer;
//! - **index**: exact scan vs HNSW (`slag_edge::scan::hnsw`): build time, memory, top-k latency
//!   and top-k IoU against the exact scan;
//! - **footprint** ("model only what a scene requires"): a naive dense `N × D` f32 tensor over
//!   every Gaussian of the `.ply` against what slag stores (observed rows only, f16 file, shards
//!   at f32/f16/int8 with their count and sizes).
//!
//! Outputs: `OUT/tradeoffs.csv` (one row per point, every column filled; `na` for the colour
//! mIoU of an index point, which returns top-k lists, not a class per Gaussian, and for the
//! held-out mIoU of storage and index points and of a point that encoded every view) and
//! `OUT/tradeoffs.md` (header with the command and machine, one table row per CSV row, the
//! footprint table; the hand-written text below its recommendations marker survives a new run,
//! [`output::keep_hand_written`]). Encode runs are cached under `--work` (a rerun with the same arguments reuses
//! them; `--fresh` re-encodes).

pub mod encode;
pub mod heldout;
pub mod mixture;
pub mod output;
pub mod sets;
pub mod storage;

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use clap::Args;
use slag_common::embeddings::Embeddings;
use slag_common::scene::{self, Gaussians, PlyLoadOptions};
use slag_common::text::TextEncoder;
use slag_encoder::report::StageTimings;
use slag_eval as eval;

pub use encode::{Aggregation, EncodePoint, EncodeRecord, MaskChoice};

/// Arguments of `slag-bench tradeoffs`.
#[derive(Debug, Clone, Args)]
pub struct TradeoffArgs {
    /// Scene folder (point_cloud.ply, images/, sparse/0). Default: <shared>/scenes/snowmiku, or
    /// data/snowmiku-mini with --quick.
    #[arg(long = "scene-dir", value_name = "DIR")]
    pub scene: Option<PathBuf>,
    /// Output folder for tradeoffs.md and tradeoffs.csv (e.g. docs/results/).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Small study for tests: 3 encode points (reference, baseline, raster 0.25), every storage
    /// and index point, fewer repeats.
    #[arg(long)]
    pub quick: bool,
    /// Work folder for the encode runs (cached by arguments). Default:
    /// target/slag-bench/<scene folder name>[-quick].
    #[arg(long)]
    pub work: Option<PathBuf>,
    /// Re-encode every point even when the work folder holds a run with the same arguments.
    #[arg(long, conflicts_with = "cached_only")]
    pub fresh: bool,
    /// Keep every point's f32 embeddings (default: only the baseline's; the others are removed
    /// once evaluated, their results cached in eval.json).
    #[arg(long)]
    pub keep_embeddings: bool,
    /// With --cached-only, still encode these points (ids as in the tables, comma-separated).
    #[arg(long, value_delimiter = ',')]
    pub encode: Vec<String>,
    /// Encode nothing: use only the points the work folder already holds (a study cut short);
    /// the header lists the points left out. The baseline and the reference must be there.
    #[arg(long)]
    pub cached_only: bool,
    /// Fixtures folder (sam-amg/, clip/). Default: <shared>/fixtures.
    #[arg(long)]
    pub fixtures: Option<PathBuf>,
    /// Worker counts of every encode of the sweep.
    #[command(flatten)]
    pub workers: encode::Workers,
    /// Timed repetitions of each prompt's scan (default 5, --quick 1).
    #[arg(long)]
    pub repeats: Option<usize>,
    /// Cosine threshold of a match (SLAG's 0.28).
    #[arg(long, default_value_t = 0.28)]
    pub threshold: f32,
    /// k of the exact-vs-HNSW comparison (top-k; default 1000, --quick 100).
    #[arg(long)]
    pub index_top_k: Option<usize>,
    /// HNSW ef_construction, candidates per insertion (default 100, --quick 40).
    #[arg(long)]
    pub hnsw_ef_construction: Option<usize>,
    /// Rows indexed by HNSW: every n-th row of the baseline's so that about this many remain
    /// (the exact scan it is compared with runs on the same rows); 0 = all. Default 20000
    /// (building over all of snowmiku's rows takes many minutes on 2 cores), --quick 1500.
    #[arg(long)]
    pub hnsw_rows: Option<usize>,
    /// Free text for the header (e.g. "2 cores shared with other builds").
    #[arg(long)]
    pub note: Option<String>,
}

/// One row of the study's CSV (and of its markdown tables).
#[derive(Debug, Clone, serde::Serialize)]
pub struct Row {
    /// `encode`, `storage` or `index`.
    pub section: String,
    /// Unique id of the point (encode: `graph-e4-r0.5-kall`; storage: `store-f16`, …).
    pub point: String,
    /// The knob varied (`baseline`, `reference`, `masks`, `every`, `raster`, `top-k`, `dtype`,
    /// `mixture`, `index`).
    pub knob: String,
    /// Mask source of the embeddings (`graph`, `sam16`, …).
    pub masks: String,
    /// `--every` of the embeddings.
    pub every: usize,
    /// `--raster-scale` of the embeddings.
    pub raster_scale: f64,
    /// Contributors kept per pixel (`all` or K).
    pub top_k: String,
    /// Stored form of the rows (`f32`, `f16`, `int8`, `mixture-S<k>`).
    pub storage: String,
    /// Query index (`scan` = exact, `hnsw`).
    pub index: String,
    /// Views encoded.
    pub views: usize,
    /// Observed (stored) Gaussians.
    pub observed: usize,
    /// Encode wall time, s (storage/index points: the baseline's).
    pub encode_s: f64,
    /// The encode's stage seconds (summed over images; storage/index points: the baseline's).
    /// The CSV's `decode_s` … `reduce_s` columns are `decode`, `masks`, `clip`, `raster`,
    /// `image_aggregate` and `reduce`.
    pub stages: StageTimings,
    /// Seconds to build the queried form from f32 rows (quantise, fit mixture, build HNSW).
    pub build_s: f64,
    /// Bytes per stored Gaussian in memory (vector + 4 B id + 12 B mean; HNSW adds its index).
    pub bytes_per_gaussian: f64,
    /// Median latency of one prompt's query, ms (threshold scan, or top-k for `index` points).
    pub query_ms: f64,
    /// Colour mIoU, the 3D score of each Gaussian's class (`None` for index points).
    pub colour_miou: Option<f64>,
    /// Held-out 2D mIoU on the study's held-out views ([`heldout`]); `None` for storage and
    /// index points and for a point that encoded every view.
    pub held_out_miou: Option<f64>,
    /// Agreement with the exact answer (see `iou_kind`): mean IoU over prompts of the matched
    /// sets; for index points the tie-aware top-k recall.
    pub iou: f64,
    /// Mean IoU over prompts of the answer sets as returned (equal to `iou` except for index
    /// points, where ties at the k-th score make the plain top-k set IoU understate agreement).
    pub set_iou: f64,
    /// What `iou` compares: `ref-run cos>=T` (encode), `f32 cos>=T` (storage), `f32 top-k`
    /// (index).
    pub iou_kind: String,
    /// Prompts averaged in `iou` (non-empty union).
    pub iou_prompts: usize,
}

/// Everything the evaluation of a set of embeddings needs, loaded once.
pub struct EvalContext {
    /// color-clip's classes (names = the 12 colour prompts).
    pub classes: eval::ColorClasses,
    /// Ground-truth class per scene Gaussian.
    pub gt: Vec<Option<u8>>,
    /// L2-normalised text embedding per class name, `[12][D]`.
    pub prompts: Vec<Vec<f32>>,
    /// Match threshold (cosine).
    pub threshold: f32,
    /// Gaussians in the scene's `.ply`.
    pub scene_gaussians: usize,
    /// The scene's Gaussians (the held-out renders rasterize them).
    pub gaussians: Gaussians,
}

impl EvalContext {
    /// Loads the classes, the scene's ground truth and the prompts' text embeddings (color-clip
    /// textual tower under `fixtures/clip`).
    ///
    /// Errors: missing fixtures or `.ply`, model errors.
    pub fn load(scene_dir: &Path, fixtures: &Path, threshold: f32) -> anyhow::Result<Self> {
        let clip = fixtures.join("clip");
        let classes = eval::ColorClasses::load(&clip.join("color-clip.json"))?;
        let g = scene::load_ply(
            &scene_dir.join("point_cloud.ply"),
            PlyLoadOptions { colours: true },
        )?;
        let gt = eval::ground_truth(&classes, &g)?;
        let mut text = TextEncoder::new(
            &clip.join("color-clip-textual.onnx"),
            &clip.join("clip-tokenizer.json"),
            slag_common::onnx::ExecutionProvider::Cpu,
        )?;
        let names: Vec<&str> = classes.names.iter().map(String::as_str).collect();
        let prompts = text.encode(&names).context("encoding the colour prompts")?;
        Ok(EvalContext {
            classes,
            scene_gaussians: g.len(),
            gt,
            prompts,
            threshold,
            gaussians: g,
        })
    }

    /// Colour mIoU of `emb` ([`eval::assign`] + [`eval::evaluate`]).
    ///
    /// Errors: embeddings of another scene or model width.
    pub fn colour_miou(&self, emb: &Embeddings) -> anyhow::Result<Option<f64>> {
        let predicted = eval::assign(emb, &self.prompts)?;
        Ok(eval::evaluate(&self.gt, emb, &predicted, &self.classes.names)?.miou)
    }
}

/// `--mixture-keep` of the mixture source (the baseline's settings; in `--quick` the baseline
/// itself): large enough to keep every atom of every Gaussian (the
/// mixture's `S` is then its longest row); the study's smaller `S` are cut from it.
pub const MIXTURE_KEEP_ALL: usize = 1 << 16;

/// Mixture slot counts of the storage sweep (plus `all`, the baseline's own mixture).
pub const MIXTURE_KEEPS: [usize; 5] = [1, 2, 4, 8, 16];

fn with_mixture(mut p: EncodePoint) -> EncodePoint {
    p.mixture_keep = Some(MIXTURE_KEEP_ALL);
    p
}

/// The encode points of the study: the full sweep, or the `--quick` one (on snowmiku-mini:
/// baseline every 6th image at raster 0.25, reference every 2nd image at raster 0.25, and top-K 1).
/// The full sweep is ordered so that the most informative points run first (a study cut short
/// with `--cached-only` still has them).
pub fn plan(quick: bool) -> Vec<EncodePoint> {
    let g = EncodePoint::graph;
    if quick {
        return vec![
            with_mixture(g("baseline", 6, 0.25, None)),
            g("reference", 2, 0.25, None),
            g("top-k", 6, 0.25, Some(1)),
        ];
    }
    let sam = |pps: u32| EncodePoint {
        knob: "masks".into(),
        masks: MaskChoice::Sam {
            points_per_side: pps,
        },
        every: 8,
        raster_scale: 0.5,
        top_k: None,
        mixture_keep: None,
        aggregation: encode::Aggregation::Mean,
    };
    // Aggregation variants on color-sam 16x16 at every 4th image.
    let aggregation = |a: encode::Aggregation| EncodePoint {
        knob: "aggregation".into(),
        every: 4,
        aggregation: a,
        ..sam(16)
    };
    // Mask sources at every 8th image (color-sam costs ~5 s per image at 16x16 on 2 cores).
    vec![
        g("baseline", 4, 0.5, None),
        g("reference", 1, 0.5, None),
        with_mixture(g("mixture", 4, 0.5, None)),
        g("every", 20, 0.5, None),
        g("every", 10, 0.5, None),
        g("every", 5, 0.5, None),
        g("every", 2, 0.5, None),
        g("raster", 4, 0.25, None),
        g("top-k", 4, 0.5, Some(1)),
        g("top-k", 4, 0.5, Some(8)),
        g("masks", 8, 0.5, None),
        sam(8),
        sam(16),
        g("raster", 4, 1.0, None),
        g("top-k", 4, 0.5, Some(2)),
        g("top-k", 4, 0.5, Some(4)),
        sam(32),
    ]
    .into_iter()
    .chain(encode::Aggregation::ALL.map(aggregation))
    .collect()
}

/// One encoded sweep point: its plan, run record and evaluation (colour and held-out mIoU, the
/// matched id set per colour prompt, the median scan latency of its f32 embeddings).
type EncodedPoint = (EncodePoint, EncodeRecord, encode::EvalRecord);

/// The evaluation of the point encoded into `dir` with step `every`: the cached one when it is
/// complete ([`encode::EvalRecord::is_complete`]) or the embeddings are gone (a study cut short
/// keeps what it has), else computed from `dir/embeddings.safetensors` (the parts already cached
/// are reused) and cached in `dir/eval.json`.
///
/// Errors: unreadable embeddings, embeddings of another scene or width, rasterizer failures.
fn evaluate_point(
    ctx: &EvalContext,
    held: &mut heldout::HeldOutViews,
    every: usize,
    dir: &Path,
    repeats: usize,
) -> anyhow::Result<encode::EvalRecord> {
    let emb_path = dir.join("embeddings.safetensors");
    let names = held.names();
    let cached = encode::cached_eval(dir, ctx.threshold);
    if let Some(e) = &cached
        && (e.is_complete(every, &names) || !emb_path.exists())
    {
        return Ok(e.clone());
    }
    let emb = Embeddings::read(&emb_path)?;
    let mut e = match cached {
        Some(e) => e,
        None => {
            let store = storage::store_of(&emb, slag_common::shards::Dtype::F32)?.0;
            let (scan_ms, _) = storage::scan_latency(&store, &ctx.prompts, ctx.threshold, repeats)?;
            encode::EvalRecord {
                threshold: ctx.threshold,
                colour_miou: ctx.colour_miou(&emb)?,
                scan_ms,
                sets: sets::threshold_sets(&emb, &ctx.prompts, ctx.threshold)?,
                held_out: None,
            }
        }
    };
    e.held_out = if every >= 2 {
        Some(encode::HeldOutRecord {
            score: held.score(&emb, &ctx.prompts)?,
            views: names,
        })
    } else {
        None
    };
    slag_common::io::write_atomic(&dir.join(encode::EVAL_FILE), &serde_json::to_vec(&e)?)?;
    Ok(e)
}

/// Where a study runs: its scene, fixtures and work folder, and its resolved settings.
struct Setup {
    scene: PathBuf,
    fixtures: PathBuf,
    work: PathBuf,
    repeats: usize,
    index_top_k: usize,
}

impl Setup {
    /// Resolves the defaults of `a` (`--quick`, `$SLAG_SHARED`) and creates the output folder.
    ///
    /// Errors: no `.ply` in the scene, `$SLAG_SHARED` needed and unset, unwritable `--out`.
    fn resolve(a: &TradeoffArgs) -> anyhow::Result<Self> {
        // `$SLAG_SHARED`, needed only for what --scene / --fixtures do not name.
        let shared = || slag_common::paths::shared_dir();
        let scene = match &a.scene {
            Some(s) => s.clone(),
            None if a.quick => PathBuf::from("data/snowmiku-mini"),
            None => shared()?.join("scenes").join("snowmiku"),
        };
        if !scene.join("point_cloud.ply").is_file() {
            anyhow::bail!(
                "{} holds no point_cloud.ply; pass --scene DIR (a scene with point_cloud.ply, images/, sparse/0)",
                scene.display()
            );
        }
        let fixtures = match &a.fixtures {
            Some(f) => f.clone(),
            None => shared()?.join("fixtures"),
        };
        let scene_name = scene
            .file_name()
            .map(|s| s.to_string_lossy().to_string())
            .unwrap_or_else(|| "scene".into());
        let work = a.work.clone().unwrap_or_else(|| {
            PathBuf::from("target").join("slag-bench").join(format!(
                "{scene_name}{}",
                if a.quick { "-quick" } else { "" }
            ))
        });
        std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
        Ok(Setup {
            scene,
            fixtures,
            work,
            repeats: a.repeats.unwrap_or(if a.quick { 1 } else { 5 }).max(1),
            index_top_k: a.index_top_k.unwrap_or(if a.quick { 100 } else { 1000 }),
        })
    }
}

/// The encode sweep's outcome: the points encoded (or reused) and evaluated, the points left
/// out (`--cached-only`) and the held-out majority-class baseline.
struct Sweep {
    encoded: Vec<EncodedPoint>,
    skipped: Vec<String>,
    majority_miou: Option<f64>,
}

/// 1. Encodes (or reuses) and evaluates every point of the plan.
///
/// Errors: encode and evaluation errors.
fn encode_sweep(
    a: &TradeoffArgs,
    su: &Setup,
    ctx: &EvalContext,
    held: &mut heldout::HeldOutViews,
    points: &[EncodePoint],
) -> anyhow::Result<Sweep> {
    let held_names = held.names();
    let mut sweep = Sweep {
        encoded: Vec::new(),
        skipped: Vec::new(),
        majority_miou: None,
    };
    for (i, p) in points.iter().enumerate() {
        let dir = encode::point_dir(&su.work, p);
        let config = p.encode_config(&su.scene, &su.fixtures, &a.workers, &dir);
        let emb_path = dir.join("embeddings.safetensors");
        let prior = (!a.fresh).then(|| encode::cached(&dir, &config)).flatten();
        let prior_eval = prior.as_ref().and_then(|_| {
            encode::cached_eval(&dir, ctx.threshold).filter(|e| e.is_complete(p.every, &held_names))
        });
        // The baseline's embeddings feed the storage sweep: it needs them on disk.
        let keep_emb = p.knob == "baseline" || p.mixture_keep.is_some();
        let need_emb = keep_emb || prior_eval.is_none();
        let usable = prior.is_some() && (!need_emb || emb_path.exists());
        let progress = format!("[{}/{}]", i + 1, points.len());
        if a.cached_only && !usable && !a.encode.contains(&p.id()) {
            eprintln!("{progress} {} not in the work folder: left out", p.id());
            sweep.skipped.push(format!("{} ({})", p.id(), p.knob));
            continue;
        }
        eprintln!("{progress} encode {} ({})", p.id(), p.knob);
        let (rec, cached) = match prior {
            Some(r) if usable => (r, true),
            _ => encode::run_point(p, &su.scene, &su.fixtures, &a.workers, &dir, true)?,
        };
        let ev = evaluate_point(ctx, held, p.every, &dir, su.repeats)?;
        if let Some(h) = &ev.held_out {
            sweep.majority_miou = sweep.majority_miou.or(h.score.majority_miou);
        }
        if !keep_emb && !a.keep_embeddings {
            std::fs::remove_file(&emb_path).ok();
        }
        eprintln!(
            "    {:.1} s{} | observed {} | held-out mIoU {:?} | 3D mIoU {:?} | scan {:.2} ms",
            rec.stages.total,
            if cached { " (cached)" } else { "" },
            rec.observed,
            ev.held_out.as_ref().and_then(|h| h.score.miou),
            ev.colour_miou,
            ev.scan_ms
        );
        sweep.encoded.push((p.clone(), rec, ev));
    }
    Ok(sweep)
}

/// The encode rows (every encoded point but the mixture source), scored against `reference`.
fn encode_rows(ctx: &EvalContext, encoded: &[EncodedPoint], reference: &EncodedPoint) -> Vec<Row> {
    encoded
        .iter()
        .filter(|e| e.0.knob != "mixture")
        .map(|(p, rec, ev)| {
            let (iou, n) = sets::mean_iou(&ev.sets, &reference.2.sets);
            Row {
                section: "encode".into(),
                point: p.id(),
                knob: p.knob.clone(),
                masks: p.masks.name(),
                every: p.every,
                raster_scale: p.raster_scale,
                top_k: p.top_k_name(),
                storage: "f32".into(),
                index: "scan".into(),
                views: rec.views,
                observed: rec.observed,
                encode_s: rec.stages.total,
                stages: rec.stages.clone(),
                build_s: 0.0,
                bytes_per_gaussian: storage::bytes_per_gaussian_of(
                    slag_common::shards::Dtype::F32,
                    ctx.prompts.first().map_or(0, Vec::len),
                ),
                query_ms: ev.scan_ms,
                colour_miou: ev.colour_miou,
                held_out_miou: ev.held_out.as_ref().and_then(|h| h.score.miou),
                iou,
                set_iou: iou,
                iou_kind: format!("ref-run cos>={}", ctx.threshold),
                iou_prompts: n,
            }
        })
        .collect()
}

/// 2. and 3. The storage, mixture and index rows on the baseline's embeddings (appended to
/// `rows`, whose baseline row is their template) and the footprint rows.
///
/// Errors: unreadable embeddings, quantisation or index errors.
fn storage_sweep(
    a: &TradeoffArgs,
    su: &Setup,
    ctx: &EvalContext,
    sweep: &Sweep,
    rows: &mut Vec<Row>,
) -> anyhow::Result<Vec<storage::FootprintRow>> {
    let baseline = sweep
        .encoded
        .iter()
        .find(|e| e.0.knob == "baseline")
        .context("the baseline point is not in the work folder; run it first")?;
    let mixture_dir = sweep
        .encoded
        .iter()
        .find(|e| e.0.mixture_keep.is_some())
        .map(|e| encode::point_dir(&su.work, &e.0));
    let base_dir = encode::point_dir(&su.work, &baseline.0);
    let base_emb = Embeddings::read(&base_dir.join("embeddings.safetensors"))?;
    let template = rows
        .iter()
        .find(|r| r.knob == "baseline")
        .cloned()
        .context("baseline row")?;
    let st = storage::StorageOptions {
        repeats: su.repeats,
        index_top_k: su.index_top_k,
        hnsw_ef_construction: a
            .hnsw_ef_construction
            .unwrap_or(if a.quick { 40 } else { 100 }),
        hnsw_rows: match a.hnsw_rows.unwrap_or(if a.quick { 1500 } else { 20_000 }) {
            0 => None,
            n => Some(n),
        },
    };
    rows.extend(storage::storage_rows(ctx, &base_emb, &template, &st)?);
    let mut mix_footprint = Vec::new();
    if let Some(dir) = &mixture_dir {
        // The mixture's exact f32 answer is its own run's dense embeddings (same observed set).
        let mix = slag_common::mixture::MixtureEmbeddings::read(&dir.join("mixture.safetensors"))?;
        let dense = if *dir == base_dir {
            base_emb.clone()
        } else {
            Embeddings::read(&dir.join("embeddings.safetensors"))?
        };
        let (mix_rows, fp) =
            mixture::mixture_rows(ctx, &dense, &mix, &MIXTURE_KEEPS, &template, su.repeats)?;
        rows.extend(mix_rows);
        mix_footprint = fp;
    }
    rows.extend(storage::index_rows(ctx, &base_emb, &template, &st)?);
    // 3. Footprint: what the scene requires vs a dense tensor.
    let mut footprint = storage::footprint(ctx, &su.scene, &base_emb, &su.work)?;
    footprint.extend(mix_footprint);
    Ok(footprint)
}

/// Runs the study and writes `OUT/tradeoffs.{md,csv}`; returns a short summary for the terminal.
///
/// Errors: missing scene or fixtures, any encode error, unwritable output folder.
pub fn run(a: &TradeoffArgs) -> anyhow::Result<String> {
    let t_start = Instant::now();
    let machine = crate::machine::MachineInfo::detect();
    let su = Setup::resolve(a)?;
    let ctx = EvalContext::load(&su.scene, &su.fixtures, a.threshold)?;
    let points = plan(a.quick);
    let everys: Vec<usize> = points.iter().map(|p| p.every).collect();
    let mut held = heldout::HeldOutViews::load(
        &su.scene,
        &ctx.gaussians,
        &ctx.classes,
        &everys,
        slag_encoder::config::RasterBackend::Gpu,
    )?;
    let sweep = encode_sweep(a, &su, &ctx, &mut held, &points)?;
    let reference = sweep
        .encoded
        .iter()
        .find(|e| e.0.knob == "reference")
        .context("the reference point (every image) is not in the work folder; run it first")?;
    let mut rows = encode_rows(&ctx, &sweep.encoded, reference);
    let footprint = storage_sweep(a, &su, &ctx, &sweep, &mut rows)?;

    // 4. Write.
    let command = std::iter::once("slag-bench".to_string())
        .chain(std::env::args().skip(1))
        .collect::<Vec<_>>()
        .join(" ");
    let header = output::Header {
        command,
        machine,
        note: a.note.clone(),
        scene: su.scene.display().to_string(),
        scene_gaussians: ctx.scene_gaussians,
        threshold: ctx.threshold,
        repeats: su.repeats,
        index_top_k: su.index_top_k,
        skipped: sweep.skipped,
        study_s: t_start.elapsed().as_secs_f64(),
        held_out_views: held.names(),
        majority_miou: sweep.majority_miou,
    };
    let csv = output::csv(&rows);
    let csv_path = a.out.join("tradeoffs.csv");
    let md_path = a.out.join("tradeoffs.md");
    let md = output::keep_hand_written(
        &output::markdown(&header, &rows, &footprint),
        std::fs::read_to_string(&md_path).ok().as_deref(),
    );
    slag_common::io::write_atomic(&csv_path, csv.as_bytes())?;
    slag_common::io::write_atomic(&md_path, md.as_bytes())?;
    Ok(format!(
        "wrote {} and {} ({} points, {:.0} s)",
        md_path.display(),
        csv_path.display(),
        rows.len(),
        t_start.elapsed().as_secs_f64()
    ))
}
