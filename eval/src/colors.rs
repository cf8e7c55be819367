//! The colour evaluation of an embeddings file made with color-clip (`slag-encoder eval-colors`,
//! the accuracy instrument of every speed/accuracy trade).
//!
//! [`run`]: the 3D score of [`crate::eval`] (each Gaussian's class against the prototype nearest
//! its SH-DC colour). [`run_held_out`]: the 2D protocol of [`crate::heldout`] on the views the
//! encoder never saw, with the majority-class and pixel-lifting-oracle baselines, and the 3D
//! score as a secondary line.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use slag_common::Error;
use slag_common::camera;
use slag_common::embeddings::Embeddings;
use slag_common::onnx::ExecutionProvider;
use slag_common::scene::{self, Gaussians, PlyLoadOptions};
use slag_common::segments::Segments;
use slag_common::text::TextEncoder;
use slag_encoder::config::RasterBackend;
use slag_encoder::pipeline::build::make_rasterizer;
use slag_encoder::pipeline::scene_ply;
use slag_encoder::raster::WeightRasterizer;

use crate::heldout;

/// What `eval-colors` evaluates and with which models.
#[derive(Debug, Clone, PartialEq)]
pub struct EvalColorsConfig {
    /// Scene folder (its point_cloud.ply gives the ground truth colours), or use `ply`.
    pub scene: PathBuf,
    /// The .ply the embeddings were made from; `None`: `<scene>/point_cloud.ply`.
    pub ply: Option<PathBuf>,
    /// The dense embeddings.safetensors written by the encoder with color-clip (asked for with
    /// `output.dense`; the scores use each Gaussian's `Σ a_kj`, which the mixture does not store).
    pub embeddings: PathBuf,
    /// Folder holding color-clip (`color-clip-textual.onnx`, `clip-tokenizer.json`,
    /// `color-clip.json`); `None`: `$SLAG_SHARED/fixtures/clip`. The three fields below override
    /// single files.
    pub color_clip: Option<PathBuf>,
    /// color-clip text tower; `None`: `<color_clip>/color-clip-textual.onnx`.
    pub clip_textual: Option<PathBuf>,
    /// CLIP tokenizer; `None`: `<color_clip>/clip-tokenizer.json`.
    pub tokenizer: Option<PathBuf>,
    /// color-clip class rule; `None`: `<color_clip>/color-clip.json`.
    pub classes: Option<PathBuf>,
    /// ONNX Runtime execution provider of the text tower.
    pub ep: ExecutionProvider,
    /// The held-out step ([`run_held_out`] only): the encoder's `every`, or its
    /// `hold_out_every` when it held views out itself; `None`: from the report.json beside the
    /// embeddings (`inputs.hold_out_every`, else `inputs.every`).
    pub every: Option<usize>,
    /// The encoder's raster scale, at which the oracle lifts the encoded views ([`run_held_out`]
    /// only); `None`: `parameters.raster_scale` of the report.json beside the embeddings. The
    /// held-out views are always rendered at full resolution.
    pub raster_scale: Option<f64>,
    /// Weight rasterizer for the held-out renders and the oracle.
    pub rasterizer: RasterBackend,
    /// More embeddings files of the same scene and `every` to score in the same held-out pass
    /// ([`run_held_out`] only; listed under `variants` by path). Forms beside the main embeddings
    /// are scored too: `embeddings-level{0,1,2}.safetensors` and `mixture.safetensors`.
    pub compare: Vec<PathBuf>,
    /// Also score with prediction filtering (SLAG PF, [`slag_encoder::prediction_filtering`]):
    /// the 3D score with each segment's majority class, and in the held-out pass the tables
    /// `argmax`, `pf-majority` and `pf-mean` under `variants`.
    pub prediction_filtering: bool,
    /// The segments for PF; `None`: `segments.safetensors` beside the embeddings.
    pub segments: Option<PathBuf>,
    /// More segmentations of the same scene, measured and (held-out) filtered beside the main
    /// one in the same pass; their variants are named `…@<parent folder>/<file stem>`.
    pub more_segments: Vec<PathBuf>,
    /// The encode's masks' record, measured against the colour truth beside the segments
    /// ([`crate::segment_limits`]); `None`: `mask-record.safetensors` beside the
    /// embeddings when it exists.
    pub mask_record: Option<PathBuf>,
    /// [`run_held_out`] writes the lifted photo classes here ([`write_photo_classes`]).
    pub photo_classes_out: Option<PathBuf>,
    /// [`run_pf`] measures the segments against the lifted photo classes of this file (written
    /// by a held-out pass of the same encode).
    pub photo_classes: Option<PathBuf>,
}

/// Unlabelled Gaussian in a photo-classes file.
pub const NO_PHOTO_CLASS: u8 = u8::MAX;

/// Writes each Gaussian's lifted photo class as one byte per Gaussian, scene order
/// ([`NO_PHOTO_CLASS`]: the oracle gave it no weight); no header.
///
/// Errors: I/O; a class above 254 ([`Error::Internal`]).
pub fn write_photo_classes(path: &Path, classes: &[Option<u32>]) -> anyhow::Result<()> {
    let bytes = classes
        .iter()
        .map(|c| match c {
            None => Ok(NO_PHOTO_CLASS),
            Some(k) if *k < u32::from(NO_PHOTO_CLASS) => Ok(*k as u8),
            Some(k) => Err(Error::internal(format!(
                "photo class {k} does not fit a byte"
            ))),
        })
        .collect::<slag_common::Result<Vec<u8>>>()?;
    std::fs::write(path, bytes).map_err(|e| Error::io(path, e))?;
    Ok(())
}

/// Reads a file of [`write_photo_classes`] for a scene of `n` Gaussians.
///
/// Errors: I/O; a file of another length ([`Error::Mismatch`]).
pub fn read_photo_classes(path: &Path, n: usize) -> anyhow::Result<Vec<Option<u32>>> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    if bytes.len() != n {
        return Err(Error::mismatch(
            slag_common::Mismatched::Scene,
            format!(
                "{} holds {} photo classes but the scene has {n} Gaussians",
                path.display(),
                bytes.len()
            ),
        )
        .into());
    }
    Ok(bytes
        .into_iter()
        .map(|b| (b != NO_PHOTO_CLASS).then_some(u32::from(b)))
        .collect())
}

impl EvalColorsConfig {
    /// `embeddings` of `scene` with color-clip from `$SLAG_SHARED/fixtures/clip` on the CPU,
    /// the GPU rasterizer, `every` and the raster scale from the report beside the embeddings.
    pub fn new(scene: impl Into<PathBuf>, embeddings: impl Into<PathBuf>) -> Self {
        EvalColorsConfig {
            scene: scene.into(),
            ply: None,
            embeddings: embeddings.into(),
            color_clip: None,
            clip_textual: None,
            tokenizer: None,
            classes: None,
            ep: ExecutionProvider::Cpu,
            every: None,
            raster_scale: None,
            rasterizer: RasterBackend::Gpu,
            compare: Vec::new(),
            prediction_filtering: false,
            segments: None,
            more_segments: Vec::new(),
            mask_record: None,
            photo_classes_out: None,
            photo_classes: None,
        }
    }
}

/// What every evaluation needs: the classes, the scene, the embeddings and the class texts.
struct Inputs {
    classes: crate::ColorClasses,
    gaussians: Gaussians,
    emb: Embeddings,
    text_embeds: Vec<Vec<f32>>,
}

fn load_inputs(a: &EvalColorsConfig) -> anyhow::Result<Inputs> {
    // The folder is needed only for the files no flag names.
    let clip_dir = || -> anyhow::Result<PathBuf> {
        match &a.color_clip {
            Some(d) => Ok(d.clone()),
            None => Ok(slag_common::paths::shared_dir()
                .map_err(|e| {
                    Error::param(
                        "color_clip",
                        "unset",
                        format!("the folder of color-clip's files ({e})"),
                    )
                })?
                .join("fixtures")
                .join("clip")),
        }
    };
    let or = |p: &Option<PathBuf>, name: &str| -> anyhow::Result<PathBuf> {
        match p {
            Some(p) => Ok(p.clone()),
            None => Ok(clip_dir()?.join(name)),
        }
    };
    let classes = crate::ColorClasses::load(&or(&a.classes, "color-clip.json")?)?;
    let ply = scene_ply(&a.scene, a.ply.as_deref());
    let gaussians = scene::load_ply(&ply, PlyLoadOptions { colours: true })?;
    let emb = Embeddings::read(&a.embeddings)?;
    if emb.scene_gaussians != gaussians.len() as u64 {
        return Err(Error::param(
            "ply",
            format!("{} ({} Gaussians)", ply.display(), gaussians.len()),
            format!(
                "the .ply used by encode: {} was made from a scene of {} Gaussians",
                a.embeddings.display(),
                emb.scene_gaussians
            ),
        )
        .into());
    }
    let mut text = TextEncoder::new(
        &or(&a.clip_textual, "color-clip-textual.onnx")?,
        &or(&a.tokenizer, "clip-tokenizer.json")?,
        a.ep,
    )?;
    let names: Vec<&str> = classes.names.iter().map(String::as_str).collect();
    let text_embeds = text.encode(&names).context("encoding the colour prompts")?;
    Ok(Inputs {
        classes,
        gaussians,
        emb,
        text_embeds,
    })
}

fn colour_3d(i: &Inputs) -> anyhow::Result<crate::ColourEval> {
    let gt = crate::ground_truth(&i.classes, &i.gaussians)?;
    let predicted = crate::assign(&i.emb, &i.text_embeds)?;
    Ok(crate::evaluate(&gt, &i.emb, &predicted, &i.classes.names)?)
}

/// The main segments' path: `--segments`, else beside the embeddings.
fn main_segments_path(a: &EvalColorsConfig) -> PathBuf {
    a.segments.clone().unwrap_or_else(|| {
        a.embeddings
            .parent()
            .unwrap_or(Path::new("."))
            .join(slag_common::segments::FILE_NAME)
    })
}

/// The segments PF uses, checked against the scene.
fn load_segments(a: &EvalColorsConfig, scene_gaussians: usize) -> anyhow::Result<Segments> {
    read_segments(&main_segments_path(a), scene_gaussians)
}

/// The segments at `path`, checked against the scene.
fn read_segments(path: &Path, scene_gaussians: usize) -> anyhow::Result<Segments> {
    let path = path.to_path_buf();
    let s = Segments::read(&path)
        .with_context(|| format!("prediction filtering needs segments ({})", path.display()))?;
    if s.len() != scene_gaussians {
        return Err(Error::mismatch(
            slag_common::Mismatched::Scene,
            format!(
                "{} segments {} Gaussians but the scene has {scene_gaussians}; segment the .ply \
                 the embeddings were made from",
                path.display(),
                s.len()
            ),
        )
        .into());
    }
    Ok(s)
}

/// The 3D score with prediction filtering: each segment's majority class for its Gaussians.
fn colour_3d_pf(i: &Inputs, segments: &Segments) -> anyhow::Result<crate::ColourEval> {
    let gt = crate::ground_truth(&i.classes, &i.gaussians)?;
    let predicted = crate::assign(&i.emb, &i.text_embeds)?;
    let rows = segments.gather(&i.emb.ids)?;
    let filtered = slag_encoder::prediction_filtering::filter_rows(&predicted, &rows)?;
    Ok(crate::evaluate(&gt, &i.emb, &filtered, &i.classes.names)?)
}

/// `eval-colors --prediction-filtering` without `--held-out`: the 3D score without and with PF.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ColourEvalPf {
    /// Each Gaussian's own class.
    pub without_pf: crate::ColourEval,
    /// Each segment's majority class.
    pub with_pf: crate::ColourEval,
    /// Segments of the scene.
    pub segments: u32,
    /// The segments measured against the colour truth: the main ones, then `more_segments`.
    pub segment_quality: Vec<SegmentQuality>,
    /// What limits purity on this scene: the truth's local agreement, the masks' purity.
    pub segment_limits: SegmentLimits,
    /// With `photo_classes`: each segmentation's purity against the lifted photo classes, in
    /// the order of `segment_quality`.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub photo_purity: Vec<crate::segment_quality::Purity>,
}

/// One segmentation measured against the colour classes
/// ([`crate::segment_quality`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SegmentQuality {
    /// The segments file.
    pub source: PathBuf,
    /// Segment purity over the observed Gaussians that have a true class (the class of the
    /// prototype nearest their SH-DC colour).
    pub purity: crate::segment_quality::Purity,
    /// Segment count and sizes (all Gaussians of the scene).
    pub sizes: crate::segment_quality::SizeDistribution,
    /// Purity per segment-size decade.
    pub purity_by_size: Vec<crate::segment_limits::SizePurity>,
    /// Purity with each observed Gaussian counted by its total blend weight `Σ a_kj` (the
    /// embeddings' `total_weights`), and over the most-seen Gaussians; beside `purity`, not
    /// instead of it.
    pub purity_by_weight: crate::segment_limits::WeightedPurity,
}

/// What limits segment purity on this scene ([`crate::segment_limits`]), independent of
/// any segmentation but the masks'.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SegmentLimits {
    /// The colour truth's own local agreement, k = 8 and 16 (observed Gaussians).
    pub neighbour_agreement: Vec<crate::segment_limits::NeighbourAgreement>,
    /// The masks' record, when there is one.
    pub mask_record: Option<PathBuf>,
    /// Purity of the record's dominant masks against the colour truth.
    pub mask_purity: Option<crate::segment_limits::MaskPurity>,
    /// The record's disagreement on same-class and different-class neighbours (k = 10).
    pub mask_evidence: Option<crate::segment_limits::MaskEvidence>,
}

/// The total blend weight of each observed Gaussian (`None`: unobserved), scene order.
fn observed_weights(i: &Inputs) -> Vec<Option<f32>> {
    let mut w = vec![None; i.gaussians.len()];
    for (&id, &t) in i.emb.ids.iter().zip(&i.emb.total_weights) {
        if let Some(x) = w.get_mut(id as usize) {
            *x = Some(t);
        }
    }
    w
}

/// The masks' record to measure: `mask_record`, else the one beside the embeddings if any.
fn mask_record_path(a: &EvalColorsConfig) -> Option<PathBuf> {
    a.mask_record.clone().or_else(|| {
        let p = a
            .embeddings
            .parent()
            .unwrap_or(Path::new("."))
            .join(slag_common::mask_record::FILE_NAME);
        p.exists().then_some(p)
    })
}

/// [`SegmentLimits`] of the scene, said on stderr too.
fn segment_limits(a: &EvalColorsConfig, i: &Inputs) -> anyhow::Result<SegmentLimits> {
    use crate::segment_limits::{mask_evidence, mask_purity, neighbour_agreement};
    let labels = observed_truth(i)?;
    let means = &i.gaussians.means;
    let agreement = neighbour_agreement(means, &labels, &[8, 16])?;
    for n in &agreement {
        eprintln!(
            "colour truth, k = {}: {:.4} of the nearest neighbours share a Gaussian's class; \
             {:.4} of the Gaussians hold their ball's majority; pairs of different classes: {}",
            n.k,
            n.same_share,
            n.local_majority,
            n.different_pairs
                .iter()
                .map(|&(a, b, s)| format!(
                    "{}/{} {:.3}",
                    i.classes.names[a as usize], i.classes.names[b as usize], s
                ))
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    let path = mask_record_path(a);
    let (mut purity, mut evidence) = (None, None);
    if let Some(p) = &path {
        let record = slag_common::mask_record::MaskRecord::read(p)?;
        let mp = mask_purity(&labels, &record)?;
        let ev = mask_evidence(means, &labels, &record, 10)?;
        eprintln!(
            "masks' record {}: mask purity {:.4} (best view) / {:.4} (all slots) over {} masks; \
             disagreement same class {:.3} (> 0.5: {:.3}, unknown {:.3}), different class {:.3} \
             (> 0.5: {:.3}, unknown {:.3})",
            p.display(),
            mp.best_view,
            mp.all_slots,
            mp.masks,
            ev.same_label.mean_disagreement,
            ev.same_label.over_half,
            ev.same_label.unknown,
            ev.different_label.mean_disagreement,
            ev.different_label.over_half,
            ev.different_label.unknown
        );
        purity = Some(mp);
        evidence = Some(ev);
    }
    Ok(SegmentLimits {
        neighbour_agreement: agreement,
        mask_record: path,
        mask_purity: purity,
        mask_evidence: evidence,
    })
}

/// Each observed Gaussian's true class as a label (`None`: unobserved or without a class).
fn observed_truth(i: &Inputs) -> anyhow::Result<Vec<Option<u32>>> {
    let gt = crate::ground_truth(&i.classes, &i.gaussians)?;
    let mut labels = vec![None; gt.len()];
    for &id in &i.emb.ids {
        if let (Some(l), Some(t)) = (labels.get_mut(id as usize), gt.get(id as usize)) {
            *l = t.map(u32::from);
        }
    }
    Ok(labels)
}

/// Measures `segments` from `source` against the observed Gaussians' colour classes, and says
/// so on stderr.
fn segment_quality(
    i: &Inputs,
    source: &Path,
    segments: &Segments,
) -> anyhow::Result<SegmentQuality> {
    use crate::segment_limits::{purity_by_size, weighted_purity};
    use crate::segment_quality::{purity, size_distribution};
    let labels = observed_truth(i)?;
    let q = SegmentQuality {
        source: source.to_path_buf(),
        purity: purity(&labels, &segments.segments)?,
        sizes: size_distribution(&segments.segments),
        purity_by_size: purity_by_size(&labels, &segments.segments)?,
        purity_by_weight: weighted_purity(&labels, &segments.segments, &observed_weights(i))?,
    };
    eprintln!(
        "segments {}: purity {:.4} over {} observed Gaussians; {} segments, sizes min {} median \
         {} mean {:.1} p90 {} max {} (largest {:.1} % of the Gaussians)",
        source.display(),
        q.purity.purity,
        q.purity.counted,
        q.sizes.segments,
        q.sizes.min,
        q.sizes.median,
        q.sizes.mean,
        q.sizes.p90,
        q.sizes.max,
        100.0 * q.sizes.largest_share
    );
    eprintln!(
        "  by blend weight: {:.4}; top half {:.4}, top quarter {:.4}, bottom half {:.4}; by size: {}",
        q.purity_by_weight.weighted,
        q.purity_by_weight.top_half,
        q.purity_by_weight.top_quarter,
        q.purity_by_weight.bottom_half,
        q.purity_by_size
            .iter()
            .filter(|b| b.counted > 0)
            .map(|b| format!(
                "{}–{}: {:.3} ({} G)",
                b.from,
                b.to.map_or("∞".to_string(), |t| t.to_string()),
                b.purity,
                b.counted
            ))
            .collect::<Vec<_>>()
            .join(", ")
    );
    Ok(q)
}

/// The main segments and `more_segments`, each with its path.
fn all_segments(
    a: &EvalColorsConfig,
    scene_gaussians: usize,
) -> anyhow::Result<Vec<(PathBuf, Segments)>> {
    let mut out = vec![(main_segments_path(a), load_segments(a, scene_gaussians)?)];
    for p in &a.more_segments {
        out.push((p.clone(), read_segments(p, scene_gaussians)?));
    }
    Ok(out)
}

/// The 3D evaluation without and with prediction filtering.
///
/// Errors: as [`run`], and the segments unreadable or of another scene.
pub fn run_pf(a: &EvalColorsConfig) -> anyhow::Result<ColourEvalPf> {
    let inputs = load_inputs(a)?;
    let all = all_segments(a, inputs.gaussians.len())?;
    let segment_quality = all
        .iter()
        .map(|(p, s)| segment_quality(&inputs, p, s))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let segments = &all[0].1;
    let photo_purity = match &a.photo_classes {
        Some(p) => {
            let lifted = read_photo_classes(p, inputs.gaussians.len())?;
            let mut out = Vec::new();
            for (path, s) in &all {
                let q = crate::segment_quality::purity(&lifted, &s.segments)?;
                eprintln!(
                    "segments {}: purity {:.4} against the lifted photo classes of {}",
                    path.display(),
                    q.purity,
                    p.display()
                );
                out.push(q);
            }
            out
        }
        None => Vec::new(),
    };
    Ok(ColourEvalPf {
        photo_purity,
        without_pf: colour_3d(&inputs)?,
        with_pf: colour_3d_pf(&inputs, segments)?,
        segments: segments.segment_count,
        segment_quality,
        segment_limits: segment_limits(a, &inputs)?,
    })
}

/// The 3D evaluation (`eval-colors` without `--held-out`; serialisable to JSON).
///
/// Errors: [`Error::Param`] `color_clip` when no folder is given and `$SLAG_SHARED` is unset,
/// [`Error::Param`] `ply` for embeddings of another scene; the color-clip files or the scene
/// unreadable.
pub fn run(a: &EvalColorsConfig) -> anyhow::Result<crate::ColourEval> {
    colour_3d(&load_inputs(a)?)
}

/// The 2D held-out evaluation ([`crate::heldout`]); serialises to `eval-colors --held-out`'s
/// `held_out` object.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct HeldOutEval {
    /// The held-out step N (the encoder's `--hold-out-every N`, else its `--every N`): held-out
    /// views have name-sorted index ≡ ⌊N/2⌋ (mod N).
    pub every: usize,
    /// Names of the held-out views, in name order.
    pub held_out_views: Vec<String>,
    /// Number of encoded views (the report's chosen views, else the training split), which the
    /// oracle lifts.
    pub encoded_views: usize,
    /// Raster scale of the oracle's lifting (the encoder's `--raster-scale`); held-out renders
    /// are at scale 1.
    pub oracle_raster_scale: f64,
    /// The weight rasterizer that ran.
    pub rasterizer: String,
    /// Pixels count when their rendered alpha is at least this.
    pub alpha_min: f32,
    /// Pixels of all held-out views.
    pub pixels: u64,
    /// Pixels counted (alpha ≥ `alpha_min`).
    pub counted_pixels: u64,
    /// The class-size threshold of the mIoU (fraction of the counted pixels, by truth).
    pub miou_min_class_fraction: f64,
    /// Classes averaged in every mIoU below.
    pub miou_classes: Vec<String>,
    /// slag: `cos(E_k, text_c)` rendered and argmaxed.
    pub slag: heldout::PixelScore,
    /// The majority class of the counted pixels (the majority baseline's answer everywhere).
    pub majority_class: String,
    /// Baseline: every counted pixel gets `majority_class`.
    pub majority: heldout::PixelScore,
    /// Baseline: pixel-level lifting oracle `Σ_p w_kp · onehot(class(photo_p))` over the encoded
    /// views, rendered like slag.
    pub oracle: heldout::PixelScore,
    /// Gaussians that received weight in the oracle's lifting.
    pub oracle_observed_gaussians: usize,
    /// Gaussians with an embedding (slag's observed).
    pub observed_gaussians: usize,
    /// slag's mIoU / the oracle's.
    pub slag_over_oracle: Option<f64>,
    /// Other predictors scored on the same pixels: `--compare` files and the stored forms
    /// beside the embeddings (per-level embeddings, mixture), see [`crate::heldout_variants`].
    pub variants: Vec<crate::heldout_variants::VariantScore>,
    /// Wall time of the held-out evaluation (renders, oracle, scoring), seconds.
    pub seconds: f64,
}

/// What `eval-colors --held-out` prints.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct HeldOutOutput {
    /// The 2D held-out protocol (primary).
    pub held_out: HeldOutEval,
    /// The 3D per-Gaussian score (secondary line), as `eval-colors` without `--held-out`.
    pub colour_3d: crate::ColourEval,
    /// With `--prediction-filtering`: the 3D score with each segment's majority class.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub colour_3d_pf: Option<crate::ColourEval>,
    /// With `--prediction-filtering`: each segmentation measured against the colour truth.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub segment_quality: Vec<SegmentQuality>,
    /// With `--prediction-filtering`: each segmentation measured against the *photo* classes the
    /// oracle lifts (each Gaussian's class of most lifted weight, `argmax_c h_kc`, over the
    /// Gaussians the oracle saw), the truth of the held-out pixels; the segments' files in the
    /// order of `segment_quality`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub photo_truth: Option<PhotoTruthQuality>,
}

/// Segments against the lifted photo classes ([`HeldOutOutput::photo_truth`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct PhotoTruthQuality {
    /// Gaussians with a lifted class.
    pub labelled: usize,
    /// Share of the Gaussians with both truths whose lifted photo class is their SH-DC class.
    pub agrees_with_colour_truth: f64,
    /// The lifted classes' local agreement, k = 8 and 16.
    pub neighbour_agreement: Vec<crate::segment_limits::NeighbourAgreement>,
    /// Purity of each segmentation against them.
    pub purity: Vec<crate::segment_quality::Purity>,
    /// The masks' record against them (as [`SegmentLimits`]), when there is one.
    pub mask_purity: Option<crate::segment_limits::MaskPurity>,
    /// The record's disagreement on same- and different-class neighbours (k = 10).
    pub mask_evidence: Option<crate::segment_limits::MaskEvidence>,
}

/// Each Gaussian's class of most lifted weight (`None`: the oracle gave it none); ties to the
/// smaller class. `scores` is [`heldout::OracleLifting::scores`], `[n × c]`.
fn lifted_classes(scores: &[f32], c: usize) -> Vec<Option<u32>> {
    scores
        .chunks_exact(c)
        .map(|h| {
            let (best, v) =
                h.iter().enumerate().fold(
                    (0usize, 0.0f32),
                    |b, (k, &v)| if v > b.1 { (k, v) } else { b },
                );
            (v > 0.0).then_some(best as u32)
        })
        .collect()
}

/// [`PhotoTruthQuality`] of `segment_sets`, said on stderr too.
fn photo_truth_quality(
    a: &EvalColorsConfig,
    inputs: &Inputs,
    oracle_scores: &[f32],
    c: usize,
    segment_sets: &[(PathBuf, Segments)],
) -> anyhow::Result<PhotoTruthQuality> {
    let lifted = lifted_classes(oracle_scores, c);
    if let Some(p) = &a.photo_classes_out {
        write_photo_classes(p, &lifted)?;
    }
    let colour = observed_truth(inputs)?;
    let both: Vec<bool> = lifted
        .iter()
        .zip(&colour)
        .filter(|(a, b)| a.is_some() && b.is_some())
        .map(|(a, b)| a == b)
        .collect();
    let agree = both.iter().filter(|&&x| x).count() as f64 / both.len().max(1) as f64;
    let neighbour_agreement =
        crate::segment_limits::neighbour_agreement(&inputs.gaussians.means, &lifted, &[8, 16])?;
    let purity = segment_sets
        .iter()
        .map(|(_, s)| crate::segment_quality::purity(&lifted, &s.segments))
        .collect::<slag_common::Result<Vec<_>>>()?;
    for ((p, _), q) in segment_sets.iter().zip(&purity) {
        eprintln!(
            "segments {}: purity {:.4} against the lifted photo classes",
            p.display(),
            q.purity
        );
    }
    for n in &neighbour_agreement {
        eprintln!(
            "lifted photo classes, k = {}: {:.4} of the nearest neighbours share a Gaussian's \
             class; {:.4} hold their ball's majority; {:.4} equal the SH-DC class",
            n.k, n.same_share, n.local_majority, agree
        );
    }
    let (mut mask_purity, mut mask_evidence) = (None, None);
    if let Some(p) = mask_record_path(a) {
        use crate::segment_limits as lim;
        let record = slag_common::mask_record::MaskRecord::read(&p)?;
        let mp = lim::mask_purity(&lifted, &record)?;
        let ev = lim::mask_evidence(&inputs.gaussians.means, &lifted, &record, 10)?;
        eprintln!(
            "masks' record against the lifted photo classes: mask purity {:.4} (best view) / \
             {:.4} (all slots); disagreement same class {:.3} (> 0.5: {:.3}), different class \
             {:.3} (> 0.5: {:.3})",
            mp.best_view,
            mp.all_slots,
            ev.same_label.mean_disagreement,
            ev.same_label.over_half,
            ev.different_label.mean_disagreement,
            ev.different_label.over_half
        );
        mask_purity = Some(mp);
        mask_evidence = Some(ev);
    }
    Ok(PhotoTruthQuality {
        labelled: lifted.iter().filter(|l| l.is_some()).count(),
        agrees_with_colour_truth: agree,
        neighbour_agreement,
        purity,
        mask_purity,
        mask_evidence,
    })
}

/// What the held-out pass reads of the encoder's report.json.
#[derive(Debug, Default)]
pub(crate) struct ReportSettings {
    /// `inputs.every`.
    every: Option<usize>,
    /// `inputs.hold_out_every`: the held-out step, when the encode held views out itself.
    hold_out_every: Option<usize>,
    /// `parameters.raster_scale`.
    raster_scale: Option<f64>,
    /// `view_selection.chosen`: the encoded views' names.
    chosen: Option<Vec<String>>,
}

/// The settings of the report.json beside `embeddings`, if there is one.
pub(crate) fn report_settings(embeddings: &Path) -> anyhow::Result<ReportSettings> {
    let path = embeddings
        .parent()
        .unwrap_or(Path::new("."))
        .join("report.json");
    if !path.exists() {
        return Ok(ReportSettings::default());
    }
    let text =
        std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let v: serde_json::Value = serde_json::from_str(&text).map_err(|e| {
        Error::param(
            "every",
            "unknown",
            format!(
                "every and raster_scale given, as {} is not JSON ({e})",
                path.display()
            ),
        )
    })?;
    Ok(ReportSettings {
        every: v["inputs"]["every"].as_u64().map(|e| e as usize),
        hold_out_every: v["inputs"]["hold_out_every"].as_u64().map(|e| e as usize),
        raster_scale: v["parameters"]["raster_scale"].as_f64(),
        chosen: v["view_selection"]["chosen"].as_array().map(|a| {
            a.iter()
                .filter_map(|n| n.as_str().map(str::to_string))
                .collect()
        }),
    })
}

/// The held-out step: the report's `hold_out_every` when the encode held views out itself
/// (`every` given must then agree with it), else the encoder's `every` (given, or the
/// report's).
///
/// Errors: [`Error::Param`] `every` when the given step contradicts the report, or none is
/// known.
pub(crate) fn held_out_step(
    given: Option<usize>,
    r: &ReportSettings,
    embeddings: &Path,
) -> slag_common::Result<usize> {
    let (report_step, what) = match r.hold_out_every {
        Some(h) => (Some(h), "hold_out_every"),
        None => (r.every, "every"),
    };
    match (given, report_step) {
        (Some(f), Some(r)) if f != r => Err(Error::param(
            "every",
            f,
            format!(
                "{r}, the encoder's {what} in the report beside {} (another value would hold \
                 out views that were encoded)",
                embeddings.display()
            ),
        )),
        (Some(e), _) | (None, Some(e)) => Ok(e),
        (None, None) => Err(Error::param(
            "every",
            "unknown",
            format!(
                "the encoder's every (and raster_scale): there is no report.json beside {}",
                embeddings.display()
            ),
        )),
    }
}

/// The views the encoder encoded, which the oracle lifts: the report's chosen views, else the
/// training split of the report's `every` and `hold_out_every` (`every` = the held-out step
/// without a report).
///
/// Errors: as [`slag_encoder::views::training_indices`].
pub(crate) fn encoded_views<'a>(
    views: &'a [camera::View],
    r: &ReportSettings,
    step: usize,
) -> slag_common::Result<Vec<&'a camera::View>> {
    if let Some(names) = &r.chosen {
        return Ok(views.iter().filter(|v| names.contains(&v.name)).collect());
    }
    let every = if r.hold_out_every.is_some() {
        r.every.unwrap_or(1)
    } else {
        step
    };
    let keep = slag_encoder::views::training_indices(views.len(), every, r.hold_out_every)?;
    Ok(keep.iter().map(|&i| &views[i]).collect())
}

/// Runs `eval-colors --held-out` (the 2D protocol of [`crate::heldout`], plus the 3D score).
///
/// Errors: [`Error::Param`] `every` when it is unknown (no report.json beside the embeddings and
/// none given), contradicts the report, is < 2 or holds out no view; [`Error::Param`]
/// `raster_scale` when unknown; the scene's views or photos unreadable, rasterizer failures, and
/// everything [`run`] refuses.
pub fn run_held_out(a: &EvalColorsConfig) -> anyhow::Result<HeldOutOutput> {
    let settings = report_settings(&a.embeddings)?;
    let every = held_out_step(a.every, &settings, &a.embeddings)?;
    let raster_scale = oracle_raster_scale(a, &settings)?;
    let inputs = load_inputs(a)?;
    let colour_3d = colour_3d(&inputs)?;
    let segment_sets = if a.prediction_filtering {
        all_segments(a, inputs.gaussians.len())?
    } else {
        Vec::new()
    };
    let (colour_3d_pf, segment_quality) = segments_scored(&inputs, &segment_sets)?;
    let t0 = Instant::now();
    let views = camera::load_views(&a.scene)?;
    let held = held_out_of(&a.scene, views.len(), every)?;
    let n = inputs.gaussians.len();
    let c = inputs.classes.len();
    let names = &inputs.classes.names;
    let slag_scores = heldout::gaussian_scores(&inputs.emb, &inputs.text_embeds, n)?;
    let mut rasterizer = make_rasterizer(a.rasterizer, &inputs.gaussians)?;

    let encoded = encoded_views(&views, &settings, every)?;
    let oracle = lift_oracle(&inputs, rasterizer.as_mut(), &encoded, raster_scale)?;
    let oracle_scores = oracle.scores();
    let photo_truth = if segment_sets.is_empty() {
        None
    } else {
        Some(photo_truth_quality(
            a,
            &inputs,
            &oracle_scores,
            c,
            &segment_sets,
        )?)
    };
    let variants = held_out_variants(a, &inputs, &slag_scores, &segment_sets)?;

    // Held-out views at full resolution: slag, the oracle and the variants on the same pixels.
    let mut tables: Vec<&[f32]> = vec![&slag_scores, &oracle_scores];
    tables.extend(variants.iter().map(|v| v.scores.as_slice()));
    let held_views: Vec<&camera::View> = held.iter().map(|&i| &views[i]).collect();
    let tally = tally_held_out(&inputs, rasterizer.as_mut(), &held_views, &tables)?;
    let slag = tally.score(&tally.predictors[0], names);
    let oracle_score = tally.score(&tally.predictors[1], names);
    let majority = tally.score(&tally.majority(), names);
    let variants = variants
        .into_iter()
        .zip(&tally.predictors[2..])
        .map(|(v, cf)| v.scored(tally.score(cf, names)))
        .collect();
    let slag_over_oracle = miou_ratio(slag.miou, oracle_score.miou);
    let held_out = HeldOutEval {
        every,
        held_out_views: held.iter().map(|&i| views[i].name.clone()).collect(),
        encoded_views: encoded.len(),
        oracle_raster_scale: raster_scale,
        rasterizer: rasterizer.name().to_string(),
        alpha_min: heldout::ALPHA_MIN,
        pixels: tally.pixels,
        counted_pixels: tally.counted(),
        miou_min_class_fraction: crate::MIOU_MIN_CLASS_FRACTION,
        miou_classes: slag.miou_classes(),
        majority_class: names[tally.majority_class()].clone(),
        slag,
        majority,
        oracle: oracle_score,
        oracle_observed_gaussians: oracle.observed(),
        observed_gaussians: inputs.emb.len(),
        slag_over_oracle,
        variants,
        seconds: t0.elapsed().as_secs_f64(),
    };
    Ok(HeldOutOutput {
        held_out,
        colour_3d,
        colour_3d_pf,
        segment_quality,
        photo_truth,
    })
}

/// With segments (`segment_sets`, the first the main set): the 3D colour score after
/// prediction filtering by the main set, and every set's quality; `None` and nothing without.
fn segments_scored(
    inputs: &Inputs,
    segment_sets: &[(PathBuf, Segments)],
) -> anyhow::Result<(Option<crate::ColourEval>, Vec<SegmentQuality>)> {
    let colour_3d_pf = match segment_sets.first() {
        Some((_, s)) => Some(colour_3d_pf(inputs, s)?),
        None => None,
    };
    let quality = segment_sets
        .iter()
        .map(|(p, s)| segment_quality(inputs, p, s))
        .collect::<anyhow::Result<Vec<_>>>()?;
    Ok((colour_3d_pf, quality))
}

/// The raster scale of the oracle's lifting: `a.raster_scale`, else the encoder's, from the
/// report beside the embeddings. Errors: neither ([`Error::Param`] `raster_scale`).
fn oracle_raster_scale(a: &EvalColorsConfig, settings: &ReportSettings) -> anyhow::Result<f64> {
    Ok(a.raster_scale.or(settings.raster_scale).ok_or_else(|| {
        Error::param(
            "raster_scale",
            "unknown",
            format!(
                "the encoder's raster_scale: the report beside {} has none",
                a.embeddings.display()
            ),
        )
    })?)
}

/// `miou / reference`, when both are known and the reference is above 0.
fn miou_ratio(miou: Option<f64>, reference: Option<f64>) -> Option<f64> {
    match (miou, reference) {
        (Some(s), Some(o)) if o > 0.0 => Some(s / o),
        _ => None,
    }
}

/// The predictors scored beside slag's: the aggregation variants
/// ([`crate::heldout_variants::variant_tables`]), then, with segments, the prediction-filtering
/// ones ([`crate::pf_variants::pf_tables`]).
///
/// Errors: those of both.
fn held_out_variants(
    a: &EvalColorsConfig,
    inputs: &Inputs,
    slag_scores: &[f32],
    segment_sets: &[(PathBuf, Segments)],
) -> anyhow::Result<Vec<crate::heldout_variants::VariantTable>> {
    let n = inputs.gaussians.len();
    let mut variants = crate::heldout_variants::variant_tables(
        &a.embeddings,
        &a.compare,
        slag_scores,
        &inputs.text_embeds,
        n,
    )?;
    if !segment_sets.is_empty() {
        let pf = crate::pf_variants::pf_tables(
            &inputs.emb,
            n,
            slag_scores,
            &variants,
            segment_sets,
            inputs.classes.len(),
        )?;
        variants.extend(pf);
    }
    Ok(variants)
}

/// The held-out view indices of a scene of `views` views at step `every`.
///
/// Errors: [`Error::Param`] `every` when it holds out no view.
fn held_out_of(scene: &Path, views: usize, every: usize) -> anyhow::Result<Vec<usize>> {
    let held = slag_encoder::views::held_out_indices(views, every)?;
    if held.is_empty() {
        return Err(Error::param(
            "every",
            every,
            format!(
                "a smaller every: {} has {views} views, none with an index ≡ {} (mod {every})",
                scene.display(),
                every / 2
            ),
        )
        .into());
    }
    Ok(held)
}

/// The oracle: the encoded views' photo classes lifted onto the Gaussians at the encoder's
/// raster scale.
///
/// Errors: unreadable photos, rasterizer failures.
fn lift_oracle(
    inputs: &Inputs,
    rasterizer: &mut dyn WeightRasterizer,
    encoded: &[&camera::View],
    raster_scale: f64,
) -> anyhow::Result<heldout::OracleLifting> {
    let mut oracle = heldout::OracleLifting::new(inputs.gaussians.len(), inputs.classes.len())?;
    for v in encoded {
        let intr = slag_encoder::raster::raster_intrinsics(&v.intrinsics, raster_scale)?;
        let photo = slag_encoder::pipeline::read_image(v)?;
        let truth = heldout::photo_classes(&inputs.classes, &photo, intr.width, intr.height)?;
        oracle
            .add_view(rasterizer, &intr, &v.world_to_camera, &truth)
            .with_context(|| format!("oracle lifting of view {}", v.name))?;
    }
    Ok(oracle)
}

/// Every score table of `tables` on the pixels of the held-out `views`, rendered at full
/// resolution against each photo's classes.
///
/// Errors: unreadable photos, rasterizer failures, tables of another size.
fn tally_held_out(
    inputs: &Inputs,
    rasterizer: &mut dyn WeightRasterizer,
    views: &[&camera::View],
    tables: &[&[f32]],
) -> anyhow::Result<heldout::HeldOutTally> {
    let mut tally = heldout::HeldOutTally::new(inputs.classes.len(), tables.len());
    for v in views {
        let intr = slag_encoder::raster::raster_intrinsics(&v.intrinsics, 1.0)?;
        let weights = rasterizer
            .rasterize(&intr, &v.world_to_camera)
            .with_context(|| format!("rendering held-out view {}", v.name))?;
        let photo = slag_encoder::pipeline::read_image(v)?;
        let truth = heldout::photo_classes(&inputs.classes, &photo, intr.width, intr.height)?;
        tally.add_view(&weights, &truth, tables, inputs.gaussians.len())?;
        tracing::info!("held-out view {} scored", v.name);
    }
    Ok(tally)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn lifted_classes_take_the_heaviest_and_round_trip() {
        // Three Gaussians, three classes: class 2, none, class 0 (ties to the smaller).
        let scores = [0.1, 0.2, 0.9, 0.0, 0.0, 0.0, 0.5, 0.5, 0.1];
        let lifted = lifted_classes(&scores, 3);
        assert_eq!(lifted, vec![Some(2), None, Some(0)]);
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("photo.u8");
        write_photo_classes(&p, &lifted).unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), vec![2, NO_PHOTO_CLASS, 0]);
        assert_eq!(read_photo_classes(&p, 3).unwrap(), lifted);
        assert!(read_photo_classes(&p, 4).is_err());
        assert!(write_photo_classes(&p, &[Some(255)]).is_err());
    }
}
