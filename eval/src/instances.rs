//! Instance accuracy of a query's objects against ground-truth instances: **AP50** and **box
//! IoU**, as 3D instance segmentation and detection report them (ScanNet's instance AP at 50 %
//! overlap; the 3D box IoU of detection).
//!
//! - A **ground-truth instance** is a set of the scene's Gaussians with a class and a true
//!   axis-aligned box (on `synth-scene --objects`: one placed box, its shell's Gaussians,
//!   [`slag_encoder::synthetic::PlacedObject`]).
//! - A **predicted instance** is one object of the answer to the prompt naming its class
//!   ([`slag_common::objects::SceneObject`]): its member Gaussians, its box (the AABB of the
//!   members' means) and a confidence (the object's `score_mass`, the answer's own order).
//! - **Overlap** of a prediction and an instance: the IoU of their Gaussian sets,
//!   `|P ∩ T| / |P ∪ T|` ([`member_iou`]). Membership, not boxes, decides a match, as in
//!   ScanNet's benchmark: two touching boxes merged into one object overlap each true box by
//!   less than half when they are of similar size.
//! - **AP per class** ([`average_precision`]): predictions in descending confidence; each is a
//!   true positive when it overlaps a not yet matched instance of its class by ≥ the threshold
//!   (the best such instance), else a false positive; AP is the area under the precision–recall
//!   curve with precision made monotone (all-point interpolation, as PASCAL VOC 2010+ and
//!   ScanNet). A class with instances but no prediction scores 0.
//! - **AP50** ([`InstanceScore::ap50`]): the mean of the per-class APs at overlap 0.5 over the
//!   classes that have ground-truth instances. **Box AP50**: the same with box IoU as the overlap.
//! - **Box IoU** ([`InstanceScore::mean_box_iou`]): per ground-truth instance, the 3D IoU of its
//!   true box with the box of the best-overlapping prediction of its class (0 when there is
//!   none), averaged over the instances.
//! - **The segments against the instances** ([`SegmentsAgainstInstances`]): the segments that
//!   `--smooth segment` joins into objects, measured on their own with every placed box one
//!   label and all other Gaussians (the ground) another: instance purity (the share of Gaussians
//!   whose segment's majority label is theirs, [`crate::segment_quality::purity`]), the
//!   same over the boxes' Gaussians only, and boundary recall (of the neighbour pairs that cross
//!   an instance border, the share that crosses a segment border,
//!   [`crate::segment_quality::boundary_recall`]).

use std::path::{Path, PathBuf};

use slag_common::objects::ObjectParams;
use slag_common::onnx::ExecutionProvider;
use slag_common::{Error, Result};
use slag_encoder::query::{QueryParams, Smooth};

/// An axis-aligned box `[min xyz, max xyz]`, scene frame, scene units.
pub type Aabb = [[f64; 3]; 2];

/// One ground-truth instance.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct TruthInstance {
    /// Class name (the prompt that should find it).
    pub class: String,
    /// True box.
    pub aabb: Aabb,
    /// Its Gaussians' ids (vertex indices of the scene's `.ply`), ascending, no duplicates.
    #[serde(skip)]
    pub members: Vec<u32>,
}

/// One predicted instance (an object of the answer to its class's prompt).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct PredictedInstance {
    /// Class name (the prompt whose answer holds it).
    pub class: String,
    /// Confidence; higher ranks first.
    pub score: f64,
    /// Box of its members' means.
    pub aabb: Aabb,
    /// Its Gaussians' ids, ascending, no duplicates.
    #[serde(skip)]
    pub members: Vec<u32>,
}

/// One class's average precision.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ClassAp {
    /// Class name.
    pub class: String,
    /// Ground-truth instances of the class.
    pub instances: usize,
    /// Predictions of the class.
    pub predictions: usize,
    /// Predictions matched to an instance (membership IoU ≥ the threshold).
    pub true_positives: usize,
    /// AP with membership IoU as the overlap.
    pub ap: f64,
    /// AP with box IoU as the overlap.
    pub box_ap: f64,
}

/// The instance scores of one set of predictions.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct InstanceScore {
    /// Overlap a match needs (0.5 for AP50).
    pub iou_threshold: f64,
    /// Mean AP over the classes with ground-truth instances, membership overlap.
    pub ap50: f64,
    /// The same with box IoU as the overlap.
    pub box_ap50: f64,
    /// Mean over the ground-truth instances of the box IoU with the best-overlapping prediction
    /// of its class (0 when none).
    pub mean_box_iou: f64,
    /// Per class, in the order classes first appear among the instances.
    pub classes: Vec<ClassAp>,
    /// Per ground-truth instance (the order given): the membership IoU and box IoU of the
    /// best-overlapping prediction of its class (0 when none).
    pub instances: Vec<InstanceMatch>,
}

/// How well one ground-truth instance was found.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct InstanceMatch {
    /// Class name.
    pub class: String,
    /// True box.
    pub aabb: Aabb,
    /// Membership IoU of the best-overlapping prediction of its class.
    pub iou: f64,
    /// Box IoU of that prediction.
    pub box_iou: f64,
    /// That prediction's box, if any.
    pub predicted_aabb: Option<Aabb>,
}

/// 3D IoU of two axis-aligned boxes; 0 when either has no volume.
pub fn box_iou(a: &Aabb, b: &Aabb) -> f64 {
    let vol = |x: &Aabb| {
        (0..3)
            .map(|k| (x[1][k] - x[0][k]).max(0.0))
            .product::<f64>()
    };
    let inter: f64 = (0..3)
        .map(|k| (a[1][k].min(b[1][k]) - a[0][k].max(b[0][k])).max(0.0))
        .product();
    let union = vol(a) + vol(b) - inter;
    if union > 0.0 { inter / union } else { 0.0 }
}

/// IoU of two ascending, duplicate-free id lists; 0 when both are empty.
pub fn member_iou(a: &[u32], b: &[u32]) -> f64 {
    let (mut i, mut j, mut inter) = (0usize, 0usize, 0usize);
    while i < a.len() && j < b.len() {
        match a[i].cmp(&b[j]) {
            std::cmp::Ordering::Less => i += 1,
            std::cmp::Ordering::Greater => j += 1,
            std::cmp::Ordering::Equal => {
                inter += 1;
                i += 1;
                j += 1;
            }
        }
    }
    let union = a.len() + b.len() - inter;
    if union > 0 {
        inter as f64 / union as f64
    } else {
        0.0
    }
}

/// Average precision of one class: `overlaps[p][t]` is the overlap of prediction `p` (already in
/// descending confidence) with instance `t`; greedy matching at `threshold`, all-point
/// interpolated area under the precision–recall curve. 0 when there are no instances.
pub fn average_precision(overlaps: &[Vec<f64>], instances: usize, threshold: f64) -> (f64, usize) {
    if instances == 0 {
        return (0.0, 0);
    }
    let mut taken = vec![false; instances];
    let mut tp_flags = Vec::with_capacity(overlaps.len());
    for row in overlaps {
        let best = (0..instances)
            .filter(|&t| !taken[t] && row[t] >= threshold)
            .max_by(|&a, &b| row[a].total_cmp(&row[b]));
        if let Some(t) = best {
            taken[t] = true;
        }
        tp_flags.push(best.is_some());
    }
    // Precision and recall after each prediction.
    let (mut tp, mut points) = (0usize, Vec::with_capacity(tp_flags.len()));
    for (k, &hit) in tp_flags.iter().enumerate() {
        tp += usize::from(hit);
        points.push((tp as f64 / instances as f64, tp as f64 / (k + 1) as f64));
    }
    // All-point interpolation: precision at recall r is the best precision at any recall ≥ r.
    let mut ap = 0.0;
    let mut prev_recall = 0.0;
    for (k, &(recall, _)) in points.iter().enumerate() {
        if recall > prev_recall {
            let p = points[k..].iter().map(|x| x.1).fold(0.0, f64::max);
            ap += (recall - prev_recall) * p;
            prev_recall = recall;
        }
    }
    (ap, tp)
}

/// Scores `predictions` against `truth` (module doc) at overlap `iou_threshold` (0.5 for AP50).
///
/// Errors ([`Error::Param`] `iou_threshold`): a threshold outside (0, 1]; ([`Error::Invalid`])
/// no ground-truth instance.
pub fn score_instances(
    predictions: &[PredictedInstance],
    truth: &[TruthInstance],
    iou_threshold: f64,
) -> Result<InstanceScore> {
    if !(iou_threshold > 0.0 && iou_threshold <= 1.0) {
        return Err(Error::param(
            "iou_threshold",
            iou_threshold,
            "an overlap in (0, 1], e.g. 0.5 for AP50",
        ));
    }
    if truth.is_empty() {
        return Err(Error::Invalid(
            "no ground-truth instance to score against: write the scene with objects \
             (synth-scene --objects K)"
                .into(),
        ));
    }
    let mut class_names: Vec<&str> = Vec::new();
    for t in truth {
        if !class_names.contains(&t.class.as_str()) {
            class_names.push(&t.class);
        }
    }
    let classes = class_names
        .iter()
        .map(|&c| class_ap(c, predictions, truth, iou_threshold))
        .collect::<Vec<_>>();
    let instances: Vec<InstanceMatch> = truth.iter().map(|t| best_match(t, predictions)).collect();
    let mean = |v: &mut dyn Iterator<Item = f64>, n: usize| v.sum::<f64>() / n as f64;
    Ok(InstanceScore {
        iou_threshold,
        ap50: mean(&mut classes.iter().map(|c| c.ap), classes.len()),
        box_ap50: mean(&mut classes.iter().map(|c| c.box_ap), classes.len()),
        mean_box_iou: mean(&mut instances.iter().map(|i| i.box_iou), instances.len()),
        classes,
        instances,
    })
}

/// AP of one class, with membership and with box overlap.
fn class_ap(
    class: &str,
    predictions: &[PredictedInstance],
    truth: &[TruthInstance],
    threshold: f64,
) -> ClassAp {
    let mut preds: Vec<&PredictedInstance> =
        predictions.iter().filter(|p| p.class == class).collect();
    // Descending confidence; ties keep the given order (stable sort).
    preds.sort_by(|a, b| b.score.total_cmp(&a.score));
    let truths: Vec<&TruthInstance> = truth.iter().filter(|t| t.class == class).collect();
    let overlaps = |f: &dyn Fn(&PredictedInstance, &TruthInstance) -> f64| -> Vec<Vec<f64>> {
        preds
            .iter()
            .map(|p| truths.iter().map(|t| f(p, t)).collect())
            .collect()
    };
    let (ap, tp) = average_precision(
        &overlaps(&|p, t| member_iou(&p.members, &t.members)),
        truths.len(),
        threshold,
    );
    let (box_ap, _) = average_precision(
        &overlaps(&|p, t| box_iou(&p.aabb, &t.aabb)),
        truths.len(),
        threshold,
    );
    ClassAp {
        class: class.to_string(),
        instances: truths.len(),
        predictions: preds.len(),
        true_positives: tp,
        ap,
        box_ap,
    }
}

/// The prediction of `t`'s class that overlaps it most (membership IoU; ties: the first given).
fn best_match(t: &TruthInstance, predictions: &[PredictedInstance]) -> InstanceMatch {
    let best = predictions
        .iter()
        .filter(|p| p.class == t.class)
        .map(|p| (member_iou(&p.members, &t.members), p))
        .fold(None::<(f64, &PredictedInstance)>, |acc, x| match acc {
            Some(a) if a.0 >= x.0 => Some(a),
            _ => Some(x),
        });
    InstanceMatch {
        class: t.class.clone(),
        aabb: t.aabb,
        iou: best.map_or(0.0, |b| b.0),
        box_iou: best.map_or(0.0, |b| box_iou(&b.1.aabb, &t.aabb)),
        predicted_aabb: best.map(|b| b.1.aabb),
    }
}

/// What `slag-encoder eval-objects` evaluates: the objects of each placed colour's query on a
/// `synth-scene --objects` scene, against the placed boxes.
#[derive(Debug, Clone, PartialEq)]
pub struct EvalObjectsConfig {
    /// The scene folder `synth-scene --objects` wrote (`objects.json`, `point_cloud.ply`).
    pub scene: PathBuf,
    /// The embeddings of that scene, made with color-clip, either form
    /// (`slag_common::forms::read_rows`): `mixture.safetensors` or the dense
    /// `embeddings.safetensors`.
    pub embeddings: PathBuf,
    /// Folder holding color-clip's text tower and tokenizer (`color-clip-textual.onnx`,
    /// `clip-tokenizer.json`).
    pub color_clip: PathBuf,
    /// How matches are grouped into objects (scene units).
    pub objects: ObjectParams,
    /// Scored once per entry: each Gaussian's own score, and/or its segment's mean.
    pub smooth: Vec<Smooth>,
    /// Segments for [`Smooth::Segment`]; `None`: `segments.safetensors` beside the embeddings.
    pub segments: Option<PathBuf>,
    /// ONNX Runtime execution provider of the text tower.
    pub ep: ExecutionProvider,
}

/// The instance scores of one smoothing.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SmoothScore {
    /// The query's score smoothing.
    pub smooth: Smooth,
    /// Objects returned per class prompt, in the classes' order.
    pub objects: Vec<(String, usize)>,
    /// AP50, box AP50, box IoU and their details.
    pub score: InstanceScore,
}

/// Neighbours per Gaussian for [`SegmentsAgainstInstances::boundary_recall`].
pub const BOUNDARY_NEIGHBOURS: usize = 8;

/// The segments measured against the ground-truth instances (module doc).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SegmentsAgainstInstances {
    /// The segments file.
    pub source: PathBuf,
    /// Segments in it.
    pub segments: u32,
    /// Purity over every Gaussian of the scene: each placed box one label, the rest (the
    /// ground) one more.
    pub purity: crate::segment_quality::Purity,
    /// Purity over the placed boxes' Gaussians only, the ground left out: whether boxes of
    /// different classes share segments.
    pub object_purity: crate::segment_quality::Purity,
    /// Boundary recall over each Gaussian's [`BOUNDARY_NEIGHBOURS`] nearest neighbours within
    /// the object gap (scene units).
    pub boundary_recall: crate::segment_quality::BoundaryRecall,
}

/// What `eval-objects` prints.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ObjectsEval {
    /// Placed objects (ground-truth instances).
    pub instances: usize,
    /// The segments against the instances, when a segments file is given or lies beside the
    /// embeddings (`segments.safetensors`).
    pub segments: Option<SegmentsAgainstInstances>,
    /// The single-linkage gap given; `None`: each answer derived its own from its matches'
    /// spacing ([`slag_common::objects::derived_gap`]).
    pub object_gap: Option<f32>,
    /// Smallest object returned, Gaussians.
    pub object_min_gaussians: usize,
    /// One score per smoothing asked for.
    pub runs: Vec<SmoothScore>,
}

/// The ground-truth instances of a `synth-scene --objects` scene, from its `objects.json`.
///
/// Errors: the file missing or not the list `synth-scene` writes ([`Error::Invalid`], also for
/// a file of an older `synth-scene` without the Gaussians' ranges: write the scene again).
pub fn synthetic_truth(scene: &Path) -> Result<Vec<TruthInstance>> {
    #[derive(serde::Deserialize)]
    struct Placed {
        name: String,
        aabb: Aabb,
        gaussians: Option<[u32; 2]>,
    }
    let path = scene.join("objects.json");
    let bytes = std::fs::read(&path).map_err(|e| Error::io(&path, e))?;
    let placed: Vec<Placed> = serde_json::from_slice(&bytes).map_err(|e| {
        Error::Invalid(format!(
            "{} is not the object list synth-scene writes ({e}); write the scene with \
             `synth-scene --objects K`",
            path.display()
        ))
    })?;
    placed
        .into_iter()
        .map(|p| {
            let [start, end] = p.gaussians.ok_or_else(|| {
                Error::Invalid(format!(
                    "{} has no Gaussian ranges (an older synth-scene); write the scene again",
                    path.display()
                ))
            })?;
            Ok(TruthInstance {
                class: p.name,
                aabb: p.aabb,
                members: (start..end).collect(),
            })
        })
        .collect()
}

/// Queries every class of the placed objects on `c.embeddings` (with the scene's `.ply` for
/// the opacities, as `slag-encoder query --ply` does), once per smoothing, and scores the
/// answers' objects at overlap 0.5 ([`score_instances`]).
///
/// Errors: [`synthetic_truth`]'s; the query's (models, embeddings, segments for
/// [`Smooth::Segment`]); [`Error::Param`] `smooth` for an empty list.
pub fn evaluate_synthetic_objects(c: &EvalObjectsConfig) -> Result<ObjectsEval> {
    if c.smooth.is_empty() {
        return Err(Error::param(
            "smooth",
            "none",
            "at least one smoothing to score (none, segment)",
        ));
    }
    let truth = synthetic_truth(&c.scene)?;
    let mut classes: Vec<String> = Vec::new();
    for t in &truth {
        if !classes.contains(&t.class) {
            classes.push(t.class.clone());
        }
    }
    let mut runs = Vec::with_capacity(c.smooth.len());
    for &smooth in &c.smooth {
        let mut predictions = Vec::new();
        let mut counts = Vec::new();
        for class in &classes {
            let q = QueryParams {
                ply: Some(c.scene.join("point_cloud.ply")),
                objects: c.objects,
                smooth,
                segments: c.segments.clone(),
                ep: c.ep,
                ..QueryParams::new(
                    &c.embeddings,
                    c.color_clip.join("color-clip-textual.onnx"),
                    c.color_clip.join("clip-tokenizer.json"),
                    class.as_str(),
                )
            };
            let answer = slag_encoder::query::run(&q)?;
            counts.push((class.clone(), answer.objects.len()));
            predictions.extend(answer.objects.iter().zip(answer.object_members).map(
                |(o, members)| PredictedInstance {
                    class: class.clone(),
                    score: f64::from(o.score_mass),
                    aabb: o.aabb.map(|c| c.map(f64::from)),
                    members,
                },
            ));
        }
        runs.push(SmoothScore {
            smooth,
            objects: counts,
            score: score_instances(&predictions, &truth, 0.5)?,
        });
    }
    Ok(ObjectsEval {
        instances: truth.len(),
        segments: segments_against_instances(c, &truth)?,
        object_gap: c.objects.gap,
        object_min_gaussians: c.objects.min_gaussians,
        runs,
    })
}

/// Measures the segments of `c` (its `segments`, else `segments.safetensors` beside the
/// embeddings; `None` when neither exists) against `truth` on the scene's Gaussians.
///
/// Errors: an unreadable segments file or `.ply`; segments of another Gaussian count than the
/// scene's ([`Error::Invalid`]: segment the scene the embeddings were made from).
fn segments_against_instances(
    c: &EvalObjectsConfig,
    truth: &[TruthInstance],
) -> Result<Option<SegmentsAgainstInstances>> {
    let path = c.segments.clone().unwrap_or_else(|| {
        c.embeddings
            .parent()
            .unwrap_or(Path::new("."))
            .join(slag_common::segments::FILE_NAME)
    });
    if c.segments.is_none() && !path.exists() {
        return Ok(None);
    }
    let segments = slag_common::segments::Segments::read(&path)?;
    let gaussians = slag_common::scene::load_ply(
        &c.scene.join("point_cloud.ply"),
        slag_common::scene::PlyLoadOptions { colours: false },
    )?;
    Ok(Some(measure_segments(
        &path,
        &segments,
        &gaussians.means,
        truth,
        c.objects
            .gap
            .unwrap_or_else(|| slag_common::objects::derived_gap(&gaussians.means)),
    )?))
}

/// [`SegmentsAgainstInstances`] of `segments` (read from `source`) for Gaussians at `means`
/// (scene units) whose instances are `truth`; neighbours within `radius` count for boundary
/// recall.
///
/// Errors: segments and means of different counts, or an instance member past the end
/// ([`Error::Invalid`]).
pub fn measure_segments(
    source: &Path,
    segments: &slag_common::segments::Segments,
    means: &[[f32; 3]],
    truth: &[TruthInstance],
    radius: f32,
) -> Result<SegmentsAgainstInstances> {
    use crate::segment_quality::{boundary_recall, purity};
    let n = means.len();
    if segments.segments.len() != n {
        return Err(Error::Invalid(format!(
            "{} segments {} Gaussians but the scene has {n}; segment the scene the embeddings \
             were made from",
            source.display(),
            segments.segments.len()
        )));
    }
    let ground = truth.len() as u32;
    let mut labels = vec![Some(ground); n];
    for (k, t) in truth.iter().enumerate() {
        for &m in &t.members {
            let slot = labels.get_mut(m as usize).ok_or_else(|| {
                Error::Invalid(format!(
                    "instance {k} ({}) names Gaussian {m} of {n}: the scene's objects.json does \
                     not belong to its point_cloud.ply",
                    t.class
                ))
            })?;
            *slot = Some(k as u32);
        }
    }
    let objects_only: Vec<Option<u32>> =
        labels.iter().map(|l| l.filter(|&l| l != ground)).collect();
    Ok(SegmentsAgainstInstances {
        source: source.to_path_buf(),
        segments: segments.segment_count,
        purity: purity(&labels, &segments.segments)?,
        object_purity: purity(&objects_only, &segments.segments)?,
        boundary_recall: boundary_recall(
            means,
            &labels,
            &segments.segments,
            BOUNDARY_NEIGHBOURS,
            radius,
        )?,
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn truth(class: &str, aabb: Aabb, members: std::ops::Range<u32>) -> TruthInstance {
        TruthInstance {
            class: class.into(),
            aabb,
            members: members.collect(),
        }
    }

    fn predicted(class: &str, score: f64, aabb: Aabb, members: Vec<u32>) -> PredictedInstance {
        PredictedInstance {
            class: class.into(),
            score,
            aabb,
            members,
        }
    }

    /// Two touching boxes (x in 0..1 and 1..2, on a 0.1 grid) on a strip of ground below them
    /// (z = −0.1): Gaussians 0..200 box A, 200..400 box B, 400..600 ground.
    fn touching_scene() -> (Vec<[f32; 3]>, Vec<TruthInstance>) {
        let mut means = Vec::new();
        for (x0, z) in [(0.0f32, 0.0f32), (1.0, 0.0)] {
            for i in 0..10 {
                for j in 0..20 {
                    means.push([x0 + i as f32 * 0.1, j as f32 * 0.1, z]);
                }
            }
        }
        for i in 0..20 {
            for j in 0..10 {
                means.push([i as f32 * 0.1, j as f32 * 0.2, -0.1]);
            }
        }
        let aabb = [[0.0; 3], [1.0; 3]];
        (
            means,
            vec![truth("red", aabb, 0..200), truth("blue", aabb, 200..400)],
        )
    }

    fn segs(segments: Vec<u32>) -> slag_common::segments::Segments {
        let segment_count = segments.iter().max().map_or(0, |m| m + 1);
        slag_common::segments::Segments {
            segments,
            segment_count,
            ..Default::default()
        }
    }

    #[test]
    fn segments_are_measured_against_the_instances_and_the_ground() {
        let (means, truth) = touching_scene();
        let p = Path::new("s.safetensors");
        // One segment per box and one for the ground: pure, every border a segment border.
        let exact = segs((0..600).map(|i| i / 200).collect());
        let m = measure_segments(p, &exact, &means, &truth, 0.15).unwrap();
        assert_eq!(
            (m.segments, m.purity.counted, m.object_purity.counted),
            (3, 600, 400)
        );
        assert_eq!((m.purity.purity, m.object_purity.purity), (1.0, 1.0));
        assert!(m.boundary_recall.boundary_pairs > 0);
        assert_eq!(m.boundary_recall.recall, 1.0);
        // The two boxes joined (the failure touching objects invite): half of the boxes'
        // Gaussians are impure, the border between them is lost; the ground stays apart.
        let merged = segs((0..600).map(|i| u32::from(i >= 400)).collect());
        let j = measure_segments(p, &merged, &means, &truth, 0.15).unwrap();
        assert_eq!(j.object_purity.purity, 0.5);
        assert!((j.purity.purity - 400.0 / 600.0).abs() < 1e-12);
        assert!(j.boundary_recall.recall > 0.0 && j.boundary_recall.recall < 1.0);
        // Everything one segment: only the largest label is pure, no border is kept.
        let one = segs(vec![0; 600]);
        let o = measure_segments(p, &one, &means, &truth, 0.15).unwrap();
        assert_eq!(o.boundary_recall.recall, 0.0);
        // Segments of another scene are refused.
        let e = measure_segments(p, &segs(vec![0; 10]), &means, &truth, 0.15).unwrap_err();
        assert!(e.to_string().contains("segment the scene"), "{e}");
    }

    #[test]
    fn box_and_member_iou() {
        let a = [[0.0, 0.0, 0.0], [2.0, 1.0, 1.0]];
        let b = [[1.0, 0.0, 0.0], [3.0, 1.0, 1.0]];
        assert!((box_iou(&a, &b) - 1.0 / 3.0).abs() < 1e-12);
        assert_eq!(box_iou(&a, &a), 1.0);
        assert_eq!(box_iou(&a, &[[5.0; 3], [6.0; 3]]), 0.0);
        assert_eq!(box_iou(&[[0.0; 3], [0.0; 3]], &[[0.0; 3], [0.0; 3]]), 0.0);
        assert_eq!(member_iou(&[1, 2, 3, 4], &[3, 4, 5]), 2.0 / 5.0);
        assert_eq!(member_iou(&[], &[]), 0.0);
    }

    #[test]
    fn precision_recall_area() {
        // Two instances; predictions: hit, miss, hit. Precision 1 at recall 0.5, then 2/3 at
        // recall 1: AP = 0.5 · 1 + 0.5 · 2/3.
        let o = vec![vec![0.9, 0.0], vec![0.1, 0.2], vec![0.0, 0.6]];
        let (ap, tp) = average_precision(&o, 2, 0.5);
        assert_eq!(tp, 2);
        assert!((ap - (0.5 + 1.0 / 3.0)).abs() < 1e-12, "{ap}");
        // The same predictions in a worse order (miss first) score lower.
        let worse = vec![o[1].clone(), o[0].clone(), o[2].clone()];
        assert!(average_precision(&worse, 2, 0.5).0 < ap);
        // One prediction cannot match two instances.
        let (ap1, tp1) = average_precision(&[vec![0.9, 0.8]], 2, 0.5);
        assert_eq!((ap1, tp1), (0.5, 1));
        assert_eq!(average_precision(&[], 3, 0.5), (0.0, 0));
    }

    #[test]
    fn bad_thresholds_and_empty_truth_are_refused() {
        let t = [truth("red", [[0.0; 3], [1.0; 3]], 0..4)];
        for bad in [0.0, -1.0, 1.5, f64::NAN] {
            assert!(matches!(
                score_instances(&[], &t, bad),
                Err(Error::Param {
                    name: "iou_threshold",
                    ..
                })
            ));
        }
        assert!(matches!(
            score_instances(&[], &[], 0.5),
            Err(Error::Invalid(_))
        ));
        // No prediction at all: AP 0 and box IoU 0, not an error.
        let s = score_instances(&[], &t, 0.5).unwrap();
        assert_eq!((s.ap50, s.box_ap50, s.mean_box_iou), (0.0, 0.0, 0.0));
    }
    #[test]
    fn touching_boxes_perfect_predictions_score_1_and_a_merged_pair_less() {
        use slag_encoder::synthetic::{
            SyntheticSceneParams, scene_with_instances, touching_layout,
        };
        let p = SyntheticSceneParams {
            gaussians: 4000,
            views: 1,
            width: 8,
            height: 8,
            extent: 20.0,
            seed: 5,
            ..Default::default()
        };
        let placed = touching_layout(6, p.extent).unwrap();
        let (g, ranges) = scene_with_instances(&p, &placed);
        assert_eq!(ranges.last().unwrap().end, g.len());
        let boxes: Vec<Aabb> = placed.iter().map(|o| o.aabb()).collect();
        let inside = |m: [f32; 3], b: &Aabb, tol: f64| {
            (0..3).all(|a| f64::from(m[a]) >= b[0][a] - tol && f64::from(m[a]) <= b[1][a] + tol)
        };
        for (k, r) in ranges.iter().enumerate() {
            assert!(r.len() > 20, "box {k}: {} Gaussians", r.len());
            for i in r.clone() {
                assert!(
                    inside(g.means[i], &boxes[k], 1e-4),
                    "box {k}: {:?}",
                    g.means[i]
                );
                // A shared wall holds no Gaussians: none lies in or on a touching box.
                for (j, b) in boxes.iter().enumerate().filter(|&(j, _)| j != k) {
                    assert!(!inside(g.means[i], b, 1e-5), "box {k} Gaussian on box {j}");
                }
            }
        }
        // The pairs touch: red's +x wall is blue's -x wall.
        assert!((boxes[0][1][0] - boxes[1][0][0]).abs() < 1e-9);
        let truth: Vec<TruthInstance> = placed
            .iter()
            .zip(&ranges)
            .map(|(o, r)| TruthInstance {
                class: o.name.into(),
                aabb: o.aabb(),
                members: (r.start as u32..r.end as u32).collect(),
            })
            .collect();
        let means_box = |members: &[u32]| -> Aabb {
            let mut b = [[f64::INFINITY; 3], [f64::NEG_INFINITY; 3]];
            for &i in members {
                for (a, &v) in g.means[i as usize].iter().enumerate() {
                    b[0][a] = b[0][a].min(f64::from(v));
                    b[1][a] = b[1][a].max(f64::from(v));
                }
            }
            b
        };
        let perfect: Vec<PredictedInstance> = truth
            .iter()
            .map(|t| predicted(&t.class, 1.0, means_box(&t.members), t.members.clone()))
            .collect();
        let s = score_instances(&perfect, &truth, 0.5).unwrap();
        assert_eq!((s.ap50, s.box_ap50), (1.0, 1.0));
        assert!(s.mean_box_iou > 0.6, "{}", s.mean_box_iou);

        // Red and blue merged into one object, which both prompts return.
        let mut union = truth[0].members.clone();
        union.extend(&truth[1].members);
        union.sort_unstable();
        let merged_box = means_box(&union);
        let mut merged = perfect.clone();
        for k in [0, 1] {
            merged[k].members = union.clone();
            merged[k].aabb = merged_box;
        }
        let m = score_instances(&merged, &truth, 0.5).unwrap();
        let share = |k: usize| truth[k].members.len() as f64 / union.len() as f64;
        let found = [0, 1].iter().filter(|&&k| share(k) >= 0.5).count();
        assert!(found <= 1, "a merged pair cannot match both boxes");
        assert!(
            (m.ap50 - (4 + found) as f64 / 6.0).abs() < 1e-12,
            "{}",
            m.ap50
        );
        assert!(m.ap50 < s.ap50);
        assert!(m.mean_box_iou < s.mean_box_iou);
        assert!((m.instances[0].iou - share(0)).abs() < 1e-12);
    }
}
