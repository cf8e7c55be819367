//! 2D held-out accuracy: render per-Gaussian class scores into views that were never encoded and
//! compare them pixel by pixel with labels taken from the photos (the LERF / LangSplat protocol,
//! with the 12 colour classes of the color-clip fixture as the labels).
//!
//! Protocol (`slag-encoder eval-colors --held-out`):
//!
//! - **Views.** The encoder keeps views with name-sorted index `i ≡ 0 (mod N)` (`--every N`); the
//!   held-out views are those with `i ≡ ⌊N/2⌋ (mod N)`
//!   ([`slag_encoder::views::held_out_indices`]), so none of them was encoded (`N ≥ 2`).
//! - **Scores.** Each Gaussian carries one score per class, `s_kc = cos(E_k, text_c)`
//!   ([`gaussian_scores`]); Gaussians without an embedding (unobserved) carry 0.
//! - **Render.** Every held-out view is rasterized at full resolution with slag's weight
//!   rasterizer and the scores are composited with the same front-to-back α-blend as the colour
//!   render ([`slag_encoder::raster::colour`]): `S_pc = Σ_k w_kp · s_kc` with `w_kp = α·T`. The
//!   pixel's rendered alpha is `Σ_k w_kp` (all contributors, observed or not).
//! - **Prediction.** `argmax_c S_pc` (ties → the lower class index).
//! - **Truth.** The class whose prototype is nearest (squared RGB distance, RGB in `[0, 1]` =
//!   8-bit value / 255, ties → the lower index) to the photo's pixel colour
//!   ([`crate::ColorClasses::nearest`], the same 12 prototypes as `color-clip.json`).
//! - **Counted pixels.** Only pixels whose rendered alpha is ≥ [`ALPHA_MIN`].
//! - **Score.** Intersections and unions per class are summed over all held-out views;
//!   `IoU_c = |pred = c ∧ truth = c| / |pred = c ∨ truth = c|`; the mIoU averages the classes that
//!   hold ≥ [`crate::MIOU_MIN_CLASS_FRACTION`] of the counted pixels (by truth).
//! - **Baselines** (same pixels, same classes): the *majority class* (every counted pixel gets the
//!   class most frequent among the counted pixels' truth), and the *pixel-level lifting oracle*
//!   ([`OracleLifting`]): each Gaussian gets `h_kc = Σ_p w_kp · [class(photo_p) = c]` over the
//!   encoded views at the encoder's raster scale, i.e. the paper's lifting with perfect masks and
//!   a perfect CLIP (one-hot class embeddings), scored like slag as `cos(h_k, onehot_c)`.

use image::RgbImage;
use rayon::prelude::*;
use slag_common::camera::{Intrinsics, WorldToCamera};
use slag_common::embeddings::Embeddings;
use slag_common::{Error, Result};
use slag_encoder::raster::{PixelWeights, WeightRasterizer};

use crate::{ColorClasses, MIOU_MIN_CLASS_FRACTION};

/// A pixel is counted when its rendered alpha `Σ_k w_kp` is at least this.
pub const ALPHA_MIN: f32 = 0.5;

/// The class of every raster pixel of a `width × height` grid from the full-resolution photo:
/// nearest sampling at raster pixel centres (as the encoder resamples masks), then the class of
/// the nearest prototype to the pixel's RGB in `[0, 1]`. Returns `[height × width]` row-major.
///
/// Errors ([`Error::Invalid`]): an empty photo or grid, no class.
pub fn photo_classes(
    classes: &ColorClasses,
    photo: &RgbImage,
    width: u32,
    height: u32,
) -> Result<Vec<u8>> {
    let (pw, ph) = photo.dimensions();
    if pw == 0 || ph == 0 || width == 0 || height == 0 || classes.is_empty() {
        return Err(Error::Invalid(format!(
            "photo {pw}x{ph}, grid {width}x{height}, {} classes: none may be empty",
            classes.len()
        )));
    }
    let mut out = vec![0u8; width as usize * height as usize];
    out.par_chunks_mut(width as usize)
        .enumerate()
        .for_each(|(y, row)| {
            let sy = (((y as f64 + 0.5) * ph as f64 / height as f64) as u32).min(ph - 1);
            for (x, c) in row.iter_mut().enumerate() {
                let sx = (((x as f64 + 0.5) * pw as f64 / width as f64) as u32).min(pw - 1);
                let p = photo.get_pixel(sx, sy).0;
                *c = classes.nearest(p.map(|v| v as f64 / 255.0));
            }
        });
    Ok(out)
}

/// Per-Gaussian class scores `s_kc = cos(E_k, text_c)`, `[scene_gaussians × C]` row-major f32;
/// rows of Gaussians absent from `embeddings` (unobserved) are 0.
///
/// Both sides are L2-normalised here (the embeddings file stores them normalised already; the
/// texts may come in any scale), so the cosine holds whatever the inputs' norms.
///
/// Errors: no class text or more than 256 ([`Error::Param`] `classes`), a text of another width
/// than the embeddings or of zero norm, a Gaussian id outside `scene_gaussians`
/// ([`Error::Mismatch`]), a malformed matrix ([`Error::Internal`]).
pub fn gaussian_scores(
    embeddings: &Embeddings,
    class_text_embeds: &[Vec<f32>],
    scene_gaussians: usize,
) -> Result<Vec<f32>> {
    let (n, dim, c) = (embeddings.len(), embeddings.dim, class_text_embeds.len());
    if c == 0 || c > 256 {
        return Err(Error::param(
            "classes",
            c,
            "1 to 256 class text embeddings (one per colour class)",
        ));
    }
    if dim == 0 || embeddings.vectors.len() != n * dim || embeddings.ids.len() != n {
        return Err(Error::internal(format!(
            "embeddings hold {} values and {} ids for {n} rows of width {dim}",
            embeddings.vectors.len(),
            embeddings.ids.len()
        )));
    }
    let mut texts = Vec::with_capacity(c);
    for (i, t) in class_text_embeds.iter().enumerate() {
        let norm = t.iter().map(|v| v * v).sum::<f32>().sqrt();
        if t.len() != dim || !(norm.is_finite() && norm > 0.0) {
            return Err(Error::mismatch(
                slag_common::Mismatched::EmbeddingWidth,
                format!(
                    "class {i} text embedding has {} values of norm {norm}; expected {dim} \
                     values of positive norm: encode the texts with the CLIP model that made the \
                     embeddings",
                    t.len()
                ),
            ));
        }
        texts.push(t.iter().map(|v| v / norm).collect::<Vec<f32>>());
    }
    let mut scores = vec![0f32; scene_gaussians * c];
    for (row, &id) in embeddings.vectors.chunks_exact(dim).zip(&embeddings.ids) {
        let slot = scores
            .get_mut(id as usize * c..(id as usize + 1) * c)
            .ok_or_else(|| {
                Error::mismatch(
                    slag_common::Mismatched::Scene,
                    format!(
                        "Gaussian id {id} outside the scene's {scene_gaussians} Gaussians; \
                         evaluate against the .ply the encoder ran on"
                    ),
                )
            })?;
        let norm = row.iter().map(|v| v * v).sum::<f32>().sqrt();
        if !(norm.is_finite() && norm > 0.0) {
            continue; // no direction: scores stay 0, as for an unobserved Gaussian
        }
        for (s, t) in slot.iter_mut().zip(&texts) {
            *s = row.iter().zip(t).map(|(a, b)| a * b).sum::<f32>() / norm;
        }
    }
    Ok(scores)
}

/// The pixel-level lifting oracle: `h_kc = Σ_p w_kp · [class(photo_p) = c]` summed over the
/// encoded views (the paper's `a_kj` with one perfect mask per class), then scored as slag is,
/// `cos(h_k, onehot_c) = h_kc / ‖h_k‖₂` ([`Self::scores`]).
#[derive(Debug, Clone, PartialEq)]
pub struct OracleLifting {
    classes: usize,
    /// `[scene Gaussians × classes]` row-major, units: pixels at the raster resolution.
    hist: Vec<f64>,
}

impl OracleLifting {
    /// An empty oracle for `scene_gaussians` Gaussians and `classes` classes (1 to 256).
    pub fn new(scene_gaussians: usize, classes: usize) -> Result<Self> {
        if classes == 0 || classes > 256 {
            return Err(Error::param("classes", classes, "1 to 256 classes"));
        }
        Ok(Self {
            classes,
            hist: vec![0.0; scene_gaussians * classes],
        })
    }

    /// Adds one encoded view: `pixel_classes` is `[height × width]` at the raster size of
    /// `intrinsics` ([`photo_classes`] of the photo). Uses the rasterizer's per-label sums when it
    /// has them (label = class + 1), otherwise its per-pixel lists.
    ///
    /// Errors: `pixel_classes` of the wrong length or holding a class outside the oracle's
    /// ([`Error::Internal`]), a contributor outside the scene ([`Error::Mismatch`]), the
    /// rasterizer's errors.
    pub fn add_view(
        &mut self,
        rasterizer: &mut dyn WeightRasterizer,
        intrinsics: &Intrinsics,
        world_to_camera: &WorldToCamera,
        pixel_classes: &[u8],
    ) -> Result<()> {
        let pixels = intrinsics.width as usize * intrinsics.height as usize;
        if pixel_classes.len() != pixels {
            return Err(Error::internal(format!(
                "{} pixel classes for a {}x{} raster",
                pixel_classes.len(),
                intrinsics.width,
                intrinsics.height
            )));
        }
        if let Some(&c) = pixel_classes.iter().find(|&&c| c as usize >= self.classes) {
            return Err(Error::internal(format!(
                "pixel class {c} but the oracle has {} classes",
                self.classes
            )));
        }
        let labels: Vec<u32> = pixel_classes.iter().map(|&c| c as u32 + 1).collect();
        let n = self.hist.len() / self.classes;
        let outside = |k: u32| {
            Error::mismatch(
                slag_common::Mismatched::Scene,
                format!(
                    "the rasterizer returned Gaussian {k} but the scene has {n}; rasterize the \
                     same scene"
                ),
            )
        };
        if let Some(sums) = rasterizer.label_sums(intrinsics, world_to_camera, &labels)? {
            for s in &sums.reduced() {
                let (k, c) = (s.gaussian as usize, s.label as usize - 1);
                if k >= n || c >= self.classes {
                    return Err(outside(s.gaussian));
                }
                self.hist[k * self.classes + c] += s.weight();
            }
            return Ok(());
        }
        let w = rasterizer.rasterize(intrinsics, world_to_camera)?;
        check_weights(&w, pixels)?;
        for (p, &c) in pixel_classes.iter().enumerate() {
            let (a, b) = (w.offsets[p] as usize, w.offsets[p + 1] as usize);
            for (&k, &wk) in w.ids[a..b].iter().zip(&w.weights[a..b]) {
                if k as usize >= n {
                    return Err(outside(k));
                }
                self.hist[k as usize * self.classes + c as usize] += wk as f64;
            }
        }
        Ok(())
    }

    /// Per-Gaussian scores `h_kc / ‖h_k‖₂` (`[scene Gaussians × classes]`, 0 for Gaussians that
    /// received no weight), to render like [`gaussian_scores`].
    pub fn scores(&self) -> Vec<f32> {
        self.hist
            .par_chunks_exact(self.classes)
            .flat_map_iter(|h| {
                let norm = h.iter().map(|v| v * v).sum::<f64>().sqrt();
                h.iter()
                    .map(move |v| if norm > 0.0 { (v / norm) as f32 } else { 0.0 })
            })
            .collect()
    }

    /// Gaussians that received any weight.
    pub fn observed(&self) -> usize {
        self.hist
            .chunks_exact(self.classes)
            .filter(|h| h.iter().any(|&v| v > 0.0))
            .count()
    }
}

fn check_weights(w: &PixelWeights, pixels: usize) -> Result<()> {
    let ok = w.offsets.len() == pixels + 1
        && w.ids.len() == w.weights.len()
        && w.offsets.windows(2).all(|p| p[0] <= p[1])
        && w.offsets.last().is_some_and(|&e| e as usize == w.ids.len());
    if ok {
        Ok(())
    } else {
        Err(Error::internal(
            "malformed PixelWeights (offsets/ids/weights); rasterize at the view's raster size",
        ))
    }
}

/// Per-class pixel counts of one predictor, summed over views.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Confusion {
    /// Counted pixels predicted `c` whose truth is `c`.
    pub intersection: Vec<u64>,
    /// Counted pixels predicted `c`.
    pub predicted: Vec<u64>,
}

impl Confusion {
    fn new(classes: usize) -> Self {
        Self {
            intersection: vec![0; classes],
            predicted: vec![0; classes],
        }
    }
    fn add(&mut self, other: &Confusion) {
        for (a, b) in self.intersection.iter_mut().zip(&other.intersection) {
            *a += b;
        }
        for (a, b) in self.predicted.iter_mut().zip(&other.predicted) {
            *a += b;
        }
    }
}

/// The held-out tallies of several predictors over the same counted pixels.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HeldOutTally {
    /// Counted pixels (alpha ≥ [`ALPHA_MIN`]) per truth class.
    pub truth: Vec<u64>,
    /// Pixels seen (counted or not).
    pub pixels: u64,
    /// One [`Confusion`] per predictor, in the order the score tables were passed.
    pub predictors: Vec<Confusion>,
}

impl HeldOutTally {
    /// An empty tally of `predictors` predictors over `classes` classes.
    pub fn new(classes: usize, predictors: usize) -> Self {
        Self {
            truth: vec![0; classes],
            pixels: 0,
            predictors: vec![Confusion::new(classes); predictors],
        }
    }

    /// Counted pixels.
    pub fn counted(&self) -> u64 {
        self.truth.iter().sum()
    }

    /// Adds one held-out view: `weights` is its full-resolution raster, `truth` its
    /// [`photo_classes`] on the same grid, `scores` one `[scene Gaussians × C]` table per predictor
    /// (as [`gaussian_scores`] returns). Each predictor's per-pixel class is
    /// `argmax_c Σ_k w_kp · s_kc` (ties → lower index); a pixel counts when `Σ_k w_kp ≥ ALPHA_MIN`.
    ///
    /// Errors: a different number of score tables than predictors, a table of the wrong size,
    /// truth of the wrong length or class, malformed weights ([`Error::Internal`]), a contributor
    /// outside the scene ([`Error::Mismatch`]).
    pub fn add_view(
        &mut self,
        weights: &PixelWeights,
        truth: &[u8],
        scores: &[&[f32]],
        scene_gaussians: usize,
    ) -> Result<()> {
        let c = self.truth.len();
        let pixels = weights.width as usize * weights.height as usize;
        if scores.len() != self.predictors.len() {
            return Err(Error::internal(format!(
                "{} score tables for {} predictors",
                scores.len(),
                self.predictors.len()
            )));
        }
        if let Some(s) = scores.iter().find(|s| s.len() != scene_gaussians * c) {
            return Err(Error::internal(format!(
                "a score table holds {} values; expected {scene_gaussians} Gaussians × {c} classes",
                s.len()
            )));
        }
        if truth.len() != pixels || truth.iter().any(|&t| t as usize >= c) {
            return Err(Error::internal(format!(
                "{} truth labels for {pixels} pixels (classes 0..{c}); take them with \
                 photo_classes at the raster size",
                truth.len()
            )));
        }
        check_weights(weights, pixels)?;
        if let Some(&k) = weights.ids.iter().find(|&&k| k as usize >= scene_gaussians) {
            return Err(Error::mismatch(
                slag_common::Mismatched::Scene,
                format!("pixel weights reference Gaussian {k} but the scene has {scene_gaussians}"),
            ));
        }
        let width = weights.width as usize;
        let np = self.predictors.len();
        let parts: Vec<(Vec<u64>, Vec<Confusion>)> = (0..weights.height as usize)
            .into_par_iter()
            .fold(
                || (vec![0u64; c], vec![Confusion::new(c); np]),
                |(mut tr, mut conf), y| {
                    let mut acc = vec![0f32; c];
                    let row = y * width..(y + 1) * width;
                    for (p, &t) in row.clone().zip(&truth[row]) {
                        let (a, b) = (weights.offsets[p] as usize, weights.offsets[p + 1] as usize);
                        let (ids, ws) = (&weights.ids[a..b], &weights.weights[a..b]);
                        let alpha: f32 = ws.iter().sum();
                        if alpha < ALPHA_MIN {
                            continue;
                        }
                        let t = t as usize;
                        tr[t] += 1;
                        for (table, cf) in scores.iter().zip(conf.iter_mut()) {
                            acc.iter_mut().for_each(|v| *v = 0.0);
                            for (&k, &wk) in ids.iter().zip(ws) {
                                let s = &table[k as usize * c..(k as usize + 1) * c];
                                acc.iter_mut().zip(s).for_each(|(v, s)| *v += wk * s);
                            }
                            let mut best = 0;
                            for i in 1..c {
                                if acc[i] > acc[best] {
                                    best = i;
                                }
                            }
                            cf.predicted[best] += 1;
                            if best == t {
                                cf.intersection[best] += 1;
                            }
                        }
                    }
                    (tr, conf)
                },
            )
            .collect();
        for (tr, conf) in parts {
            self.truth.iter_mut().zip(&tr).for_each(|(a, b)| *a += b);
            for (a, b) in self.predictors.iter_mut().zip(&conf) {
                a.add(b);
            }
        }
        self.pixels += pixels as u64;
        Ok(())
    }

    /// The class most frequent among the counted pixels' truth (ties → lower index).
    pub fn majority_class(&self) -> usize {
        let mut best = 0;
        for (i, &t) in self.truth.iter().enumerate() {
            if t > self.truth[best] {
                best = i;
            }
        }
        best
    }

    /// The majority-class predictor's confusion: every counted pixel predicted
    /// [`Self::majority_class`].
    pub fn majority(&self) -> Confusion {
        let m = self.majority_class();
        let mut cf = Confusion::new(self.truth.len());
        cf.predicted[m] = self.counted();
        cf.intersection[m] = self.truth[m];
        cf
    }

    /// Scores `confusion` against this tally's truth (`names`: class names, one per class).
    pub fn score(&self, confusion: &Confusion, names: &[String]) -> PixelScore {
        let counted = self.counted();
        let classes: Vec<PixelClassScore> = (0..self.truth.len())
            .map(|c| {
                let (i, t, p) = (
                    confusion.intersection[c],
                    self.truth[c],
                    confusion.predicted[c],
                );
                let union = t + p - i;
                PixelClassScore {
                    name: names
                        .get(c)
                        .cloned()
                        .unwrap_or_else(|| format!("class {c}")),
                    iou: (union > 0).then(|| i as f64 / union as f64),
                    truth_pixels: t,
                    predicted_pixels: p,
                    intersection: i,
                    in_miou: counted > 0 && t as f64 >= MIOU_MIN_CLASS_FRACTION * counted as f64,
                }
            })
            .collect();
        let averaged: Vec<&PixelClassScore> = classes.iter().filter(|c| c.in_miou).collect();
        let miou = (!averaged.is_empty()).then(|| {
            averaged.iter().map(|c| c.iou.unwrap_or(0.0)).sum::<f64>() / averaged.len() as f64
        });
        let correct: u64 = confusion.intersection.iter().sum();
        PixelScore {
            miou,
            pixel_accuracy: (counted > 0).then(|| correct as f64 / counted as f64),
            classes,
        }
    }
}

/// One class's held-out pixel score.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct PixelClassScore {
    /// Class name (colour word).
    pub name: String,
    /// `|pred = c ∧ truth = c| / |pred = c ∨ truth = c|` over the counted pixels of all held-out
    /// views; `None` when the union is empty.
    pub iou: Option<f64>,
    /// Counted pixels whose truth is this class.
    pub truth_pixels: u64,
    /// Counted pixels predicted as this class.
    pub predicted_pixels: u64,
    /// Counted pixels with truth and prediction both this class.
    pub intersection: u64,
    /// Whether the class enters the mIoU (truth ≥ 1 % of the counted pixels).
    pub in_miou: bool,
}

/// One predictor's held-out score.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct PixelScore {
    /// Mean IoU over the classes with `in_miou`; `None` when no pixel was counted.
    pub miou: Option<f64>,
    /// Correct counted pixels / counted pixels.
    pub pixel_accuracy: Option<f64>,
    /// Per-class scores, in class-index order.
    pub classes: Vec<PixelClassScore>,
}

impl PixelScore {
    /// The names of the classes that [`PixelScore::miou`] averages over (`in_miou`), in
    /// class-index order.
    pub fn miou_classes(&self) -> Vec<String> {
        self.classes
            .iter()
            .filter(|c| c.in_miou)
            .map(|c| c.name.clone())
            .collect()
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)] // tests fail loudly on purpose
mod tests {
    use super::*;

    fn names(k: usize) -> Vec<String> {
        (0..k).map(|c| format!("c{c}")).collect()
    }

    /// A raster with the given per-pixel contributor lists.
    fn raster(width: u32, height: u32, pixels: &[&[(u32, f32)]]) -> PixelWeights {
        let mut w = PixelWeights {
            width,
            height,
            offsets: vec![0],
            ..PixelWeights::default()
        };
        for p in pixels {
            for &(k, x) in *p {
                w.ids.push(k);
                w.weights.push(x);
            }
            w.offsets.push(w.ids.len() as u32);
        }
        w
    }

    #[test]
    fn blended_argmax_alpha_cut_and_ious() {
        // 3 Gaussians, 2 classes. Scores: g0 → class 0, g1 → class 1, g2 unobserved (0, 0).
        let scores = [1.0, 0.0, 0.0, 1.0, 0.0, 0.0];
        // 4 pixels in a 2×2 raster:
        //  p0: g0 0.7                    → alpha 0.7, predicts 0
        //  p1: g0 0.3, g1 0.6            → alpha 0.9, predicts 1 (blend 0.3 vs 0.6)
        //  p2: g1 0.2                    → alpha 0.2 < 0.5: not counted
        //  p3: g2 0.9                    → alpha 0.9, all scores 0 → class 0 (tie → lower)
        let w = raster(
            2,
            2,
            &[&[(0, 0.7)], &[(0, 0.3), (1, 0.6)], &[(1, 0.2)], &[(2, 0.9)]],
        );
        let truth = [0u8, 0, 1, 1];
        let mut t = HeldOutTally::new(2, 1);
        t.add_view(&w, &truth, &[&scores], 3).unwrap();
        assert_eq!(t.truth, vec![2, 1]);
        assert_eq!(t.counted(), 3);
        assert_eq!(t.pixels, 4);
        let cf = &t.predictors[0];
        assert_eq!(cf.predicted, vec![2, 1]);
        assert_eq!(cf.intersection, vec![1, 0]);
        let s = t.score(cf, &names(2));
        // class 0: ∩ {p0}, ∪ {p0, p1, p3} → 1/3; class 1: ∩ {}, ∪ {p1, p3} → 0.
        assert_eq!(s.classes[0].iou, Some(1.0 / 3.0));
        assert_eq!(s.classes[1].iou, Some(0.0));
        assert_eq!(s.miou, Some(1.0 / 6.0));
        assert_eq!(s.pixel_accuracy, Some(1.0 / 3.0));
        // Majority: class 0 everywhere → IoU 2/3 and 0.
        let m = t.score(&t.majority(), &names(2));
        assert_eq!(m.classes[0].iou, Some(2.0 / 3.0));
        assert_eq!(m.classes[1].iou, Some(0.0));
    }

    #[test]
    fn tally_rejects_inconsistent_input() {
        let w = raster(1, 1, &[&[(0, 1.0)]]);
        let mut t = HeldOutTally::new(2, 1);
        let s = [1.0f32, 0.0];
        assert!(t.add_view(&w, &[0], &[&s[..1]], 1).is_err()); // table too small
        assert!(t.add_view(&w, &[2], &[&s], 1).is_err()); // class out of range
        assert!(t.add_view(&w, &[0, 0], &[&s], 1).is_err()); // truth too long
        assert!(t.add_view(&w, &[0], &[&s, &s], 1).is_err()); // two tables, one predictor
        let bad = raster(1, 1, &[&[(5, 1.0)]]);
        assert!(t.add_view(&bad, &[0], &[&s], 1).is_err()); // Gaussian outside the scene
        assert_eq!(t.counted(), 0);
    }

    #[test]
    fn scores_are_cosines_and_zero_for_unobserved() {
        let e = Embeddings {
            ids: vec![2, 0],
            means: vec![[0.0; 3]; 2],
            dim: 2,
            vectors: vec![0.6, 0.8, 1.0, 0.0],
            total_weights: vec![1.0; 2],
            scene_gaussians: 3,
            ..Embeddings::default()
        };
        // Texts of any norm are normalised.
        let texts = vec![vec![2.0, 0.0], vec![0.0, 0.5]];
        let s = gaussian_scores(&e, &texts, 3).unwrap();
        assert_eq!(s, vec![1.0, 0.0, 0.0, 0.0, 0.6, 0.8]);
        assert!(gaussian_scores(&e, &texts, 2).is_err()); // id 2 outside 2 Gaussians
        assert!(gaussian_scores(&e, &[vec![0.0, 0.0]], 3).is_err());
        assert!(gaussian_scores(&e, &[vec![1.0]], 3).is_err());
        assert!(gaussian_scores(&e, &[], 3).is_err());
    }

    #[test]
    fn oracle_lifts_photo_classes_with_the_blend_weights() {
        let cc = ColorClasses {
            names: names(2),
            prototypes_rgb01: vec![[0.0; 3], [1.0; 3]],
        };
        // 2×1 photo: black, white.
        let photo = RgbImage::from_fn(2, 1, |x, _| image::Rgb([255 * x as u8; 3]));
        let classes = photo_classes(&cc, &photo, 2, 1).unwrap();
        assert_eq!(classes, vec![0, 1]);
        // Downsampled to one pixel: the centre samples column 1.
        assert_eq!(photo_classes(&cc, &photo, 1, 1).unwrap(), vec![1]);

        struct Fixed(PixelWeights);
        impl WeightRasterizer for Fixed {
            fn rasterize(&mut self, _: &Intrinsics, _: &WorldToCamera) -> Result<PixelWeights> {
                Ok(self.0.clone())
            }
            fn name(&self) -> &str {
                "fixed"
            }
        }
        // g0 sees both pixels (0.3 black, 0.4 white), g1 only the white one, g2 nothing.
        let mut r = Fixed(raster(2, 1, &[&[(0, 0.3)], &[(0, 0.4), (1, 0.5)]]));
        let intr = Intrinsics {
            width: 2,
            height: 1,
            fx: 1.0,
            fy: 1.0,
            cx: 1.0,
            cy: 0.5,
        };
        let pose = WorldToCamera {
            rotation: glam::DMat3::IDENTITY,
            translation: glam::DVec3::ZERO,
        };
        let mut o = OracleLifting::new(3, 2).unwrap();
        o.add_view(&mut r, &intr, &pose, &classes).unwrap();
        let s = o.scores();
        assert!(
            (s[0] - 0.6).abs() < 1e-6 && (s[1] - 0.8).abs() < 1e-6,
            "{s:?}"
        );
        assert_eq!(&s[2..], &[0.0, 1.0, 0.0, 0.0]);
        assert_eq!(o.observed(), 2);
        assert!(o.add_view(&mut r, &intr, &pose, &[0]).is_err());
        assert!(o.add_view(&mut r, &intr, &pose, &[0, 2]).is_err());
    }
}
