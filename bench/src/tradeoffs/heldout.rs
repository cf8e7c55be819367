//! The study's accuracy axis: held-out 2D mIoU, the protocol of `slag-encoder eval-colors
//! --held-out` ([`slag_eval::heldout`]) on one set of views shared by every point.
//!
//! `eval-colors --held-out` holds out the views `i ≡ ⌊N/2⌋ (mod N)` of an encode made with
//! `--every N`; the study's points use different steps, so their splits differ, and a point with
//! `--every 2` encodes views another point holds out. The study therefore holds out the views
//! that **no** point of its plan encodes ([`slag_encoder::views::held_out_for_all`] over the
//! plan's steps of 2 or more) and scores every point on exactly those pixels: renders at full
//! resolution, class scores `cos(E_k, text_c)` blended with `w_kp`, argmax, pixels of rendered
//! alpha ≥ [`heldout::ALPHA_MIN`], mIoU over the classes holding ≥ 1 % of the counted pixels. A
//! point encoded from every view (`--every 1`) leaves none held out and gets no held-out score.

use std::path::Path;

use anyhow::Context;
use slag_common::camera::{self, View};
use slag_common::embeddings::Embeddings;
use slag_common::scene::Gaussians;
use slag_encoder::config::RasterBackend;
use slag_encoder::raster::WeightRasterizer;
use slag_eval::{ColorClasses, heldout};

/// The held-out views of a study, their photo classes, and the rasterizer that renders them.
pub struct HeldOutViews {
    /// The held-out views, name order.
    pub views: Vec<View>,
    /// Per view, the class of every full-resolution pixel ([`heldout::photo_classes`]).
    truth: Vec<Vec<u8>>,
    rasterizer: Box<dyn WeightRasterizer>,
    classes: Vec<String>,
    scene_gaussians: usize,
}

/// One point's held-out score.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct HeldOutScore {
    /// mIoU over the classes with ≥ 1 % of the counted pixels.
    pub miou: Option<f64>,
    /// Correct counted pixels / counted pixels.
    pub pixel_accuracy: Option<f64>,
    /// The majority-class baseline on the same pixels (every counted pixel its most frequent
    /// class).
    pub majority_miou: Option<f64>,
}

impl HeldOutViews {
    /// The views of `scene` that none of the encodes with steps `everys` saw (steps below 2 are
    /// left out: those encodes are not scored), with their photo classes, and a `backend`
    /// rasterizer over `gaussians` (the scene's `.ply`).
    ///
    /// Errors: no step of 2 or more, or no view left unencoded ([`slag_common::Error::Param`]
    /// `every`); unreadable views or photos; the rasterizer's errors.
    pub fn load(
        scene: &Path,
        gaussians: &Gaussians,
        classes: &ColorClasses,
        everys: &[usize],
        backend: RasterBackend,
    ) -> anyhow::Result<Self> {
        let mut steps: Vec<usize> = everys.iter().copied().filter(|&e| e >= 2).collect();
        steps.sort_unstable();
        steps.dedup();
        let all = camera::load_views(scene)?;
        let held = slag_encoder::views::held_out_for_all(all.len(), &steps)?;
        let views: Vec<View> = all
            .into_iter()
            .enumerate()
            .filter(|(i, _)| held.contains(i))
            .map(|(_, v)| v)
            .collect();
        // At the grid the renders use (`raster_intrinsics` at scale 1), as eval-colors does.
        let truth = views
            .iter()
            .map(|v| {
                let intr = slag_encoder::raster::raster_intrinsics(&v.intrinsics, 1.0)?;
                let photo = slag_encoder::pipeline::read_image(v)?;
                Ok(heldout::photo_classes(
                    classes,
                    &photo,
                    intr.width,
                    intr.height,
                )?)
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        Ok(HeldOutViews {
            views,
            truth,
            rasterizer: slag_encoder::pipeline::build::make_rasterizer(backend, gaussians)?,
            classes: classes.names.clone(),
            scene_gaussians: gaussians.len(),
        })
    }

    /// Names of the held-out views, name order.
    pub fn names(&self) -> Vec<String> {
        self.views.iter().map(|v| v.name.clone()).collect()
    }

    /// Scores `emb` against the class texts `prompts` (one per class, the classes' order) on
    /// every held-out view.
    ///
    /// Errors: embeddings of another scene or width ([`heldout::gaussian_scores`]), rasterizer
    /// failures.
    pub fn score(
        &mut self,
        emb: &Embeddings,
        prompts: &[Vec<f32>],
    ) -> anyhow::Result<HeldOutScore> {
        let n = self.scene_gaussians;
        let scores = heldout::gaussian_scores(emb, prompts, n)?;
        let mut tally = heldout::HeldOutTally::new(self.classes.len(), 1);
        for (v, truth) in self.views.iter().zip(&self.truth) {
            let intr = slag_encoder::raster::raster_intrinsics(&v.intrinsics, 1.0)?;
            let weights = self
                .rasterizer
                .rasterize(&intr, &v.world_to_camera)
                .with_context(|| format!("rendering held-out view {}", v.name))?;
            tally.add_view(&weights, truth, &[&scores], n)?;
        }
        let slag = tally.score(&tally.predictors[0], &self.classes);
        Ok(HeldOutScore {
            miou: slag.miou,
            pixel_accuracy: slag.pixel_accuracy,
            majority_miou: tally.score(&tally.majority(), &self.classes).miou,
        })
    }
}
