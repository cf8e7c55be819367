//! The encode pipeline: for each posed image, masks → CLIP crop embeddings → weight raster →
//! image-stage aggregation, then the reduction over all images and the output files.
//!
//! Two threads overlap the stages: the *front* thread decodes image i+1, generates its masks and
//! embeds its crops while the *back* thread rasterizes image i and computes its `a_kj`
//! (a bounded channel of depth 2 keeps memory flat). Every per-image step is independent, as in
//! the paper; only the reduction sees all images.

use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::Instant;

use image::RgbImage;
use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle};
use slag_common::camera::{self, View};
use slag_common::embeddings::{Embeddings, StoredPrecision, write_atomic};
use slag_common::scene::{self, Gaussians, PlyLoadOptions};
use slag_common::{Error, Result};

use crate::aggregate::{self, ContributionStore, ImageStageParams, ReduceParams};
use crate::masks::{Mask, MaskGenerator};
use crate::raster::WeightRasterizer;
use crate::report::{Counts, Report, StageTimings};

/// Embeds the masks of one image: one L2-normalised vector per mask (the paper's
/// `E_j = CLIP(crop_j(I ⊙ M_j))`).
pub trait CropEmbedder: Send {
    /// Model id recorded in the outputs (e.g. the ONNX file stem).
    fn model_id(&self) -> &str;
    /// Embedding width D.
    fn dim(&self) -> usize;
    /// `[masks.len()]` vectors of length [`CropEmbedder::dim`].
    fn embed(&mut self, image: &RgbImage, masks: &[Mask]) -> Result<Vec<Vec<f32>>>;
}

/// Where the scene comes from and what to encode.
#[derive(Debug, Clone)]
pub struct SceneInput {
    /// Scene folder with `images/` and `sparse/0` or `transforms.json`.
    pub dir: PathBuf,
    /// The `.ply` (default `<dir>/point_cloud.ply`).
    pub ply: PathBuf,
    /// Keep every N-th view (paper: 1:20 on large scenes).
    pub every: usize,
}

impl SceneInput {
    /// `dir` with the default `.ply` location.
    pub fn new(dir: &Path, ply: Option<&Path>, every: usize) -> Self {
        let ply = ply
            .map(Path::to_path_buf)
            .unwrap_or_else(|| dir.join("point_cloud.ply"));
        Self {
            dir: dir.to_path_buf(),
            ply,
            every,
        }
    }

    /// Loads the Gaussians (geometry only: the weights never need SH colours) and the views.
    pub fn load(&self) -> Result<(Gaussians, Vec<View>, usize)> {
        if !self.dir.is_dir() {
            return Err(Error::Invalid(format!(
                "scene folder {} does not exist; pass --scene DIR holding point_cloud.ply, images/ and sparse/0 or transforms.json",
                self.dir.display()
            )));
        }
        let gaussians = scene::load_ply(&self.ply, PlyLoadOptions::default())?;
        let views = camera::load_views(&self.dir)?;
        let total = views.len();
        Ok((gaussians, camera::subsample(views, self.every), total))
    }
}

/// Parameters of one encode run besides the stage implementations.
#[derive(Debug, Clone)]
pub struct EncodeParams {
    /// Raster resolution relative to the images (`--raster-scale`, 0 < s ≤ 1 typical).
    pub raster_scale: f64,
    /// Image-stage knobs.
    pub image_stage: ImageStageParams,
    /// Reduction knobs.
    pub reduce: ReduceParams,
    /// Bytes of image contributions kept in memory before spilling to disk.
    pub contribution_budget_bytes: usize,
    /// Stored precision of the embeddings.
    pub precision: StoredPrecision,
    /// Output folder (`embeddings.safetensors`, `report.json`).
    pub out_dir: PathBuf,
    /// Show progress bars (stderr).
    pub progress: bool,
    /// Also write `<out>/mixture.safetensors`: the embeddings as a shared codebook of mask
    /// embeddings plus each Gaussian's `S` largest `a_kj` ([`aggregate::reduce_mixture`]);
    /// `None` = dense file only.
    pub mixture_keep: Option<usize>,
}

/// Decoded image + its masks and mask embeddings, passed from the front to the back thread.
struct FrontItem {
    view: usize,
    masks: Vec<Mask>,
    embeddings: Vec<f32>,
    decode_s: f64,
    masks_s: f64,
    clip_s: f64,
}

/// Reads an image and checks it against the camera's intrinsics.
pub fn read_image(view: &View) -> Result<RgbImage> {
    // Pillow-exact JPEG decoding, so SAM/CLIP inputs match the Python reference pipeline.
    let img = crate::preprocess::load_rgb(&view.image_path)?;
    let (w, h) = (view.intrinsics.width, view.intrinsics.height);
    if img.dimensions() != (w, h) {
        return Err(Error::Invalid(format!(
            "{} is {}x{} but its camera is {w}x{h}: images/ must hold the (undistorted) images the camera model describes",
            view.image_path.display(),
            img.width(),
            img.height()
        )));
    }
    Ok(img)
}

fn bar(multi: &MultiProgress, len: usize, label: &str) -> ProgressBar {
    let style =
        ProgressStyle::with_template("{prefix:>18} [{bar:30}] {pos}/{len} {per_sec} eta {eta}")
            .map(|s| s.progress_chars("=> "))
            .unwrap_or_else(|_| ProgressStyle::default_bar());
    multi.add(
        ProgressBar::new(len as u64)
            .with_style(style)
            .with_prefix(label.to_string()),
    )
}

/// Runs the whole Semantic Embedding stage on `scene` and writes
/// `<out>/embeddings.safetensors` (+ `<out>/mixture.safetensors` with
/// [`EncodeParams::mixture_keep`]) + `<out>/report.json` (each atomically; the report last, so a
/// report's presence means the run completed).
pub fn encode(
    scene: &SceneInput,
    mut masks: Box<dyn MaskGenerator>,
    mut crops: Box<dyn CropEmbedder>,
    make_rasterizer: impl FnOnce(&Gaussians) -> Result<Box<dyn WeightRasterizer>>,
    params: &EncodeParams,
    mut report: Report,
) -> Result<Report> {
    let t_total = Instant::now();
    let mut t = StageTimings::default();
    let t0 = Instant::now();
    let (gaussians, views, views_total) = scene.load()?;
    t.load_scene = t0.elapsed().as_secs_f64();
    if views.is_empty() {
        return Err(Error::Invalid(format!(
            "{}: no views to encode (check --every)",
            scene.dir.display()
        )));
    }
    // Raster intrinsics of every view, checked (scale range, raster size) before any image work.
    let raster_intrinsics = views
        .iter()
        .map(|v| crate::raster::raster_intrinsics(&v.intrinsics, params.raster_scale))
        .collect::<Result<Vec<_>>>()?;
    tracing::info!(
        gaussians = gaussians.len(),
        views = views.len(),
        "scene loaded"
    );
    let mut rasterizer = make_rasterizer(&gaussians)?;
    if let Some(models) = report.models.as_object_mut() {
        models.insert("rasterizer".into(), rasterizer.name().into());
        models.insert("clip_model_id".into(), crops.model_id().into());
        models.insert("masks".into(), masks.name().into());
    }
    let dim = crops.dim();
    let model_id = crops.model_id().to_string();
    let multi = MultiProgress::with_draw_target(if params.progress {
        ProgressDrawTarget::stderr()
    } else {
        ProgressDrawTarget::hidden()
    });
    let bar_front = bar(&multi, views.len(), "masks + CLIP");
    let bar_back = bar(&multi, views.len(), "raster + a_kj");
    let spill_dir = params.out_dir.join(".contributions.partial");
    let mut store = ContributionStore::new(params.contribution_budget_bytes, spill_dir);
    let mut counts = Counts {
        views_total,
        views_used: views.len(),
        gaussians: gaussians.len(),
        ..Default::default()
    };
    let mut raster_pixels = 0usize;
    let mut raster_entries = 0usize;

    std::thread::scope(|s| -> Result<()> {
        let (tx, rx) = mpsc::sync_channel::<Result<FrontItem>>(2);
        let views_ref = &views;
        let bar_front = &bar_front;
        s.spawn(move || {
            for (i, view) in views_ref.iter().enumerate() {
                let item = (|| {
                    let t0 = Instant::now();
                    let img = read_image(view)?;
                    let t1 = Instant::now();
                    let m = masks.generate(&img)?;
                    let t2 = Instant::now();
                    let e = crops.embed(&img, &m)?;
                    let t3 = Instant::now();
                    if e.len() != m.len() || e.iter().any(|v| v.len() != dim) {
                        return Err(Error::Invalid(format!(
                            "{}: CLIP returned {} vectors for {} masks",
                            view.name,
                            e.len(),
                            m.len()
                        )));
                    }
                    Ok(FrontItem {
                        view: i,
                        masks: m,
                        embeddings: e.concat(),
                        decode_s: (t1 - t0).as_secs_f64(),
                        masks_s: (t2 - t1).as_secs_f64(),
                        clip_s: (t3 - t2).as_secs_f64(),
                    })
                })();
                let failed = item.is_err();
                bar_front.inc(1);
                if tx.send(item).is_err() || failed {
                    return;
                }
            }
        });
        for item in rx {
            let item = item?;
            t.decode += item.decode_s;
            t.masks += item.masks_s;
            t.clip += item.clip_s;
            let view = &views[item.view];
            let t0 = Instant::now();
            let intr = &raster_intrinsics[item.view];
            let weights = rasterizer.rasterize(intr, &view.world_to_camera)?;
            let t1 = Instant::now();
            raster_pixels += (weights.width * weights.height) as usize;
            raster_entries += weights.ids.len();
            counts.masks += item.masks.len();
            let c = aggregate::image_contribution(
                &weights,
                &item.masks,
                item.embeddings,
                dim,
                params.image_stage,
            )?;
            counts.entries += c.entries.len();
            store.push(c)?;
            t.raster += (t1 - t0).as_secs_f64();
            t.image_aggregate += t1.elapsed().as_secs_f64();
            bar_back.inc(1);
            tracing::debug!(view = %view.name, masks = item.masks.len(), "image done");
        }
        Ok(())
    })?;
    bar_front.finish();
    bar_back.finish();

    let t0 = Instant::now();
    let reduced = aggregate::reduce(&store, gaussians.len(), dim, params.reduce)?;
    t.reduce = t0.elapsed().as_secs_f64();
    counts.spilled_images = store.spilled();
    counts.reduce_chunks = reduced.chunks;
    counts.observed = reduced.ids.len();
    counts.observed_fraction = reduced.ids.len() as f64 / gaussians.len().max(1) as f64;
    counts.contributors_per_pixel = raster_entries as f64 / raster_pixels.max(1) as f64;
    let t0 = Instant::now();
    let mixture = params
        .mixture_keep
        .map(|keep| {
            let (n, p) = (gaussians.len(), params.reduce);
            aggregate::reduce_mixture(&store, n, dim, p, keep, &model_id, &gaussians.means)
        })
        .transpose()?;
    let mixture_s = t0.elapsed().as_secs_f64();
    drop(store);

    let t0 = Instant::now();
    let embeddings = Embeddings {
        means: reduced
            .ids
            .iter()
            .map(|&k| gaussians.means[k as usize])
            .collect(),
        ids: reduced.ids,
        dim,
        vectors: reduced.vectors,
        total_weights: reduced.total_weights,
        model: model_id,
        scene_gaussians: gaussians.len() as u64,
        source_ply: scene.ply.display().to_string(),
    };
    let emb_path = params.out_dir.join("embeddings.safetensors");
    let report_path = params.out_dir.join("report.json");
    // A stale report from an earlier run must not vouch for the new embeddings while they are written.
    if report_path.exists() {
        std::fs::remove_file(&report_path).map_err(|e| Error::io(&report_path, e))?;
    }
    embeddings.write(&emb_path, params.precision)?;
    let mix_path = params.out_dir.join("mixture.safetensors");
    match &mixture {
        Some(m) => m.write(&mix_path)?,
        // A mixture of an earlier run must not sit beside this run's report.
        None if mix_path.exists() => {
            std::fs::remove_file(&mix_path).map_err(|e| Error::io(&mix_path, e))?
        }
        None => {}
    }
    t.write = t0.elapsed().as_secs_f64();
    t.total = t_total.elapsed().as_secs_f64();
    let emb_bytes = std::fs::metadata(&emb_path).map(|m| m.len()).unwrap_or(0);
    report.timings = t;
    report.counts = counts;
    report.outputs = serde_json::json!({
        "embeddings": emb_path, "embeddings_bytes": emb_bytes,
        "precision": params.precision, "report": report_path,
        "mixture": mixture.as_ref().map(|_| &mix_path),
        "mixture_keep": mixture.as_ref().map(|m| m.keep),
        "mixture_codebook_rows": mixture.as_ref().map(|m| m.codebook_len()),
        "mixture_bytes_per_gaussian": mixture.as_ref().map(|m| m.bytes_per_gaussian()),
        "mixture_reduce_s": mixture.as_ref().map(|_| mixture_s),
    });
    let json =
        serde_json::to_vec_pretty(&report).map_err(|e| Error::Invalid(format!("report: {e}")))?;
    write_atomic(&report_path, &json)?;
    Ok(report)
}

impl CropEmbedder for crate::clip::ClipVisual {
    fn model_id(&self) -> &str {
        crate::clip::ClipVisual::model_id(self)
    }
    fn dim(&self) -> usize {
        crate::clip::ClipVisual::dim(self)
    }
    fn embed(&mut self, image: &RgbImage, masks: &[Mask]) -> Result<Vec<Vec<f32>>> {
        self.embed_masks(image, masks)
    }
}
