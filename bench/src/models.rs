//! `slag-bench models`: each ONNX model of the encode timed alone, as the encoder runs it, and
//! variants of one model checked against the first on the same inputs.
//!
//! - CLIP image towers (`--clip-visual`, repeatable): the white-background crops of real masks
//!   (the graph segmenter's, on `--images` views of `--scene`), cut and resized as `encode`
//!   does, run `--batch` crops at a time (short batches padded, as on a GPU); reported per crop,
//!   CLIP's normalisation on the host included for a tower whose input is f32 (a tower with
//!   byte input does it in its graph). Every tower after the first is compared with the first crop by crop (cosine of
//!   the L2-normalised embeddings).
//! - SAM (`--sam-encoder` / `--sam-decoder`, paired in order): the image encoder per image on the
//!   same views, and the prompt decoder per image for the `--points-per-side`² grid in runs of
//!   `--prompt-batch` prompts (SAM's automatic mask generation prompts, as `encode` feeds them:
//!   one point and one padding point each). Decoder variants after the first are compared with it
//!   on the first encoder's embeddings: predicted IoUs (largest absolute difference) and the
//!   low-resolution masks (IoU of the `logit > 0` sets per prompt and channel).
//!
//! Times are medians over `--repeats` passes after one warm-up pass, wall clock around each
//! session run (inputs on the host, outputs back to the host, as in `encode`); the decoder's
//! time counts its session runs only, not the comparison of its outputs. With
//! `SLAG_ORT_PROFILE=PREFIX` every session also writes ONNX Runtime's per-node trace.

use anyhow::{Context, ensure};
use ort::session::Session;
use ort::value::TensorRef;
use slag_common::camera::load_views;
use slag_common::onnx::{OnnxModel, Placement};
use slag_common::table::Table;
use slag_encoder::clip::{ClipVisual, CropFill, VisualInput, crop_pixels};
use slag_encoder::masks::MaskGenerator;
use slag_encoder::masks::graph::{GraphParams, GraphSegmenter};
use slag_encoder::preprocess::{load_rgb, sam_pixel_values};
use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Instant;

/// Arguments of `slag-bench models`.
#[derive(Debug, Clone, clap::Args)]
pub struct ModelsArgs {
    /// Scene folder whose images give the inputs (COLMAP or transforms.json).
    #[arg(long = "scene-dir", value_name = "DIR")]
    pub scene: PathBuf,
    /// Views used, spread evenly over the scene.
    #[arg(long, default_value_t = 8)]
    pub images: usize,
    /// CLIP image tower to time (repeatable; the first is the reference of the others).
    #[arg(long)]
    pub clip_visual: Vec<PathBuf>,
    /// Crops per CLIP run.
    #[arg(long, default_value_t = 64)]
    pub batch: usize,
    /// SAM image encoder to time (repeatable; paired with --sam-decoder in order).
    #[arg(long)]
    pub sam_encoder: Vec<PathBuf>,
    /// SAM prompt decoder to time (repeatable; the first is the reference of the others).
    #[arg(long)]
    pub sam_decoder: Vec<PathBuf>,
    /// SAM prompt grid side (256 prompts at 16).
    #[arg(long, default_value_t = 16)]
    pub points_per_side: u32,
    /// Prompts per decoder run.
    #[arg(long, default_value_t = 256)]
    pub prompt_batch: usize,
    /// Timed passes over the inputs, after one warm-up pass.
    #[arg(long, default_value_t = 5)]
    pub repeats: usize,
    /// Execution provider.
    #[arg(long, value_enum, default_value_t = slag_common::cli::EpArg::Cuda)]
    pub ep: slag_common::cli::EpArg,
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Plain cosine of `a` and `b`: [`centred_cosine`] about a zero mean.
fn cosine(a: &[f32], b: &[f32]) -> f64 {
    centred_cosine(a, b, std::iter::repeat(0.0))
}

/// The mean of equal-length rows.
fn mean_row(rows: &[Vec<f32>]) -> Vec<f64> {
    let mut m = vec![0f64; rows.first().map_or(0, Vec::len)];
    for r in rows {
        for (a, &v) in m.iter_mut().zip(r) {
            *a += f64::from(v);
        }
    }
    let n = rows.len().max(1) as f64;
    m.iter_mut().for_each(|a| *a /= n);
    m
}

/// Cosine of `a − mean` and `b − mean`, summed in f64 (`mean` yields one value per component).
fn centred_cosine(a: &[f32], b: &[f32], mean: impl IntoIterator<Item = f64>) -> f64 {
    let (mut ab, mut aa, mut bb) = (0f64, 0f64, 0f64);
    for ((&x, &y), m) in a.iter().zip(b).zip(mean) {
        let (x, y) = (f64::from(x) - m, f64::from(y) - m);
        ab += x * y;
        aa += x * x;
        bb += y * y;
    }
    ab / (aa.sqrt() * bb.sqrt()).max(1e-30)
}

/// `"min / median"` of `v`, five decimals.
fn min_median(v: Vec<f64>) -> String {
    let min = v.iter().copied().fold(f64::INFINITY, f64::min);
    format!("{min:.5} / {:.5}", median(v))
}

/// Runs `models`, returns the markdown report (also one JSON line per row on stderr).
///
/// # Errors
/// Unreadable scene or images, a model that does not load or has the wrong signature, an
/// inference failure, or mismatched `--sam-encoder` / `--sam-decoder` counts.
pub fn run(a: &ModelsArgs) -> anyhow::Result<String> {
    ensure!(
        a.repeats > 0 && a.images > 0 && a.batch > 0,
        "--repeats, --images and --batch must be at least 1"
    );
    ensure!(
        a.sam_encoder.len() == a.sam_decoder.len(),
        "pass one --sam-decoder per --sam-encoder (got {} and {})",
        a.sam_encoder.len(),
        a.sam_decoder.len()
    );
    let views = load_views(&a.scene)?;
    ensure!(!views.is_empty(), "{} has no views", a.scene.display());
    let step = (views.len() / a.images).max(1);
    let images = views
        .iter()
        .step_by(step)
        .take(a.images)
        .map(|v| load_rgb(&v.image_path))
        .collect::<slag_common::Result<Vec<_>>>()?;
    let ep: slag_common::onnx::ExecutionProvider = a.ep.into();
    let mut out = String::new();
    let (w, h) = images[0].dimensions();
    writeln!(
        out,
        "inputs: {} views of {} at {w}x{h}; provider {ep}; median of {} passes after a warm-up\n",
        images.len(),
        a.scene.display(),
        a.repeats
    )?;
    if !a.clip_visual.is_empty() {
        clip_rows(a, &images, &mut out)?;
    }
    if !a.sam_encoder.is_empty() {
        sam_rows(a, &images, &mut out)?;
    }
    Ok(out)
}

/// The CLIP table: ms per crop at the batch size, and each tower's cosine to the first.
fn clip_rows(a: &ModelsArgs, images: &[image::RgbImage], out: &mut String) -> anyhow::Result<()> {
    let mut seg = GraphSegmenter::new(GraphParams::default());
    let mut pixels = Vec::new();
    for img in images {
        let masks = seg.generate(img)?;
        pixels.extend(crop_pixels(img, &masks, CropFill::default())?);
    }
    let per = 3 * 224 * 224;
    let crops = pixels.len() / per;
    ensure!(
        crops > 0,
        "the graph segmenter found no masks in the chosen views"
    );
    writeln!(
        out,
        "CLIP: {crops} crops of graph masks ({:.1} per view), batch {}\n",
        crops as f64 / images.len() as f64,
        a.batch
    )?;
    let mut table = Table::with_header("CLIP image tower | input | ms per crop | ms per batch | cosine to the first: min / median | centred on the first's mean: min / median")
    .right_from(2);
    let mut reference: Option<Vec<Vec<f32>>> = None;
    let mut notes = String::new();
    for path in &a.clip_visual {
        let mut clip =
            ClipVisual::with_placement(path, &Placement::new(a.ep.into(), 0, 0), a.batch)?;
        clip.set_fixed_batch(true);
        let mut emb = clip.embed_pixels(&pixels)?; // warm-up, and the embeddings compared
        let mut passes = Vec::new();
        for _ in 0..a.repeats {
            let t = Instant::now();
            emb = clip.embed_pixels(&pixels)?;
            passes.push(t.elapsed().as_secs_f64());
        }
        let per_crop_ms = median(passes) * 1e3 / crops as f64;
        let batches = crops.div_ceil(a.batch);
        let (cos, centred) = match &reference {
            None => {
                // How much the reference's embeddings vary between crops: a random-weight tower
                // can answer nearly the same vector for every crop, and then a plain cosine
                // cannot tell two towers apart. The centred cosine can.
                let mean = mean_row(&emb);
                let spread = emb
                    .iter()
                    .map(|e| cosine(e, &emb[0]))
                    .fold(f64::INFINITY, f64::min);
                notes = format!(
                    "The first tower's embeddings: min cosine between two crops {spread:.4}, \
                     norm of their mean {:.4} (rows are L2-normalised).\n",
                    mean.iter().map(|v| v * v).sum::<f64>().sqrt()
                );
                ("reference".to_string(), "reference".to_string())
            }
            Some(r) => {
                let c: Vec<f64> = r.iter().zip(&emb).map(|(x, y)| cosine(x, y)).collect();
                let mean = mean_row(r);
                let cc: Vec<f64> = r
                    .iter()
                    .zip(&emb)
                    .map(|(x, y)| centred_cosine(x, y, mean.iter().copied()))
                    .collect();
                (min_median(c), min_median(cc))
            }
        };
        table.row([
            path.display().to_string(),
            match clip.input() {
                VisualInput::U8Pixels => "u8 pixels",
                VisualInput::F32PixelValues => "f32, normalised on the host",
            }
            .to_string(),
            format!("{per_crop_ms:.4}"),
            format!("{:.2}", per_crop_ms * crops as f64 / batches as f64),
            cos.clone(),
            centred.clone(),
        ]);
        eprintln!(
            "{}",
            serde_json::json!({"model": path, "kind": "clip_visual", "crops": crops,
                "batch": a.batch, "input": clip.input(), "ms_per_crop": per_crop_ms, "cosine_to_first": cos,
                "centred_cosine_to_first": centred})
        );
        if reference.is_none() {
            reference = Some(emb);
        }
    }
    out.push_str(&table.markdown());
    writeln!(out, "\n{notes}")?;
    Ok(())
}

/// One decoder pass's outputs for the comparison: predicted IoUs and low-res mask signs.
struct Decoded {
    ious: Vec<f32>,
    /// Signs of the multimask channels 1..=3 (what automatic mask generation reads), 3 maps of
    /// 256 × 256 per prompt, whether the decoder returns 4 channels in f32 or 3 in f16.
    positive: Vec<bool>,
    /// Seconds inside the decoder's session runs (outputs on the host included).
    run_s: f64,
}

/// The SAM table: encoder ms per image, decoder ms per image for the whole grid, and each
/// decoder's agreement with the first.
fn sam_rows(a: &ModelsArgs, images: &[image::RgbImage], out: &mut String) -> anyhow::Result<()> {
    let n = (a.points_per_side * a.points_per_side) as usize;
    writeln!(
        out,
        "SAM: {n} prompts per image ({}×{} grid) in runs of {}\n",
        a.points_per_side, a.points_per_side, a.prompt_batch
    )?;
    let mut table = Table::with_header("SAM encoder / decoder | encoder ms per image | decoder ms per image (session runs) | max abs Δ predicted IoU | low-res mask IoU: min / mean")
    .right_from(1);
    let inputs: Vec<Vec<f32>> = images
        .iter()
        .map(|img| sam_pixel_values(img).map(|(p, _)| p))
        .collect::<slag_common::Result<_>>()?;
    let (w, h) = images[0].dimensions();
    let grid = slag_encoder::masks::sam::build_point_grid(a.points_per_side);
    let (nh, nw) = slag_encoder::preprocess::sam_preprocess_shape(h, w, 1024);
    let coords: Vec<f32> = grid
        .iter()
        .flat_map(|p| {
            [
                (p[0] * f64::from(w) * f64::from(nw) / f64::from(w)) as f32,
                (p[1] * f64::from(h) * f64::from(nh) / f64::from(h)) as f32,
                0.0,
                0.0,
            ]
        })
        .collect();
    let placement = Placement::new(a.ep.into(), 0, 0);
    let mut reference: Option<Vec<Decoded>> = None;
    let mut reference_embeddings: Option<Vec<Vec<f32>>> = None;
    for (enc_path, dec_path) in a.sam_encoder.iter().zip(&a.sam_decoder) {
        let mut enc = OnnxModel::load(enc_path, &placement)?;
        let mut dec = OnnxModel::load(dec_path, &placement)?;
        let mut embeddings = Vec::new();
        let mut enc_passes = Vec::new();
        for pass in 0..=a.repeats {
            let t = Instant::now();
            embeddings = inputs
                .iter()
                .map(|p| encode(enc.session_mut(), p))
                .collect::<anyhow::Result<Vec<_>>>()?;
            if pass > 0 {
                enc_passes.push(t.elapsed().as_secs_f64() / images.len() as f64);
            }
        }
        // Decoders are compared on the same embeddings: the first encoder's.
        let emb = reference_embeddings.get_or_insert(embeddings);
        let mut dec_passes = Vec::new();
        let mut decoded = Vec::new();
        for pass in 0..=a.repeats {
            decoded = emb
                .iter()
                .map(|e| decode(dec.session_mut(), e, &coords, a.prompt_batch, (h, w)))
                .collect::<anyhow::Result<Vec<_>>>()?;
            if pass > 0 {
                dec_passes.push(decoded.iter().map(|d| d.run_s).sum::<f64>() / images.len() as f64);
            }
        }
        let (d_iou, mask_iou) = match &reference {
            None => ("reference".to_string(), "reference".to_string()),
            Some(r) => compare(r, &decoded),
        };
        let (enc_ms, dec_ms) = (median(enc_passes) * 1e3, median(dec_passes) * 1e3);
        table.row([
            format!("{} / {}", enc_path.display(), dec_path.display()),
            format!("{enc_ms:.1}"),
            format!("{dec_ms:.1}"),
            d_iou.clone(),
            mask_iou.clone(),
        ]);
        eprintln!(
            "{}",
            serde_json::json!({"encoder": enc_path, "decoder": dec_path, "kind": "sam",
                "prompts": n, "prompt_batch": a.prompt_batch, "encoder_ms": enc_ms,
                "decoder_ms": dec_ms, "d_iou": d_iou, "mask_iou": mask_iou})
        );
        if reference.is_none() {
            reference = Some(decoded);
        }
    }
    out.push_str(&table.markdown());
    Ok(())
}

/// Largest absolute predicted-IoU difference, and min / mean IoU of the positive low-res mask
/// sets per prompt and channel (pairs where both are empty count as 1).
fn compare(r: &[Decoded], d: &[Decoded]) -> (String, String) {
    let mut max_d = 0f64;
    let (mut min_iou, mut sum_iou, mut count) = (1f64, 0f64, 0usize);
    for (x, y) in r.iter().zip(d) {
        for (p, q) in x.ious.iter().zip(&y.ious) {
            max_d = max_d.max(f64::from((p - q).abs()));
        }
        for (mx, my) in x
            .positive
            .chunks(256 * 256)
            .zip(y.positive.chunks(256 * 256))
        {
            let inter = mx.iter().zip(my).filter(|(p, q)| **p && **q).count();
            let union = mx.iter().zip(my).filter(|(p, q)| **p || **q).count();
            let iou = if union == 0 {
                1.0
            } else {
                inter as f64 / union as f64
            };
            min_iou = min_iou.min(iou);
            sum_iou += iou;
            count += 1;
        }
    }
    (
        format!("{max_d:.2e}"),
        format!("{min_iou:.4} / {:.4}", sum_iou / count.max(1) as f64),
    )
}

fn encode(session: &mut Session, pixels: &[f32]) -> anyhow::Result<Vec<f32>> {
    let input = TensorRef::from_array_view(([1usize, 3, 1024, 1024], pixels))?;
    let outputs = session.run(ort::inputs!["pixel_values" => input])?;
    let (shape, data) = outputs["image_embeddings"].try_extract_tensor::<f32>()?;
    ensure!(
        **shape == [1, 256, 64, 64],
        "image_embeddings of shape {shape:?}"
    );
    Ok(data.to_vec())
}

/// Decodes the grid in runs of `batch` prompts; `run_s` counts the session runs only.
fn decode(
    session: &mut Session,
    embedding: &[f32],
    coords: &[f32],
    batch: usize,
    (h, w): (u32, u32),
) -> anyhow::Result<Decoded> {
    let mask_input = vec![0f32; 256 * 256];
    let has_mask = [0f32];
    let orig = [h as f32, w as f32];
    let mut ious = Vec::new();
    let mut positive = Vec::new();
    let mut run_s = 0.0;
    for chunk in coords.chunks(batch * 4) {
        let n = chunk.len() / 4;
        let labels: Vec<f32> = (0..n).flat_map(|_| [1.0f32, -1.0]).collect();
        let inputs = ort::inputs![
            "image_embeddings" => TensorRef::from_array_view(([1usize, 256, 64, 64], embedding))?,
            "point_coords" => TensorRef::from_array_view(([n, 2, 2], chunk))?,
            "point_labels" => TensorRef::from_array_view(([n, 2], labels.as_slice()))?,
            "mask_input" => TensorRef::from_array_view(([1usize, 1, 256, 256], mask_input.as_slice()))?,
            "has_mask_input" => TensorRef::from_array_view(([1usize], &has_mask[..]))?,
            "orig_im_size" => TensorRef::from_array_view(([2usize], &orig[..]))?,
        ];
        let options = ort::session::RunOptions::new()?.with_outputs(
            ort::session::OutputSelector::no_default()
                .with("iou_predictions")
                .with("low_res_masks"),
        );
        let t = Instant::now();
        let outputs = session
            .run_with_options(inputs, &options)
            .context("decoder run")?;
        run_s += t.elapsed().as_secs_f64();
        let (_, iou) = outputs["iou_predictions"].try_extract_tensor::<f32>()?;
        ious.extend_from_slice(iou);
        let low = &outputs["low_res_masks"];
        const LP: usize = 256 * 256;
        if let Ok((shape, low)) = low.try_extract_tensor::<f32>() {
            ensure!(
                **shape == [n as i64, 4, 256, 256],
                "low_res_masks of shape {shape:?}"
            );
            // Channel 0 (the single-mask output) is left out, as automatic generation does.
            for prompt in low.chunks(4 * LP) {
                positive.extend(prompt[LP..].iter().map(|&v| v > 0.0));
            }
        } else {
            let (shape, low) = low
                .try_extract_tensor::<half::f16>()
                .context("low_res_masks are neither f32 nor f16")?;
            ensure!(
                **shape == [n as i64, 3, 256, 256],
                "low_res_masks of shape {shape:?}"
            );
            positive.extend(low.iter().map(|&v| v.to_f32() > 0.0));
        }
    }
    Ok(Decoded {
        ious,
        positive,
        run_s,
    })
}
