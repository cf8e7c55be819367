//! The encode sweep: one `slag-encoder encode` run per point, in process, cached on disk.

use std::path::{Path, PathBuf};

use anyhow::Context;
use slag_common::embeddings::StoredPrecision;
use slag_encoder::aggregate::MaskOverlap;
use slag_encoder::aggregate::MaskWeighting;
use slag_encoder::config::{EncodeConfig, MasksConfig};
use slag_encoder::pipeline::Encoder;
use slag_encoder::report::StageTimings;

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
    /// How `a_kj` are formed: `--mask-weighting` and `--overlap`, always passed
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

    /// `(mask weighting, overlap)` of the encode (`--mask-weighting`, `--overlap`).
    pub fn settings(self) -> (MaskWeighting, MaskOverlap) {
        match self {
            Aggregation::Mean => (MaskWeighting::None, MaskOverlap::All),
            Aggregation::Area => (MaskWeighting::Area, MaskOverlap::All),
            Aggregation::Finest => (MaskWeighting::None, MaskOverlap::Finest),
            Aggregation::FinestArea => (MaskWeighting::Area, MaskOverlap::Finest),
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

    /// The encode of this point on `scene` into `out`: everything the point does not set stays
    /// at the command line's defaults, except every view of the point's step (the study varies
    /// the step), f32 output and no progress bars. `fixtures` is `shared/fixtures`.
    pub fn encode_config(
        &self,
        scene: &Path,
        fixtures: &Path,
        workers: &Workers,
        out: &Path,
    ) -> EncodeConfig {
        let mut c = EncodeConfig::new(scene, fixtures.join("clip/color-clip-visual.onnx"), out);
        c.masks = match self.masks {
            MaskChoice::Graph => MasksConfig::graph(),
            MaskChoice::Sam { points_per_side } => {
                let mut m = MasksConfig::sam(
                    fixtures.join("sam-amg/color-sam-encoder.onnx"),
                    fixtures.join("sam-amg/color-sam-decoder.onnx"),
                );
                m.sam.points_per_side = points_per_side;
                m.sam.pred_iou_thresh = 0.8;
                m.sam.stability_score_thresh = 0.5;
                m
            }
        };
        c.scene.every = self.every;
        c.scene.views.mode = slag_encoder::views::SelectionMode::All;
        c.raster.scale = self.raster_scale;
        c.aggregate.top_k_per_pixel = self.top_k;
        (c.aggregate.mask_weighting, c.aggregate.overlap) = self.aggregation.settings();
        c.aggregate.mixture_keep = self.mixture_keep;
        c.execution.threads = workers.threads;
        c.execution.front_workers = workers.front_workers;
        c.output.precision = StoredPrecision::F32;
        c.output.progress = false;
        // The study scores the dense rows and sizes them against the mixture.
        c.output.dense = true;
        c
    }
}

/// Worker counts passed to every encode of the sweep (part of each point's cache key); the
/// study's `--threads` and `--front-workers`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, clap::Args)]
pub struct Workers {
    /// Worker threads of the encoder (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Front workers of the encoder (masks + CLIP; default GPUs + 1: raise it on many cores).
    #[arg(long)]
    pub front_workers: Option<usize>,
}

/// What the study keeps of one encode run's `report.json` (also the cache record).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EncodeRecord {
    /// The encode the run used; its JSON is the cache key ([`cached`]).
    pub config: EncodeConfig,
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
    /// The report's stage seconds (summed over images, overlapping; `total` is the run's wall
    /// time), as the encoder measured them.
    pub stages: StageTimings,
}

/// The record of a completed run in `dir` made with exactly `config` (same JSON), if there is
/// one (its embeddings may have been removed after evaluation, see [`EvalRecord`]). Records of
/// older versions (keyed by an argument list) never match.
pub fn cached(dir: &Path, config: &EncodeConfig) -> Option<EncodeRecord> {
    if !dir.join("report.json").exists() {
        return None;
    }
    let bytes = std::fs::read(dir.join("record.json")).ok()?;
    let stored: serde_json::Value = serde_json::from_slice(&bytes).ok()?;
    // Both sides as parsed JSON text (`to_value` would widen the f32 settings to f64 while the
    // file holds their shortest f32 form).
    let key: serde_json::Value = serde_json::from_str(&serde_json::to_string(config).ok()?).ok()?;
    if stored.get("config")? != &key {
        return None;
    }
    serde_json::from_value::<EncodeRecord>(stored).ok()
}

/// Runs `point` on `scene` into `dir` (unless `dir` already holds a completed run with the same
/// arguments, see [`cached`], and `fresh` is false) and returns its record and whether it came
/// from the cache; the embeddings are at `dir/embeddings.safetensors` (f32).
///
/// Errors: settings the encoder refuses (a bug here), any encode error (missing fixture, bad
/// scene, …).
pub fn run_point(
    point: &EncodePoint,
    scene: &Path,
    fixtures: &Path,
    workers: &Workers,
    dir: &Path,
    fresh: bool,
) -> anyhow::Result<(EncodeRecord, bool)> {
    let config = point.encode_config(scene, fixtures, workers, dir);
    if !fresh
        && dir.join("embeddings.safetensors").exists()
        && let Some(rec) = cached(dir, &config)
    {
        return Ok((rec, true));
    }
    // A stale evaluation must not outlive the run it measured.
    std::fs::remove_file(dir.join(EVAL_FILE)).ok();
    let record_path = dir.join("record.json");
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let r = Encoder::new(config.clone())
        .with_context(|| format!("encode settings of point {}", point.id()))?
        .run()
        .with_context(|| format!("encoding point {}", point.id()))?;
    let rec = EncodeRecord {
        config,
        views: r.counts.views_used,
        gaussians: r.counts.gaussians,
        observed: r.counts.observed,
        masks: r.counts.masks,
        contributors_per_pixel: r.counts.contributors_per_pixel,
        stages: r.timings,
    };
    slag_common::io::write_atomic(&record_path, &serde_json::to_vec_pretty(&rec)?)?;
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
    /// The held-out 2D score and the views it was taken on (`None` for a point that encoded
    /// every view, or an evaluation made before the study scored held-out views).
    #[serde(default)]
    pub held_out: Option<HeldOutRecord>,
}

/// A point's held-out score with the views it was taken on (the cache is valid only for the
/// same views).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct HeldOutRecord {
    /// Names of the held-out views, name order.
    pub views: Vec<String>,
    /// The score on them.
    pub score: super::heldout::HeldOutScore,
}

/// The cached evaluation in `dir` taken at `threshold`, if any (complete or not, see
/// [`EvalRecord::is_complete`]).
pub fn cached_eval(dir: &Path, threshold: f32) -> Option<EvalRecord> {
    let bytes = std::fs::read(dir.join(EVAL_FILE)).ok()?;
    let e = serde_json::from_slice::<EvalRecord>(&bytes).ok()?;
    (e.threshold == threshold).then_some(e)
}

impl EvalRecord {
    /// Whether this evaluation holds everything the study reports for a point encoded with
    /// `every`: a held-out score on exactly `held_out_views` when `every >= 2` (a point that
    /// encoded every view has none).
    pub fn is_complete(&self, every: usize, held_out_views: &[String]) -> bool {
        every < 2
            || self
                .held_out
                .as_ref()
                .is_some_and(|h| h.views == held_out_views)
    }
}

/// Cache folder of a point under the study's work folder.
pub fn point_dir(work: &Path, point: &EncodePoint) -> PathBuf {
    work.join("points").join(point.id())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn aggregation_points_name_and_pass_their_settings() {
        let mut p = EncodePoint::graph("baseline", 4, 0.5, None);
        assert_eq!(
            p.id(),
            "graph-e4-r0.5-kall",
            "the paper's mean keeps the old id"
        );
        let (f, w, out) = (Path::new("f"), Workers::default(), Path::new("o"));
        let c = p.encode_config(Path::new("s"), f, &w, out);
        assert_eq!(c.aggregate.mask_weighting, MaskWeighting::None);
        assert_eq!(c.aggregate.overlap, MaskOverlap::All);
        assert_eq!(c.output.precision, StoredPrecision::F32);
        assert!(c.validate().is_ok());
        p.aggregation = Aggregation::FinestArea;
        p.mixture_keep = Some(4);
        assert_eq!(p.id(), "graph-e4-r0.5-kall-finest-area-mix");
        let c2 = p.encode_config(Path::new("s"), f, &w, out);
        assert_eq!(c2.aggregate.mask_weighting, MaskWeighting::Area);
        assert_eq!(c2.aggregate.overlap, MaskOverlap::Finest);
        assert_eq!(c2.aggregate.mixture_keep, Some(4));
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

    #[test]
    fn the_cache_key_is_the_configs_json() {
        let dir = tempfile::tempdir().unwrap();
        let p = EncodePoint::graph("baseline", 4, 0.5, None);
        let c = p.encode_config(
            Path::new("s"),
            Path::new("f"),
            &Workers::default(),
            dir.path(),
        );
        let rec = EncodeRecord {
            config: c.clone(),
            views: 1,
            gaussians: 2,
            observed: 2,
            masks: 3,
            contributors_per_pixel: 1.5,
            stages: StageTimings {
                total: 1.0,
                decode: 0.1,
                ..Default::default()
            },
        };
        std::fs::write(dir.path().join("report.json"), "{}").unwrap();
        std::fs::write(
            dir.path().join("record.json"),
            serde_json::to_vec(&rec).unwrap(),
        )
        .unwrap();
        assert_eq!(cached(dir.path(), &c), Some(rec));
        let mut other = c.clone();
        other.execution.threads = Some(3);
        assert_eq!(cached(dir.path(), &other), None, "another setting misses");
        // A record of an older version (argument list) misses instead of failing.
        std::fs::write(
            dir.path().join("record.json"),
            r#"{"argv": ["--scene", "s"]}"#,
        )
        .unwrap();
        assert_eq!(cached(dir.path(), &c), None);
    }
}
