//! Colour-classes accuracy: ScanNet-style multi-class mIoU over a scene's Gaussians, with the 12
//! colour words of the color-clip fixture as the classes (`shared/fixtures/clip/color-clip.json`).
//!
//! Protocol (the ScanNet/LERF-style "assign every point the best-matching class text, then score
//! per-class IoU", with colours as classes so that real scenes have a ground truth):
//!
//! - **Ground truth** ([`ground_truth`]): a Gaussian's class is the colour prototype nearest (squared
//!   RGB distance, ties → the lower class index) to its SH-DC colour
//!   `clamp(0.5 + SH_C0 · f_dc, 0, 1)` (INRIA/gsplat convention, `SH_C0 = 0.28209479177387814`).
//!   Gaussians with activated opacity `≤ 0.1` are excluded (`None`): they barely render.
//! - **Prediction** ([`assign`]): an observed Gaussian (a row of the embeddings file) gets the
//!   class whose text embedding has the highest cosine with its embedding `E_k`.
//! - **Scoring** ([`evaluate`]): the universe is the opaque Gaussians (ground truth `Some`). An
//!   opaque Gaussian that the encoder never observed has *no* prediction: it counts as a miss for
//!   its ground-truth class (it enters that class's union, never an intersection), so unobserved
//!   Gaussians lower IoU and accuracy; [`ColourEval::observed_fraction`] says how many there are.
//!   Observed Gaussians that are not opaque are ignored. Per class `c`:
//!   `IoU_c = |pred = c ∧ gt = c| / |pred = c ∨ gt = c|`; `miou` averages `IoU_c` over the classes
//!   holding at least [`MIOU_MIN_CLASS_FRACTION`] of the opaque Gaussians (rarer classes make the
//!   mean noisy; they are still reported individually).
//!
//! The rest of evaluation and research, apart from the paper's stages: [`heldout`] (2D accuracy
//! on views never encoded), [`heldout_variants`] (the aggregation variants scored in the same
//! pass), [`colors`] (`slag-encoder eval-colors`: both protocols on an embeddings file),
//! [`instances`] (`slag-encoder eval-objects`: instance AP50 and box IoU of query answers' objects
//! on a synthetic scene with placed boxes), [`segment_quality`] and [`segment_limits`] (geometric
//! segments against per-Gaussian labels, and what limits their purity).
//!
//! This crate depends on the encoder's library (`slag_encoder`: the rasterizer, the training
//! split [`slag_encoder::views::held_out_indices`], the synthetic scenes
//! [`slag_encoder::synthetic`]), never the other way: the encode pipeline carries no evaluation.

pub mod colors;
pub mod heldout;
pub mod heldout_variants;
pub mod instances;
pub mod object_truth;
pub mod pf_variants;
pub mod segment_limits;
pub mod segment_quality;

use std::path::Path;

use rayon::prelude::*;
use slag_common::embeddings::Embeddings;
use slag_common::scene::Gaussians;
use slag_common::{Error, Result};

/// The zeroth-order real SH basis constant, `1 / (2√π)` (INRIA 3DGS / gsplat `C0`).
pub const SH_C0: f64 = 0.28209479177387814;

/// Gaussians whose activated opacity is at or below this are excluded from the ground truth.
pub const OPACITY_THRESHOLD: f32 = 0.1;

/// A class enters the mean IoU when it holds at least this fraction of the opaque Gaussians.
pub const MIOU_MIN_CLASS_FRACTION: f64 = 0.01;

/// The colour classes of the color-clip fixture: names and RGB prototypes.
#[derive(Debug, Clone, PartialEq)]
pub struct ColorClasses {
    /// Class names (colour words), in class-index order; at most 256.
    pub names: Vec<String>,
    /// One prototype colour per class, linear RGB in `[0, 1]` (the fixture's `prototypes_rgb01`).
    pub prototypes_rgb01: Vec<[f64; 3]>,
}

#[derive(serde::Deserialize)]
struct ColorClipJson {
    classes: Vec<String>,
    prototypes_rgb01: Vec<[f64; 3]>,
}

impl ColorClasses {
    /// Reads `color-clip.json` (fields `classes` and `prototypes_rgb01`; others are ignored).
    ///
    /// Errors: unreadable file ([`Error::Io`]); not JSON, missing fields, class and prototype
    /// counts that differ, no class or more than 256, non-finite prototype values
    /// ([`Error::Format`]).
    pub fn load(path: &Path) -> Result<ColorClasses> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let json: ColorClipJson = serde_json::from_str(&text).map_err(|e| {
            Error::format(
                path,
                format!(
                    "not a color-clip class file ({e}); pass shared/fixtures/clip/color-clip.json"
                ),
            )
        })?;
        let (n, p) = (json.classes.len(), json.prototypes_rgb01.len());
        if n != p || n == 0 || n > 256 {
            return Err(Error::format(
                path,
                format!(
                    "{n} classes and {p} prototypes; expected the same number, 1 to 256; \
                     regenerate the file with shared/fixtures/gen"
                ),
            ));
        }
        if json
            .prototypes_rgb01
            .iter()
            .flatten()
            .any(|v| !v.is_finite())
        {
            return Err(Error::format(path, "a prototype colour is not finite"));
        }
        Ok(ColorClasses {
            names: json.classes,
            prototypes_rgb01: json.prototypes_rgb01,
        })
    }

    /// Number of classes.
    pub fn len(&self) -> usize {
        self.names.len()
    }

    /// True when there is no class.
    pub fn is_empty(&self) -> bool {
        self.names.is_empty()
    }

    /// The class whose prototype is nearest to `rgb01` (squared Euclidean distance in RGB;
    /// ties → the lower index). Returns 0 when there is no class.
    pub fn nearest(&self, rgb01: [f64; 3]) -> u8 {
        let mut best = (0u8, f64::INFINITY);
        for (c, p) in self.prototypes_rgb01.iter().enumerate() {
            let d: f64 = (0..3).map(|i| (rgb01[i] - p[i]).powi(2)).sum();
            if d < best.1 {
                best = (c as u8, d);
            }
        }
        best.0
    }
}

/// The SH-DC colour of a Gaussian, `clamp(0.5 + SH_C0 · f_dc, 0, 1)` per channel (RGB in `[0, 1]`).
pub fn dc_colour(f_dc: [f32; 3]) -> [f64; 3] {
    f_dc.map(|f| (0.5 + SH_C0 * f as f64).clamp(0.0, 1.0))
}

/// Ground-truth colour class of every Gaussian of the scene (`[N]`, `.ply` vertex order):
/// `Some(class)` for opacity `> 0.1`, `None` otherwise (see the module docs).
///
/// Errors: the Gaussians were loaded without SH colours ([`Error::Param`] `colours`: load them
/// with `PlyLoadOptions { colours: true }`), no class or a class without prototype
/// ([`Error::Param`] `classes`), arrays that disagree in length ([`Error::Internal`]).
pub fn ground_truth(classes: &ColorClasses, gaussians: &Gaussians) -> Result<Vec<Option<u8>>> {
    if classes.is_empty() || classes.len() > 256 || classes.prototypes_rgb01.len() != classes.len()
    {
        return Err(Error::param(
            "classes",
            format!(
                "{} colour classes with {} prototypes",
                classes.len(),
                classes.prototypes_rgb01.len()
            ),
            "1 to 256 classes, one prototype each (ColorClasses::load)",
        ));
    }
    let sh = gaussians.sh.as_ref().ok_or_else(|| {
        Error::param(
            "colours",
            false,
            "Gaussians with their SH colours to evaluate colour classes: load the .ply with \
             PlyLoadOptions { colours: true }",
        )
    })?;
    let n = gaussians.opacities.len();
    if sh.coeffs.len() != n * sh.per_channel() * 3 {
        return Err(Error::internal(format!(
            "{n} opacities but {} SH values for degree {}; the Gaussians are inconsistent",
            sh.coeffs.len(),
            sh.degree
        )));
    }
    Ok((0..n)
        .map(|i| {
            (gaussians.opacities[i] > OPACITY_THRESHOLD)
                .then(|| classes.nearest(dc_colour(sh.dc(i))))
        })
        .collect())
}

/// The predicted class of every stored (observed) Gaussian: the index of the class text
/// embedding with the highest cosine to its embedding row (`[embeddings.len()]`, row order).
///
/// Both sides are taken as L2-normalised (embeddings rows are, by the file's contract; pass the
/// text embeddings normalised), so cosine = f32 dot product. Ties → the lower class index.
///
/// Errors: no class or more than 256 ([`Error::Param`] `classes`), a text embedding whose width
/// differs from `embeddings.dim` ([`Error::Mismatch`]), an embeddings matrix whose size is not
/// `len · dim` ([`Error::Internal`]).
pub fn assign(embeddings: &Embeddings, class_text_embeds: &[Vec<f32>]) -> Result<Vec<u8>> {
    let (n, dim) = (embeddings.len(), embeddings.dim);
    if class_text_embeds.is_empty() || class_text_embeds.len() > 256 {
        return Err(Error::param(
            "classes",
            class_text_embeds.len(),
            "1 to 256 class text embeddings (one per colour class)",
        ));
    }
    if let Some((c, t)) = class_text_embeds
        .iter()
        .enumerate()
        .find(|(_, t)| t.len() != dim)
    {
        return Err(Error::mismatch(
            slag_common::Mismatched::EmbeddingWidth,
            format!(
                "class {c} text embedding has {} values but the Gaussian embeddings have \
                 {dim}; encode the texts with the CLIP model that made the embeddings",
                t.len()
            ),
        ));
    }
    if dim == 0 || embeddings.vectors.len() != n * dim {
        return Err(Error::internal(format!(
            "embeddings hold {} values for {n} rows of width {dim}",
            embeddings.vectors.len()
        )));
    }
    Ok(embeddings
        .vectors
        .par_chunks_exact(dim)
        .map(|row| {
            let mut best = (0u8, f32::NEG_INFINITY);
            for (c, t) in class_text_embeds.iter().enumerate() {
                let dot: f32 = row.iter().zip(t).map(|(a, b)| a * b).sum();
                if dot > best.1 {
                    best = (c as u8, dot);
                }
            }
            best.0
        })
        .collect())
}

/// Scores of one colour class.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ClassScore {
    /// Class name (colour word).
    pub name: String,
    /// `|pred = c ∧ gt = c| / |pred = c ∨ gt = c|` over the opaque Gaussians; `None` when the
    /// union is empty (class neither present nor predicted).
    pub iou: Option<f64>,
    /// Opaque Gaussians whose ground truth is this class (observed or not).
    pub gt_count: u64,
    /// Observed opaque Gaussians predicted as this class.
    pub pred_count: u64,
    /// Opaque Gaussians with ground truth and prediction both this class.
    pub intersection: u64,
    /// Whether the class enters [`ColourEval::miou`] (`gt_count ≥ 1 %` of the opaque Gaussians).
    pub in_miou: bool,
}

/// Result of [`evaluate`]; serialises to the run report's JSON.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ColourEval {
    /// Per-class scores, in class-index order.
    pub classes: Vec<ClassScore>,
    /// Mean IoU over the classes holding at least [`MIOU_MIN_CLASS_FRACTION`] of the opaque
    /// Gaussians; `None` when no class qualifies (no opaque Gaussian).
    pub miou: Option<f64>,
    /// Names of the classes averaged in `miou`.
    pub miou_classes: Vec<String>,
    /// The class-size threshold used for `miou` (fraction of the opaque Gaussians).
    pub miou_min_class_fraction: f64,
    /// Fraction of the opaque Gaussians predicted correctly (unobserved ones count as wrong);
    /// `None` without opaque Gaussians.
    pub accuracy: Option<f64>,
    /// Observed opaque Gaussians / opaque Gaussians; `None` without opaque Gaussians.
    pub observed_fraction: Option<f64>,
    /// Gaussians in the scene.
    pub scene_gaussians: u64,
    /// Gaussians with opacity `> 0.1` (the universe).
    pub opaque_gaussians: u64,
    /// Gaussians stored in the embeddings file (observed).
    pub observed_gaussians: u64,
    /// Observed Gaussians that are opaque.
    pub observed_opaque: u64,
    /// Opaque Gaussians predicted correctly.
    pub correct: u64,
}

/// Scores predictions against the colour ground truth (protocol in the module docs).
///
/// `gt`: [`ground_truth`] of the scene (`[scene Gaussians]`); `embeddings`: the encoder output
/// whose `ids` index into `gt`; `predicted`: [`assign`] of those embeddings (`[embeddings.len()]`);
/// `class_names`: the class names ([`ColorClasses::names`]).
///
/// Errors: `predicted` and `embeddings` of different lengths ([`Error::Internal`]), a Gaussian id
/// outside the scene or the embeddings' `scene_gaussians` (when non-zero) differing from
/// `gt.len()` (embeddings of another scene; [`Error::Mismatch`]), a repeated id
/// ([`Error::Invalid`]), a class index outside `class_names` ([`Error::Param`] `class_names`).
pub fn evaluate(
    gt: &[Option<u8>],
    embeddings: &Embeddings,
    predicted: &[u8],
    class_names: &[String],
) -> Result<ColourEval> {
    let k = class_names.len();
    check_evaluate_inputs(gt, embeddings, predicted, k)?;
    let pred = predictions_per_gaussian(gt.len(), embeddings, predicted)?;
    let (mut gt_count, mut pred_count, mut inter) = (vec![0u64; k], vec![0u64; k], vec![0u64; k]);
    let (mut opaque, mut observed_opaque) = (0u64, 0u64);
    for (g, p) in gt.iter().zip(&pred) {
        let Some(g) = *g else { continue };
        opaque += 1;
        gt_count[g as usize] += 1;
        if let Some(p) = *p {
            observed_opaque += 1;
            pred_count[p as usize] += 1;
            if p == g {
                inter[g as usize] += 1;
            }
        }
    }
    let classes: Vec<ClassScore> = (0..k)
        .map(|c| {
            let union = gt_count[c] + pred_count[c] - inter[c];
            ClassScore {
                name: class_names[c].clone(),
                iou: (union > 0).then(|| inter[c] as f64 / union as f64),
                gt_count: gt_count[c],
                pred_count: pred_count[c],
                intersection: inter[c],
                in_miou: opaque > 0
                    && gt_count[c] as f64 >= MIOU_MIN_CLASS_FRACTION * opaque as f64,
            }
        })
        .collect();
    let averaged: Vec<&ClassScore> = classes.iter().filter(|c| c.in_miou).collect();
    let miou = (!averaged.is_empty()).then(|| {
        averaged.iter().map(|c| c.iou.unwrap_or(0.0)).sum::<f64>() / averaged.len() as f64
    });
    let correct: u64 = inter.iter().sum();
    Ok(ColourEval {
        miou_classes: averaged.iter().map(|c| c.name.clone()).collect(),
        classes,
        miou,
        miou_min_class_fraction: MIOU_MIN_CLASS_FRACTION,
        accuracy: (opaque > 0).then(|| correct as f64 / opaque as f64),
        observed_fraction: (opaque > 0).then(|| observed_opaque as f64 / opaque as f64),
        scene_gaussians: gt.len() as u64,
        opaque_gaussians: opaque,
        observed_gaussians: embeddings.len() as u64,
        observed_opaque,
        correct,
    })
}

/// [`evaluate`]'s refusals: a prediction count other than the embedding rows; embeddings of
/// a scene of another size than `gt`; a class index (truth or prediction) without one of the
/// `k` names.
fn check_evaluate_inputs(
    gt: &[Option<u8>],
    embeddings: &Embeddings,
    predicted: &[u8],
    k: usize,
) -> Result<()> {
    if predicted.len() != embeddings.len() {
        return Err(Error::internal(format!(
            "{} predictions for {} embedding rows; pass assign(embeddings, ..)",
            predicted.len(),
            embeddings.len()
        )));
    }
    if embeddings.scene_gaussians != 0 && embeddings.scene_gaussians != gt.len() as u64 {
        return Err(Error::mismatch(
            slag_common::Mismatched::Scene,
            format!(
                "the embeddings come from a scene of {} Gaussians but the ground truth has {}; \
                 evaluate against the .ply the encoder ran on",
                embeddings.scene_gaussians,
                gt.len()
            ),
        ));
    }
    if let Some(c) = gt
        .iter()
        .flatten()
        .chain(predicted)
        .find(|&&c| c as usize >= k)
    {
        return Err(Error::param(
            "class_names",
            format!("{k} names"),
            format!("a name for every class used (class index {c} appears)"),
        ));
    }
    Ok(())
}

/// Each of the scene's `scene_gaussians` Gaussians' predicted class, `None` where no embedding
/// row observed it. Errors: a row's Gaussian id outside the scene, or seen twice.
fn predictions_per_gaussian(
    scene_gaussians: usize,
    embeddings: &Embeddings,
    predicted: &[u8],
) -> Result<Vec<Option<u8>>> {
    let mut pred: Vec<Option<u8>> = vec![None; scene_gaussians];
    for (&id, &p) in embeddings.ids.iter().zip(predicted) {
        let slot = pred.get_mut(id as usize).ok_or_else(|| {
            Error::mismatch(
                slag_common::Mismatched::Scene,
                format!(
                    "Gaussian id {id} outside the scene's {scene_gaussians} Gaussians; evaluate \
                     against the .ply the encoder ran on"
                ),
            )
        })?;
        if slot.replace(p).is_some() {
            return Err(Error::Invalid(format!(
                "Gaussian id {id} appears twice in the embeddings"
            )));
        }
    }
    Ok(pred)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)] // tests fail loudly on purpose
mod tests {
    use super::*;
    use proptest::prelude::*;
    use slag_common::scene::ShCoeffs;
    use std::collections::BTreeSet;

    fn color_clip_path() -> std::path::PathBuf {
        slag_common::paths::source_tree_shared_dir().join("fixtures/clip/color-clip.json")
    }

    fn names(k: usize) -> Vec<String> {
        (0..k).map(|c| format!("c{c}")).collect()
    }

    /// Embeddings with the given ids (vectors irrelevant to `evaluate`).
    fn observed(ids: &[u32], scene: u64) -> Embeddings {
        Embeddings {
            ids: ids.to_vec(),
            means: vec![[0.0; 3]; ids.len()],
            dim: 1,
            vectors: vec![1.0; ids.len()],
            total_weights: vec![1.0; ids.len()],
            scene_gaussians: scene,
            ..Embeddings::default()
        }
    }

    #[test]
    fn loads_the_fixture_classes() {
        let cc = ColorClasses::load(&color_clip_path()).unwrap();
        assert_eq!(cc.len(), 12);
        assert_eq!(cc.names[0], "red");
        assert_eq!(cc.names[11], "black");
        assert_eq!(cc.prototypes_rgb01[9], [0.95, 0.95, 0.95]);
        // Each prototype is nearest to itself.
        for (c, p) in cc.prototypes_rgb01.iter().enumerate() {
            assert_eq!(cc.nearest(*p) as usize, c);
        }
    }

    #[test]
    fn load_rejects_bad_files() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("c.json");
        std::fs::write(
            &p,
            r#"{"classes": ["a", "b"], "prototypes_rgb01": [[0, 0, 0]]}"#,
        )
        .unwrap();
        assert!(matches!(ColorClasses::load(&p), Err(Error::Format { .. })));
        std::fs::write(&p, "not json").unwrap();
        assert!(matches!(ColorClasses::load(&p), Err(Error::Format { .. })));
        assert!(matches!(
            ColorClasses::load(&dir.path().join("missing")),
            Err(Error::Io { .. })
        ));
    }

    fn gaussians(dc: &[[f32; 3]], opacities: &[f32]) -> Gaussians {
        let n = dc.len();
        Gaussians {
            means: vec![[0.0; 3]; n],
            scales: vec![[1.0; 3]; n],
            rotations: vec![[1.0, 0.0, 0.0, 0.0]; n],
            opacities: opacities.to_vec(),
            sh: Some(ShCoeffs {
                degree: 0,
                coeffs: dc.iter().flatten().copied().collect(),
            }),
        }
    }

    /// f_dc that renders as `rgb` (inverse of the DC colour formula).
    fn f_dc(rgb: [f64; 3]) -> [f32; 3] {
        rgb.map(|v| ((v - 0.5) / SH_C0) as f32)
    }

    #[test]
    fn ground_truth_follows_dc_colour_and_opacity() {
        let cc = ColorClasses::load(&color_clip_path()).unwrap();
        let dc = [
            f_dc([0.8, 0.15, 0.12]),  // red
            f_dc([0.12, 0.22, 0.75]), // blue
            f_dc([0.5, 0.5, 0.5]),    // gray, but transparent
            [-10.0, -10.0, -10.0],    // clamps to (0,0,0): black
            [10.0, 10.0, 10.0],       // clamps to (1,1,1): white
            f_dc([0.5, 0.5, 0.5]),    // gray, opacity exactly at the threshold: excluded
        ];
        let g = gaussians(&dc, &[0.9, 0.5, 0.05, 0.99, 0.2, OPACITY_THRESHOLD]);
        let gt = ground_truth(&cc, &g).unwrap();
        let idx = |n: &str| cc.names.iter().position(|x| x == n).map(|i| i as u8);
        assert_eq!(
            gt,
            vec![
                idx("red"),
                idx("blue"),
                None,
                idx("black"),
                idx("white"),
                None
            ]
        );
    }

    #[test]
    fn ground_truth_without_colours_is_a_typed_error() {
        let cc = ColorClasses::load(&color_clip_path()).unwrap();
        let mut g = gaussians(&[[0.0; 3]], &[0.5]);
        g.sh = None;
        let err = ground_truth(&cc, &g).unwrap_err();
        assert!(
            matches!(
                &err,
                Error::Param {
                    name: "colours",
                    ..
                }
            ) && err.to_string().contains("colours: true"),
            "{err}"
        );
    }

    #[test]
    fn assign_picks_highest_cosine() {
        let texts = vec![
            vec![1.0, 0.0, 0.0],
            vec![0.0, 1.0, 0.0],
            vec![0.0, 0.0, 1.0],
        ];
        let s = 0.5f32.sqrt();
        let e = Embeddings {
            ids: vec![0, 1, 2, 3],
            means: vec![[0.0; 3]; 4],
            dim: 3,
            vectors: vec![0.0, 0.0, 1.0, s, s, 0.0, 0.6, 0.8, 0.0, -1.0, 0.0, 0.0],
            total_weights: vec![1.0; 4],
            ..Embeddings::default()
        };
        // Row 1 ties classes 0 and 1 (dot √½ each) → the lower index; row 3 (-1, 0, 0) ties
        // classes 1 and 2 at 0 → 1.
        assert_eq!(assign(&e, &texts).unwrap(), vec![2, 0, 1, 1]);
        assert!(matches!(
            assign(&e, &[vec![1.0, 0.0]]),
            Err(Error::Mismatch { .. })
        ));
        assert!(matches!(assign(&e, &[]), Err(Error::Param { .. })));
    }

    #[test]
    fn hand_built_case() {
        // 8 Gaussians, classes 0..3. gt:   0  0  1  1  2  -  0  1
        // observed ids 0,1,2,4,5,7 with predictions 0,1,1,2,0,0; 3 and 6 unobserved.
        let gt = [
            Some(0),
            Some(0),
            Some(1),
            Some(1),
            Some(2),
            None,
            Some(0),
            Some(1),
        ];
        let e = observed(&[0, 1, 2, 4, 5, 7], 8);
        let pred = [0, 1, 1, 2, 0, 0];
        let r = evaluate(&gt, &e, &pred, &names(3)).unwrap();
        // Universe: 0,1,2,3,4,6,7 (5 is transparent, its prediction ignored).
        // class 0: gt {0,1,6}, pred {0,7}        → ∩ {0}   ∪ {0,1,6,7}  → 1/4
        // class 1: gt {2,3,7}, pred {1,2}        → ∩ {2}   ∪ {1,2,3,7}  → 1/4
        // class 2: gt {4},     pred {4}          → 1
        let ious: Vec<_> = r.classes.iter().map(|c| c.iou.unwrap()).collect();
        assert_eq!(ious, vec![0.25, 0.25, 1.0]);
        assert_eq!(r.classes[0].gt_count, 3);
        assert_eq!(r.classes[0].pred_count, 2);
        assert_eq!(r.opaque_gaussians, 7);
        assert_eq!(r.observed_opaque, 5);
        assert_eq!(r.observed_gaussians, 6);
        assert_eq!(r.correct, 3);
        assert_eq!(r.accuracy, Some(3.0 / 7.0));
        assert_eq!(r.observed_fraction, Some(5.0 / 7.0));
        assert_eq!(r.miou, Some(0.5));
        assert_eq!(r.miou_classes, names(3));
    }

    #[test]
    fn unobserved_gaussians_lower_recall() {
        let gt = [Some(0), Some(0), Some(0), Some(0)];
        let all = evaluate(&gt, &observed(&[0, 1, 2, 3], 4), &[0, 0, 0, 0], &names(1)).unwrap();
        assert_eq!(all.miou, Some(1.0));
        let half = evaluate(&gt, &observed(&[1, 3], 4), &[0, 0], &names(1)).unwrap();
        assert_eq!(half.classes[0].iou, Some(0.5));
        assert_eq!(half.accuracy, Some(0.5));
        assert_eq!(half.observed_fraction, Some(0.5));
        let none = evaluate(&gt, &observed(&[], 4), &[], &names(1)).unwrap();
        assert_eq!(none.miou, Some(0.0));
        assert_eq!(none.observed_fraction, Some(0.0));
    }

    #[test]
    fn rare_classes_are_left_out_of_miou() {
        // 200 opaque Gaussians: class 0 ×197, class 1 ×2 (1.0 %: in), class 2 ×1 (0.5 %: out).
        let mut gt = vec![Some(0u8); 197];
        gt.extend([Some(1), Some(1), Some(2)]);
        let ids: Vec<u32> = (0..200).collect();
        // Everything predicted class 0.
        let r = evaluate(&gt, &observed(&ids, 200), &[0; 200], &names(3)).unwrap();
        assert_eq!(r.miou_classes, vec!["c0".to_string(), "c1".to_string()]);
        assert!(r.classes[1].in_miou && !r.classes[2].in_miou);
        assert_eq!(r.classes[2].iou, Some(0.0));
        assert_eq!(r.miou, Some((197.0 / 200.0 + 0.0) / 2.0));
        // A class never present nor predicted has no IoU and is not averaged.
        let r = evaluate(&gt, &observed(&ids, 200), &[0; 200], &names(4)).unwrap();
        assert_eq!(r.classes[3].iou, None);
        assert!(!r.classes[3].in_miou);
    }

    #[test]
    fn evaluate_rejects_inconsistent_input() {
        let gt = [Some(0), Some(1)];
        let n = names(2);
        assert!(matches!(
            evaluate(&gt, &observed(&[0, 1], 2), &[0], &n),
            Err(Error::Internal(_))
        ));
        assert!(matches!(
            evaluate(&gt, &observed(&[0, 2], 2), &[0, 0], &n),
            Err(Error::Mismatch { .. })
        ));
        assert!(matches!(
            evaluate(&gt, &observed(&[1, 1], 2), &[0, 0], &n),
            Err(Error::Invalid(_))
        ));
        assert!(matches!(
            evaluate(&gt, &observed(&[0], 3), &[0], &n),
            Err(Error::Mismatch { .. })
        ));
        assert!(matches!(
            evaluate(&gt, &observed(&[0], 2), &[5], &n),
            Err(Error::Param { .. })
        ));
        assert!(matches!(
            evaluate(&gt, &observed(&[0], 2), &[0], &names(1)),
            Err(Error::Param { .. })
        ));
    }

    proptest! {
        #[test]
        fn matches_brute_force_sets(
            cells in proptest::collection::vec((proptest::option::of(0u8..5), proptest::option::of(0u8..5)), 0..120),
        ) {
            // cells[i] = (gt, prediction if observed)
            let gt: Vec<Option<u8>> = cells.iter().map(|c| c.0).collect();
            let ids: Vec<u32> = (0..cells.len() as u32).filter(|&i| cells[i as usize].1.is_some()).collect();
            let pred: Vec<u8> = ids.iter().map(|&i| cells[i as usize].1.unwrap_or(0)).collect();
            let r = evaluate(&gt, &observed(&ids, cells.len() as u64), &pred, &names(5)).unwrap();
            let universe: BTreeSet<usize> = (0..cells.len()).filter(|&i| gt[i].is_some()).collect();
            let mut ious = Vec::new();
            for c in 0..5u8 {
                let g: BTreeSet<usize> = universe.iter().copied().filter(|&i| gt[i] == Some(c)).collect();
                let p: BTreeSet<usize> = universe.iter().copied().filter(|&i| cells[i].1 == Some(c)).collect();
                let inter = g.intersection(&p).count();
                let union = g.union(&p).count();
                let iou = (union > 0).then(|| inter as f64 / union as f64);
                prop_assert_eq!(r.classes[c as usize].iou, iou);
                prop_assert_eq!(r.classes[c as usize].gt_count, g.len() as u64);
                prop_assert_eq!(r.classes[c as usize].pred_count, p.len() as u64);
                if !universe.is_empty() && g.len() * 100 >= universe.len() {
                    ious.push(iou.unwrap_or(0.0));
                }
            }
            let miou = (!ious.is_empty()).then(|| ious.iter().sum::<f64>() / ious.len() as f64);
            match (r.miou, miou) {
                (Some(a), Some(b)) => prop_assert!((a - b).abs() < 1e-12),
                (a, b) => prop_assert_eq!(a, b),
            }
            let correct = universe.iter().filter(|&&i| cells[i].1 == gt[i]).count();
            prop_assert_eq!(r.correct, correct as u64);
            let observed_opaque = universe.iter().filter(|&&i| cells[i].1.is_some()).count();
            prop_assert_eq!(r.observed_opaque, observed_opaque as u64);
        }
    }

    fn read_inria_ply_dc(path: &Path) -> Gaussians {
        slag_common::scene::load_ply(path, slag_common::scene::PlyLoadOptions { colours: true })
            .unwrap()
    }

    #[test]
    fn snowmiku_class_histogram_is_sane() {
        let cc = ColorClasses::load(&color_clip_path()).unwrap();
        let ply =
            slag_common::paths::source_tree_shared_dir().join("scenes/snowmiku/point_cloud.ply");
        let g = read_inria_ply_dc(&ply);
        assert_eq!(g.len(), 120_000);
        let gt = ground_truth(&cc, &g).unwrap();
        let mut hist = vec![0usize; cc.len()];
        gt.iter().flatten().for_each(|&c| hist[c as usize] += 1);
        let opaque: usize = hist.iter().sum();
        println!(
            "snowmiku: {} Gaussians, {opaque} opaque (opacity > 0.1)",
            g.len()
        );
        for (name, h) in cc.names.iter().zip(&hist) {
            println!(
                "  {name:>7}: {h:>6} ({:.2} %)",
                100.0 * *h as f64 / opaque as f64
            );
        }
        // Most Gaussians of a trained scene are opaque; a real indoor scene has several colours.
        assert!(opaque > g.len() / 2, "{opaque} opaque");
        let present = hist.iter().filter(|&&h| h * 100 >= opaque).count();
        assert!(
            present >= 4,
            "only {present} classes hold ≥ 1 % of the opaque Gaussians: {hist:?}"
        );
        assert!(
            hist.iter().all(|&h| h < opaque),
            "a single class holds everything: {hist:?}"
        );
    }
}
