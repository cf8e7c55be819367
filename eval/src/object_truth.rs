//! The held-out protocol on **object truth** (`slag-encoder eval-objects --held-out`): the
//! predictors of [`crate::heldout`] scored against the class of the *object* each pixel and
//! each Gaussian belongs to, not against the photo's pixel colour. This is the truth prediction
//! filtering assumes (ScanNet's: every point of a chair is "chair", whatever its texture or
//! light), on a scene that knows it (`synth-scene --objects K --room`,
//! [`slag_encoder::object_scene`], its `truth.json`).
//!
//! - **Classes.** color-clip's 12 colour classes; an object's class is its colour, the floor is
//!   gray and the walls white ([`slag_encoder::object_scene::GaussianTruth`]).
//! - **Per pixel.** Every held-out view (those of [`slag_encoder::views::held_out_indices`] for
//!   the encoder's held-out step) is rasterized at full resolution; the truth of a pixel is the
//!   class of most blend weight among its Gaussians' true classes (the *rendered object-class
//!   map*, `argmax_c Σ_k w_kp [class_k = c]`), a predictor's class the argmax of its blended
//!   scores, as in [`crate::heldout::HeldOutTally`]; pixels of rendered alpha below
//!   [`crate::heldout::ALPHA_MIN`] do not count. mIoU over the classes holding ≥ 1 % of the
//!   counted pixels.
//! - **Per Gaussian (3D).** Each observed Gaussian's argmax class against its true class, over
//!   the Gaussians the embeddings observe (the same set for every predictor; PF's answer for
//!   unobserved Gaussians is not counted); mIoU over the classes holding ≥ 1 % of them.
//! - **Predictors.** slag (`E_k`), every form beside the embeddings
//!   ([`crate::heldout_variants::variant_tables`]: the mixture's), and with segments every PF
//!   variant per segmentation ([`crate::pf_variants::pf_tables`]), all on the same pixels.
//! - **Segments.** Each segmentation's purity against the true classes and against the objects
//!   (floor and walls one label each), over every Gaussian and over the objects' Gaussians only
//!   (each against its whole segment's majority, so an object that a floor segment swallows
//!   counts as impure).

use std::path::{Path, PathBuf};
use std::time::Instant;

use slag_common::camera;
use slag_common::embeddings::Embeddings;
use slag_common::onnx::ExecutionProvider;
use slag_common::scene::{self, PlyLoadOptions};
use slag_common::segments::Segments;
use slag_common::text::TextEncoder;
use slag_common::{Error, Result};
use slag_encoder::config::RasterBackend;
use slag_encoder::object_scene::GaussianTruth;
use slag_encoder::raster::PixelWeights;

use crate::heldout::{self, Confusion, HeldOutTally, PixelScore};

/// What the object-truth pass evaluates.
#[derive(Debug, Clone, PartialEq)]
pub struct ObjectTruthConfig {
    /// The scene folder of `synth-scene --objects K --room` (`truth.json`, `point_cloud.ply`,
    /// the views).
    pub scene: PathBuf,
    /// embeddings.safetensors of that scene, made with color-clip.
    pub embeddings: PathBuf,
    /// Folder holding color-clip (`color-clip-textual.onnx`, `clip-tokenizer.json`,
    /// `color-clip.json`).
    pub color_clip: PathBuf,
    /// Segmentations to filter with, the first named bare; empty: `segments.safetensors` beside
    /// the embeddings when it exists, else no PF.
    pub segments: Vec<PathBuf>,
    /// The held-out step; `None`: from the report.json beside the embeddings.
    pub every: Option<usize>,
    /// Weight rasterizer of the held-out renders.
    pub rasterizer: RasterBackend,
    /// ONNX Runtime execution provider of the text tower.
    pub ep: ExecutionProvider,
    /// Write a picture of the first held-out view here (PNG): the photo, the rendered
    /// object-class map, slag's classes and those of `pf-majority` (or of the best PF variant
    /// when there is no `pf-majority`), side by side, each class in its colour, uncounted
    /// pixels black.
    pub picture: Option<PathBuf>,
}

/// One predictor's scores on the object truth.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct PredictorScore {
    /// `slag`, a variant's name (`mixture-mean-S4`, `pf-majority`, `pf-confident@…`), or
    /// `majority` (every pixel the most frequent true class).
    pub name: String,
    /// Per-pixel score over the held-out views.
    pub pixel: PixelScore,
    /// Per-Gaussian score over the observed Gaussians (`None` for `majority`).
    pub gaussian: Option<PixelScore>,
}

/// One segmentation against the truth.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SegmentsAgainstTruth {
    /// The segments file.
    pub source: PathBuf,
    /// Segments in it.
    pub segments: u32,
    /// Purity against the true classes, over every Gaussian.
    pub class_purity: crate::segment_quality::Purity,
    /// Purity against the objects (floor and walls one label each), over every Gaussian.
    pub object_purity: crate::segment_quality::Purity,
    /// The objects' Gaussians only, each against its whole segment's majority class (floor and
    /// walls vote, [`crate::segment_quality::purity_within`]): the share whose segment answers
    /// their class under PF's majority. The figures over every Gaussian are dominated by the
    /// floor and walls.
    pub objects_class_purity: crate::segment_quality::Purity,
    /// The same against the objects: the share of the objects' Gaussians in a segment their
    /// own object dominates.
    pub objects_object_purity: crate::segment_quality::Purity,
}

/// What `eval-objects --held-out` prints under `object_truth`.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ObjectTruthEval {
    /// The held-out step.
    pub every: usize,
    /// Names of the held-out views.
    pub held_out_views: Vec<String>,
    /// Counted pixels (rendered alpha ≥ the minimum).
    pub counted_pixels: u64,
    /// Observed Gaussians (the 3D score's population).
    pub observed_gaussians: usize,
    /// The predictors, `slag` first, then the variants, then `majority`.
    pub predictors: Vec<PredictorScore>,
    /// The segmentations against the truth, in the order filtered.
    pub segments: Vec<SegmentsAgainstTruth>,
    /// Wall time of the pass, seconds.
    pub seconds: f64,
}

impl ObjectTruthEval {
    /// The predictor named `name`.
    pub fn predictor(&self, name: &str) -> Option<&PredictorScore> {
        self.predictors.iter().find(|p| p.name == name)
    }
}

/// Reads segments and checks them against the scene's `n` Gaussians.
fn read_segments(path: &Path, n: usize) -> Result<Segments> {
    let s = Segments::read(path)?;
    if s.len() != n {
        return Err(Error::mismatch(
            slag_common::Mismatched::Scene,
            format!(
                "{} segments {} Gaussians but the scene has {n}; segment the .ply the \
                 embeddings were made from",
                path.display(),
                s.len()
            ),
        ));
    }
    Ok(s)
}

/// The segmentations of `c` (module doc), each with its path.
fn segment_sets(c: &ObjectTruthConfig, n: usize) -> Result<Vec<(PathBuf, Segments)>> {
    let mut paths = c.segments.clone();
    if paths.is_empty() {
        let beside = c
            .embeddings
            .parent()
            .unwrap_or(Path::new("."))
            .join(slag_common::segments::FILE_NAME);
        if beside.exists() {
            paths.push(beside);
        }
    }
    paths
        .into_iter()
        .map(|p| read_segments(&p, n).map(|s| (p, s)))
        .collect()
}

/// The rendered object-class map of one view: per pixel the class of most blend weight among
/// its contributors' true classes (ties to the smaller class; an empty pixel class 0, never
/// counted).
pub fn truth_map(weights: &PixelWeights, classes: &[u8], c: usize) -> Result<Vec<u8>> {
    let pixels = weights.width as usize * weights.height as usize;
    if weights.offsets.len() != pixels + 1 {
        return Err(Error::internal(
            "pixel weights without one offset per pixel",
        ));
    }
    let mut acc = vec![0f32; c];
    let mut out = Vec::with_capacity(pixels);
    for p in 0..pixels {
        acc.iter_mut().for_each(|v| *v = 0.0);
        let (a, b) = (weights.offsets[p] as usize, weights.offsets[p + 1] as usize);
        for (&k, &w) in weights.ids[a..b].iter().zip(&weights.weights[a..b]) {
            let cl = *classes.get(k as usize).ok_or_else(|| {
                Error::mismatch(
                    slag_common::Mismatched::Scene,
                    format!("Gaussian {k} outside the truth's {}", classes.len()),
                )
            })? as usize;
            acc[cl.min(c - 1)] += w;
        }
        let mut best = 0;
        for i in 1..c {
            if acc[i] > acc[best] {
                best = i;
            }
        }
        out.push(best as u8);
    }
    Ok(out)
}

/// Writes the picture of [`ObjectTruthConfig::picture`]: `photo`, the `truth` map and each of
/// `tables`' per-pixel classes on the raster `weights`, side by side.
fn picture(
    path: &Path,
    photo: &image::RgbImage,
    weights: &PixelWeights,
    truth: &[u8],
    tables: &[&[f32]],
    c: usize,
) -> Result<()> {
    use slag_encoder::synthetic::PALETTE;
    let (w, h) = (weights.width, weights.height);
    let panels = 2 + tables.len() as u32;
    let mut out = image::RgbImage::new(w * panels, h);
    let paint = |cl: usize| PALETTE[cl.min(PALETTE.len() - 1)].map(|v| (v * 255.0).round() as u8);
    let mut acc = vec![0f32; c];
    for y in 0..h {
        for x in 0..w {
            let p = (y * w + x) as usize;
            let px = photo.get_pixel(x.min(photo.width() - 1), y.min(photo.height() - 1));
            out.put_pixel(x, y, *px);
            let (a, b) = (weights.offsets[p] as usize, weights.offsets[p + 1] as usize);
            let (ids, ws) = (&weights.ids[a..b], &weights.weights[a..b]);
            if ws.iter().sum::<f32>() < heldout::ALPHA_MIN {
                continue;
            }
            out.put_pixel(w + x, y, image::Rgb(paint(truth[p] as usize)));
            for (t, table) in tables.iter().enumerate() {
                acc.iter_mut().for_each(|v| *v = 0.0);
                for (&k, &wk) in ids.iter().zip(ws) {
                    let row = &table[k as usize * c..(k as usize + 1) * c];
                    acc.iter_mut().zip(row).for_each(|(v, s)| *v += wk * s);
                }
                let best = (0..c).fold(0, |b, i| if acc[i] > acc[b] { i } else { b });
                out.put_pixel((2 + t as u32) * w + x, y, image::Rgb(paint(best)));
            }
        }
    }
    out.save(path)
        .map_err(|e| Error::io(path, std::io::Error::other(e)))
}

/// The per-Gaussian confusion of `table` (`[n × c]`) against `truth` over `observed` Gaussians.
fn gaussian_confusion(table: &[f32], truth: &[u8], observed: &[bool], c: usize) -> Confusion {
    let mut cf = Confusion {
        intersection: vec![0; c],
        predicted: vec![0; c],
    };
    for ((row, &t), _) in table
        .chunks_exact(c)
        .zip(truth)
        .zip(observed)
        .filter(|(_, o)| **o)
    {
        let mut best = 0;
        for i in 1..c {
            if row[i] > row[best] {
                best = i;
            }
        }
        cf.predicted[best] += 1;
        if best == t as usize {
            cf.intersection[best] += 1;
        }
    }
    cf
}

/// Runs the object-truth pass (module doc).
///
/// Errors: the scene without `truth.json` or of another Gaussian count than the embeddings
/// ([`Error::Mismatch`]); class names of color-clip other than the truth's ([`Error::Mismatch`]);
/// the held-out step unknown or holding out no view ([`Error::Param`] `every`); the models,
/// segments, views and rasterizer failures.
pub fn run_object_truth(c: &ObjectTruthConfig) -> anyhow::Result<ObjectTruthEval> {
    let t0 = Instant::now();
    let truth = GaussianTruth::read(&c.scene)?;
    let classes = crate::ColorClasses::load(&c.color_clip.join("color-clip.json"))?;
    let scene_mismatch = |what: String| Error::mismatch(slag_common::Mismatched::Scene, what);
    if classes.names != truth.classes {
        return Err(scene_mismatch(format!(
            "the scene's truth names the classes {:?} but color-clip {:?}",
            truth.classes, classes.names
        ))
        .into());
    }
    let nc = classes.len();
    let gaussians = scene::load_ply(
        &c.scene.join("point_cloud.ply"),
        PlyLoadOptions { colours: false },
    )?;
    let n = gaussians.len();
    let emb = Embeddings::read(&c.embeddings)?;
    if truth.gaussians != n || emb.scene_gaussians != n as u64 {
        return Err(scene_mismatch(format!(
            "{n} Gaussians in the scene, {} in its truth, {} in the embeddings' scene",
            truth.gaussians, emb.scene_gaussians
        ))
        .into());
    }
    let true_class = truth.classes_per_gaussian();
    let mut text = TextEncoder::new(
        &c.color_clip.join("color-clip-textual.onnx"),
        &c.color_clip.join("clip-tokenizer.json"),
        c.ep,
    )?;
    let names: Vec<&str> = classes.names.iter().map(String::as_str).collect();
    let texts = text.encode(&names)?;
    let slag_scores = heldout::gaussian_scores(&emb, &texts, n)?;
    let mut variants =
        crate::heldout_variants::variant_tables(&c.embeddings, &[], &slag_scores, &texts, n)?;
    let sets = segment_sets(c, n)?;
    if !sets.is_empty() {
        let pf = crate::pf_variants::pf_tables(&emb, n, &slag_scores, &variants, &sets, nc)?;
        variants.extend(pf);
    }
    let mut tables: Vec<(String, &[f32])> = vec![("slag".into(), &slag_scores)];
    tables.extend(
        variants
            .iter()
            .map(|v| (v.name.clone(), v.scores.as_slice())),
    );

    let settings = crate::colors::report_settings(&c.embeddings)?;
    let every = crate::colors::held_out_step(c.every, &settings, &c.embeddings)?;
    let views = camera::load_views(&c.scene)?;
    let held = slag_encoder::views::held_out_indices(views.len(), every)?;
    if held.is_empty() {
        return Err(Error::param("every", every, "a step that holds out at least one view").into());
    }
    let mut rasterizer = slag_encoder::pipeline::build::make_rasterizer(c.rasterizer, &gaussians)?;
    let mut tally = HeldOutTally::new(nc, tables.len());
    let only: Vec<&[f32]> = tables.iter().map(|t| t.1).collect();
    for (k, &i) in held.iter().enumerate() {
        let v = &views[i];
        let intr = slag_encoder::raster::raster_intrinsics(&v.intrinsics, 1.0)?;
        let weights = rasterizer.rasterize(&intr, &v.world_to_camera)?;
        let map = truth_map(&weights, &true_class, nc)?;
        tally.add_view(&weights, &map, &only, n)?;
        if let (0, Some(path)) = (k, &c.picture) {
            let pf = tables
                .iter()
                .find(|t| t.0 == "pf-majority")
                .map_or(only[0], |t| t.1);
            let photo = slag_encoder::pipeline::read_image(v)?;
            picture(path, &photo, &weights, &map, &[only[0], pf], nc)?;
        }
        tracing::info!("held-out view {} scored against the object truth", v.name);
    }
    let (predictors, observed) =
        score_predictors(&tables, &tally, &emb, &true_class, &classes.names);
    let segments = segments_against_truth(&sets, &truth, &true_class)?;
    Ok(ObjectTruthEval {
        every,
        held_out_views: held.iter().map(|&i| views[i].name.clone()).collect(),
        counted_pixels: tally.counted(),
        observed_gaussians: observed,
        predictors,
        segments,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// Every predictor's pixel and per-Gaussian score (then `majority`), and the observed
/// Gaussians counted.
fn score_predictors(
    tables: &[(String, &[f32])],
    tally: &HeldOutTally,
    emb: &Embeddings,
    true_class: &[u8],
    names: &[String],
) -> (Vec<PredictorScore>, usize) {
    let (n, nc) = (true_class.len(), names.len());
    let mut observed = vec![false; n];
    for &id in &emb.ids {
        if let Some(o) = observed.get_mut(id as usize) {
            *o = true;
        }
    }
    let mut three_d = HeldOutTally::new(nc, 0);
    for (&t, _) in true_class.iter().zip(&observed).filter(|(_, o)| **o) {
        three_d.truth[t as usize] += 1;
    }
    let mut predictors: Vec<PredictorScore> = tables
        .iter()
        .zip(&tally.predictors)
        .map(|((name, table), cf)| PredictorScore {
            name: name.clone(),
            pixel: tally.score(cf, names),
            gaussian: Some(
                three_d.score(&gaussian_confusion(table, true_class, &observed, nc), names),
            ),
        })
        .collect();
    predictors.push(PredictorScore {
        name: "majority".into(),
        pixel: tally.score(&tally.majority(), names),
        gaussian: None,
    });
    let count = observed.iter().filter(|&&o| o).count();
    (predictors, count)
}

/// Each segmentation's purity against the classes and the objects.
fn segments_against_truth(
    sets: &[(PathBuf, Segments)],
    truth: &GaussianTruth,
    true_class: &[u8],
) -> Result<Vec<SegmentsAgainstTruth>> {
    let class_labels: Vec<Option<u32>> = true_class.iter().map(|&c| Some(u32::from(c))).collect();
    let mut object_labels = vec![None; truth.gaussians];
    let background = truth
        .runs
        .iter()
        .filter_map(|r| r.object)
        .max()
        .map_or(0, |m| m + 1);
    for r in &truth.runs {
        let label = match r.object {
            Some(o) => o as u32,
            None => (background + r.class) as u32,
        };
        object_labels[r.gaussians[0]..r.gaussians[1]].fill(Some(label));
    }
    let mut on_object = vec![false; truth.gaussians];
    for r in truth.runs.iter().filter(|r| r.object.is_some()) {
        on_object[r.gaussians[0]..r.gaussians[1]].fill(true);
    }
    use crate::segment_quality::{purity, purity_within};
    sets.iter()
        .map(|(p, s)| {
            let seg = &s.segments;
            Ok(SegmentsAgainstTruth {
                source: p.clone(),
                segments: s.segment_count,
                class_purity: purity(&class_labels, seg)?,
                object_purity: purity(&object_labels, seg)?,
                objects_class_purity: purity_within(&class_labels, seg, &on_object)?,
                objects_object_purity: purity_within(&object_labels, seg, &on_object)?,
            })
        })
        .collect()
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn the_truth_map_takes_the_heaviest_class_and_the_confusion_counts_observed_only() {
        // Three pixels: Gaussian 0 (class 2) alone; 0 and 1 (class 1) with 1 heavier; none.
        let w = PixelWeights {
            width: 3,
            height: 1,
            offsets: vec![0, 1, 3, 3],
            ids: vec![0, 0, 1],
            weights: vec![0.9, 0.3, 0.6],
        };
        let classes = [2u8, 1];
        assert_eq!(truth_map(&w, &classes, 3).unwrap(), vec![2, 1, 0]);
        assert!(truth_map(&w, &[2u8], 3).is_err());
        // Gaussian 0 right, 1 wrong, 2 unobserved (not counted).
        let table = [0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0];
        let cf = gaussian_confusion(&table, &[2, 1, 0], &[true, true, false], 3);
        assert_eq!(cf.predicted, vec![0, 0, 2]);
        assert_eq!(cf.intersection, vec![0, 0, 1]);
    }
}
