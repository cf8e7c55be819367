//! The encode sweep: one `slag-encoder encode` run per point, in process, cached on disk.

use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Parser;
use slag_encoder::cli::encode::EncodeArgs;

/// Where a point's masks come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum MaskChoice {
    /// The Felzenszwalb-Huttenlocher graph segmenter with slag's defaults (k 500, min 500 px).
    Graph,
    /// color-sam automatic mask generation on a `points_per_side`² grid with the reference
    /// filters (pred-IoU 0.8, stability 0.5, box NMS 0.7), as in the encoder's tests.
    Sam {
        /// Grid points per image side.
        points_per_side: u32,
    },
}

impl MaskChoice {
    /// Short name: `graph`, `sam8`, `sam16`, …
    pub fn name(&self) -> String {
        match self {
            MaskChoice::Graph => "graph".into(),
            MaskChoice::Sam { points_per_side } => format!("sam{points_per_side}"),
        }
    }
}

/// One point of the encode sweep: the knobs of `slag-encoder encode` that change speed or
/// accuracy. Everything else stays at the CLI defaults (CPU execution provider, GPU rasterizer
/// through wgpu, f32 output so that the exact f32 answer is available).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EncodePoint {
    /// Which knob this point varies around the baseline (`baseline`, `masks`, `every`,
    /// `raster`, `top-k`, `reference`).
    pub knob: String,
    /// Mask source.
    pub masks: MaskChoice,
    /// Keep every N-th image (`--every`).
    pub every: usize,
    /// Raster resolution relative to the images (`--raster-scale`).
    pub raster_scale: f64,
    /// Contributors kept per pixel (`--top-k-per-pixel`); `None` = all (the paper).
    pub top_k: Option<usize>,
    /// Also write the mixture form with this many slots (`--mixture-keep`); the dense
    /// embeddings do not depend on it. The study sets it on the baseline only.
    pub mixture_keep: Option<usize>,
    /// How `a_kj` are formed (issue 17): `--mask-weighting` and `--overlap`, always passed
    /// explicitly so that a point's meaning does not follow the encoder's defaults.
    #[serde(default)]
    pub aggregation: Aggregation,
}

/// The aggregation knobs of a point (`encode --mask-weighting W --overlap O`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
pub enum Aggregation {
    /// The paper's mean: `--mask-weighting none --overlap all`.
    #[default]
    Mean,
    /// `--mask-weighting area --overlap all`.
    Area,
    /// `--mask-weighting none --overlap finest`.
    Finest,
    /// `--mask-weighting area --overlap finest`.
    FinestArea,
}

impl Aggregation {
    /// Every choice, in the study's order.
    pub const ALL: [Aggregation; 4] = [
        Aggregation::Mean,
        Aggregation::Area,
        Aggregation::Finest,
        Aggregation::FinestArea,
    ];

    /// Id suffix: empty for the paper's mean (so older ids keep their meaning), else
    /// `-area`, `-finest`, `-finest-area`.
    pub fn suffix(self) -> &'static str {
        match self {
            Aggregation::Mean => "",
            Aggregation::Area => "-area",
            Aggregation::Finest => "-finest",
            Aggregation::FinestArea => "-finest-area",
        }
    }

    /// `(--mask-weighting, --overlap)` values.
    pub fn flags(self) -> (&'static str, &'static str) {
        match self {
            Aggregation::Mean => ("none", "all"),
            Aggregation::Area => ("area", "all"),
            Aggregation::Finest => ("none", "finest"),
            Aggregation::FinestArea => ("area", "finest"),
        }
    }
}

impl EncodePoint {
    /// A graph-mask point.
    pub fn graph(knob: &str, every: usize, raster_scale: f64, top_k: Option<usize>) -> Self {
        EncodePoint {
            knob: knob.into(),
            masks: MaskChoice::Graph,
            every,
            raster_scale,
            top_k,
            mixture_keep: None,
            aggregation: Aggregation::Mean,
        }
    }

    /// Stable identifier, also the cache folder name: e.g. `graph-e4-r0.5-kall` (the
    /// aggregation's [`Aggregation::suffix`] then `-mix` appended when the run also writes the
    /// mixture form).
    pub fn id(&self) -> String {
        format!(
            "{}-e{}-r{}-k{}{}{}",
            self.masks.name(),
            self.every,
            self.raster_scale,
            self.top_k_name(),
            self.aggregation.suffix(),
            if self.mixture_keep.is_some() {
                "-mix"
            } else {
                ""
            }
        )
    }

    /// `all` or the number of contributors kept per pixel.
    pub fn top_k_name(&self) -> String {
        self.top_k.map_or_else(|| "all".into(), |k| k.to_string())
    }

    /// The `slag-encoder encode` arguments of this point (besides `--scene`/`--out`).
    /// `fixtures` is `shared/fixtures`.
    pub fn encode_argv(&self, fixtures: &Path, workers: &Workers) -> Vec<String> {
        let f = |rel: &str| fixtures.join(rel).display().to_string();
        let mut v: Vec<String> = Vec::new();
        let mut push = |a: &str, b: String| {
            v.push(a.to_string());
            v.push(b);
        };
        match self.masks {
            MaskChoice::Graph => push("--masks", "graph".into()),
            MaskChoice::Sam { points_per_side } => {
                push("--masks", "sam".into());
                push("--sam-encoder", f("sam-amg/color-sam-encoder.onnx"));
                push("--sam-decoder", f("sam-amg/color-sam-decoder.onnx"));
                push("--sam-points-per-side", points_per_side.to_string());
                push("--sam-pred-iou-thresh", "0.8".into());
                push("--sam-stability-score-thresh", "0.5".into());
            }
        }
        push("--clip-visual", f("clip/color-clip-visual.onnx"));
        push("--every", self.every.to_string());
        push("--raster-scale", self.raster_scale.to_string());
        if let Some(k) = self.top_k {
            push("--top-k-per-pixel", k.to_string());
        }
        let (weighting, overlap) = self.aggregation.flags();
        push("--mask-weighting", weighting.into());
        push("--overlap", overlap.into());
        if let Some(s) = self.mixture_keep {
            push("--mixture-keep", s.to_string());
        }
        if let Some(t) = workers.threads {
            push("--threads", t.to_string());
        }
        if let Some(f) = workers.front_workers {
            push("--front-workers", f.to_string());
        }
        push("--precision", "f32".into());
        v.push("--quiet".into());
        v
    }
}

/// Worker counts passed to every encode of the sweep (part of each point's cache key).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Workers {
    /// `--threads` (default: all cores).
    pub threads: Option<usize>,
    /// `--front-workers` (default: the encoder's, GPUs + 1).
    pub front_workers: Option<usize>,
}

/// What the study keeps of one encode run's `report.json` (also the cache record).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EncodeRecord {
    /// The full `encode` argument list the run used (cache key).
    pub argv: Vec<String>,
    /// Views encoded.
    pub views: usize,
    /// Gaussians in the scene.
    pub gaussians: usize,
    /// Observed Gaussians (stored).
    pub observed: usize,
    /// Masks over all views.
    pub masks: usize,
    /// Mean contributors per raster pixel.
    pub contributors_per_pixel: f64,
    /// Wall time of the whole run, s.
    pub total_s: f64,
    /// Per-stage seconds summed over images (overlapping on two threads): decode, masks, CLIP,
    /// raster, image-stage aggregation; reduce and load once per run.
    pub decode_s: f64,
    /// See [`EncodeRecord::decode_s`].
    pub masks_s: f64,
    /// See [`EncodeRecord::decode_s`].
    pub clip_s: f64,
    /// See [`EncodeRecord::decode_s`].
    pub raster_s: f64,
    /// See [`EncodeRecord::decode_s`].
    pub aggregate_s: f64,
    /// See [`EncodeRecord::decode_s`].
    pub reduce_s: f64,
}

#[derive(Parser)]
struct EncodeCli {
    #[command(flatten)]
    args: EncodeArgs,
}

/// The `encode` argument list of `point` on `scene` into `dir` (the cache key).
pub fn full_argv(
    point: &EncodePoint,
    scene: &Path,
    fixtures: &Path,
    workers: &Workers,
    dir: &Path,
) -> Vec<String> {
    let mut argv = vec![
        "--scene".to_string(),
        scene.display().to_string(),
        "--out".into(),
        dir.display().to_string(),
    ];
    argv.extend(point.encode_argv(fixtures, workers));
    argv
}

/// The record of a completed run in `dir` made with exactly `argv`, if there is one (its
/// embeddings may have been removed after evaluation, see [`EvalRecord`]).
pub fn cached(dir: &Path, argv: &[String]) -> Option<EncodeRecord> {
    if !dir.join("report.json").exists() {
        return None;
    }
    let bytes = std::fs::read(dir.join("record.json")).ok()?;
    let rec = serde_json::from_slice::<EncodeRecord>(&bytes).ok()?;
    (rec.argv == argv).then_some(rec)
}

/// Runs `point` on `scene` into `dir` (unless `dir` already holds a completed run with the same
/// arguments, see [`cached`], and `fresh` is false) and returns its record and whether it came
/// from the cache; the embeddings are at `dir/embeddings.safetensors` (f32).
///
/// Errors: bad arguments (a bug here), any `encode` error (missing fixture, bad scene, …).
pub fn run_point(
    point: &EncodePoint,
    scene: &Path,
    fixtures: &Path,
    workers: &Workers,
    dir: &Path,
    fresh: bool,
) -> anyhow::Result<(EncodeRecord, bool)> {
    let argv = full_argv(point, scene, fixtures, workers, dir);
    if !fresh
        && dir.join("embeddings.safetensors").exists()
        && let Some(rec) = cached(dir, &argv)
    {
        return Ok((rec, true));
    }
    // A stale evaluation must not outlive the run it measured.
    std::fs::remove_file(dir.join(EVAL_FILE)).ok();
    let record_path = dir.join("record.json");
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let cli = EncodeCli::try_parse_from(std::iter::once("encode".to_string()).chain(argv.clone()))
        .with_context(|| format!("encode arguments of point {}", point.id()))?;
    let r = slag_encoder::cli::encode::run(&cli.args)
        .with_context(|| format!("encoding point {}", point.id()))?;
    let t = &r.timings;
    let rec = EncodeRecord {
        argv,
        views: r.counts.views_used,
        gaussians: r.counts.gaussians,
        observed: r.counts.observed,
        masks: r.counts.masks,
        contributors_per_pixel: r.counts.contributors_per_pixel,
        total_s: t.total,
        decode_s: t.decode,
        masks_s: t.masks,
        clip_s: t.clip,
        raster_s: t.raster,
        aggregate_s: t.image_aggregate,
        reduce_s: t.reduce,
    };
    slag_common::embeddings::write_atomic(&record_path, &serde_json::to_vec_pretty(&rec)?)?;
    Ok((rec, false))
}

/// File of a point's cached [`EvalRecord`].
pub const EVAL_FILE: &str = "eval.json";

/// What the study measures on a point's f32 embeddings, cached beside its record so that the
/// embeddings (240 MB at f32 for snowmiku) can be removed once evaluated.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EvalRecord {
    /// Match threshold the sets were taken at.
    pub threshold: f32,
    /// Colour mIoU.
    pub colour_miou: Option<f64>,
    /// Median f32 scan latency, ms.
    pub scan_ms: f64,
    /// Per prompt, the ascending ids with cosine `>= threshold`.
    pub sets: Vec<Vec<u32>>,
}

/// The cached evaluation in `dir` taken at `threshold`, if any.
pub fn cached_eval(dir: &Path, threshold: f32) -> Option<EvalRecord> {
    let bytes = std::fs::read(dir.join(EVAL_FILE)).ok()?;
    let e = serde_json::from_slice::<EvalRecord>(&bytes).ok()?;
    (e.threshold == threshold).then_some(e)
}

/// Cache folder of a point under the study's work folder.
pub fn point_dir(work: &Path, point: &EncodePoint) -> PathBuf {
    work.join("points").join(point.id())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn aggregation_points_name_and_pass_their_flags() {
        let mut p = EncodePoint::graph("baseline", 4, 0.5, None);
        assert_eq!(
            p.id(),
            "graph-e4-r0.5-kall",
            "the paper's mean keeps the old id"
        );
        let argv = p.encode_argv(Path::new("f"), &Workers::default());
        let flag = |argv: &[String], name: &str| {
            let i = argv.iter().position(|a| a == name).expect(name);
            argv[i + 1].clone()
        };
        assert_eq!(flag(&argv, "--mask-weighting"), "none");
        assert_eq!(flag(&argv, "--overlap"), "all");
        p.aggregation = Aggregation::FinestArea;
        p.mixture_keep = Some(4);
        assert_eq!(p.id(), "graph-e4-r0.5-kall-finest-area-mix");
        let argv = p.encode_argv(Path::new("f"), &Workers::default());
        assert_eq!(flag(&argv, "--mask-weighting"), "area");
        assert_eq!(flag(&argv, "--overlap"), "finest");
        let ids: std::collections::HashSet<String> = Aggregation::ALL
            .iter()
            .map(|&a| {
                EncodePoint {
                    aggregation: a,
                    ..p.clone()
                }
                .id()
            })
            .collect();
        assert_eq!(ids.len(), Aggregation::ALL.len(), "ids are unique");
    }
}
