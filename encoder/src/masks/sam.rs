//! SAM automatic mask generation over an ONNX encoder/decoder pair.
//!
//! A port of segment_anything 1.0's `SamAutomaticMaskGenerator` with `crop_n_layers = 0` and
//! `min_mask_region_area = 0` (one crop = the whole image, no hole/island removal):
//!
//! 1. the encoder runs once per image on SAM's input (`ResizeLongestSide(1024)`, PIL bilinear,
//!    `(x - pixel_mean) / pixel_std`, zero padding to 1024x1024; see
//!    [`crate::preprocess::sam_pixel_values`]);
//! 2. a `points_per_side`² grid (`build_point_grid`: cell centres, offset `1 / (2 n)`) is scaled to
//!    the image (`x * W`, `y * H`) and mapped to the 1024 frame (`apply_coords`);
//! 3. the decoder (segment_anything's `SamOnnxModel` signature, `return_single_mask=False`) runs in
//!    batches of `points_per_batch` prompts, each `[point, label 1] + padding point (0, 0) label -1`,
//!    `mask_input` zeros, `has_mask_input = 0`, `orig_im_size = [H, W]`; multimask channels 1..=3
//!    are used;
//! 4. filters, in SAM's order: predicted IoU `> pred_iou_thresh`; stability score (IoU of the
//!    full-resolution logits thresholded at `mask_threshold ± stability_score_offset`)
//!    `>= stability_score_thresh`; masks = logits `> mask_threshold`; boxes (xyxy, inclusive max).
//!    The full-resolution logits are not taken from the graph's `masks` output (`P × 4 × H × W`
//!    f32, 750 MB for 256 prompts at 990×742): the decoder is asked for `iou_predictions` and
//!    `low_res_masks` only (ONNX Runtime still computes `masks` unless the decoder is cut down
//!    by `scripts/sam-decoder-low-res.py`, which slag accepts; with `--f16-multimask` it returns
//!    only channels 1..=3 of `low_res_masks`, as f16, 37.5 % of the bytes to copy from the GPU,
//!    see [`LowResLogits`]), and the logits of the candidates
//!    that pass the predicted-IoU filter are upsampled on the host ([`LowResUpsampler`]) exactly
//!    as `SamOnnxModel.mask_postprocessing` does (bilinear 256 → 1024, crop to the resized
//!    image, bilinear to `H × W`, both with `align_corners=False`), composed into one separable
//!    4-tap filter per axis, and only in the 16 × 16 blocks near a threshold: the others are
//!    decided from their taps, with the same result bit for bit ([`MaskPostprocess::LowRes`],
//!    the default; [`MaskPostprocess::Graph`] keeps the old path);
//! 5. greedy box NMS (torchvision `nms`, IoU `> box_nms_thresh` suppresses, boxes areas
//!    `(x1 - x0) * (y1 - y0)`, f32), scores = predicted IoU; the output keeps NMS order (descending
//!    predicted IoU), as `SamAutomaticMaskGenerator.generate` does.

use std::ops::Range;
use std::path::Path;
use std::sync::{Arc, Mutex};

use image::RgbImage;
use ort::session::{OutputSelector, RunOptions};
use ort::value::{DynValue, TensorRef};
use rayon::prelude::*;
use slag_common::onnx::{self, ElemType, ExecutionProvider, OnnxModel, Placement, TensorSpec};
use slag_common::{Error, Result};

use super::{Mask, MaskGenerator};
use crate::check::require;
use crate::preprocess::{SAM_IMAGE_SIZE, sam_pixel_values, sam_preprocess_shape};

/// `SamAutomaticMaskGenerator` parameters (segment_anything 1.0 names and semantics).
///
/// The defaults are those of slag's reference run (`shared/fixtures/sam-amg/reference.json`), not
/// segment_anything's ViT-H defaults (32 points per side, 0.88 / 0.95 thresholds).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SamParams {
    /// Grid points along each image side (`points_per_side`² prompts per image).
    pub points_per_side: u32,
    /// Prompts per decoder call. Results do not depend on it; memory and speed do (one call
    /// holds `points_per_batch * 4` low-resolution, or full-resolution, f32 logit maps). `None`:
    /// [`GPU_POINTS_PER_BATCH`] when the decoder runs on a GPU, [`CPU_POINTS_PER_BATCH`] on the
    /// CPU. See [`SamParams::batch_for`].
    #[serde(default)]
    pub points_per_batch: Option<usize>,
    /// Keep masks whose predicted IoU is `>` this.
    pub pred_iou_thresh: f32,
    /// Keep masks whose stability score is `>=` this.
    pub stability_score_thresh: f32,
    /// Logit offset for the stability score.
    pub stability_score_offset: f32,
    /// Box IoU above which NMS drops the lower-scored mask.
    pub box_nms_thresh: f32,
    /// Logit threshold that binarises masks (`Sam.mask_threshold`).
    pub mask_threshold: f32,
    /// Where the full-resolution logits come from.
    #[serde(default)]
    pub postprocess: MaskPostprocess,
    /// Host memory one decoder call may take, bytes: the prompts per call are then at most
    /// `decoder_batch_bytes / `[`decoder_bytes_per_prompt`] (at least 1), fewer than
    /// `points_per_batch` on large images. Results do not depend on it. `None`: no cap (GPU
    /// sessions, whose tensors are on the device). The encoder sets it for CPU front workers,
    /// which each hold their own sessions: one budget shared by all of them.
    #[serde(default)]
    pub decoder_batch_bytes: Option<usize>,
}

/// Host bytes one prompt costs in a CPU decoder call on an image of `h × w` pixels: its 4
/// multimask channels as f32 at the image size and at SAM's 1024 × 1024 upsampling step, each
/// held twice (the resize's input and output, kept in ONNX Runtime's arena). Measured with
/// color-sam at 990 × 742: 61 MB per prompt; this gives 57 MB.
pub fn decoder_bytes_per_prompt(h: u32, w: u32) -> usize {
    let full = h as usize * w as usize;
    let up = SAM_IMAGE_SIZE as usize * SAM_IMAGE_SIZE as usize;
    2 * 4 * std::mem::size_of::<f32>() * (full + up)
}

impl SamParams {
    /// Prompts per decoder call on an image of `h × w` pixels with the decoder on a GPU
    /// (`on_gpu`) or not: `points_per_batch`, or when it is `None` [`GPU_POINTS_PER_BATCH`] on
    /// a GPU (at most the grid) and [`CPU_POINTS_PER_BATCH`] on the CPU; capped by
    /// [`SamParams::decoder_batch_bytes`] (at least 1).
    pub fn batch_for(&self, h: u32, w: u32, on_gpu: bool) -> usize {
        let cap = self
            .decoder_batch_bytes
            .map_or(usize::MAX, |b| b / decoder_bytes_per_prompt(h, w));
        let grid = (self.points_per_side as usize).pow(2);
        let wanted = match self.points_per_batch {
            Some(n) => n,
            None if on_gpu => grid.min(GPU_POINTS_PER_BATCH),
            None => CPU_POINTS_PER_BATCH,
        };
        wanted.min(cap).max(1)
    }
}

/// Prompts per decoder call on the CPU when none is asked for (segment_anything's default).
pub const CPU_POINTS_PER_BATCH: usize = 64;

/// Prompts per decoder call on a GPU when none is asked for. Fewer, larger calls keep the GPU
/// busier, and a decoder that does the image's work once per call (scripts/export-models.py)
/// does it for more prompts at a time; larger calls also hold larger outputs on the host. On an
/// H100 (2M Gaussians, 250 views, ViT-H fp16 timing model, 4 fronts, one run each) 128 gave an
/// encode of 45.9 s at 6.82 GiB peak RSS, 256 gave 46.1 s at 8.47 GiB.
pub const GPU_POINTS_PER_BATCH: usize = 128;

/// Where AMG's full-resolution mask logits come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MaskPostprocess {
    /// `low_res_masks` (P × 4 × 256 × 256) from the decoder, upsampled on the host for the
    /// candidates that pass the predicted-IoU filter only (the graph's full-resolution `masks`
    /// output is not requested, so it is neither copied back nor, on the GPU, kept).
    #[default]
    LowRes,
    /// The graph's own `masks` output (P × 4 × H × W), as segment_anything reads it.
    Graph,
}

impl Default for SamParams {
    fn default() -> Self {
        SamParams {
            points_per_side: 16,
            points_per_batch: None,
            pred_iou_thresh: 0.8,
            stability_score_thresh: 0.5,
            stability_score_offset: 1.0,
            box_nms_thresh: 0.7,
            mask_threshold: 0.0,
            postprocess: MaskPostprocess::LowRes,
            decoder_batch_bytes: None,
        }
    }
}

impl SamParams {
    /// Checks ranges.
    ///
    /// # Errors
    /// [`Error::Param`] (named by the field) for zero counts or non-finite / out-of-range
    /// thresholds.
    pub fn validate(&self) -> Result<()> {
        let side = self.points_per_side;
        require(
            (1..=1024).contains(&side),
            "points_per_side",
            side,
            "SAM points per side in 1..=1024",
        )?;
        let batch = self.points_per_batch.unwrap_or(1);
        require(
            batch > 0,
            "points_per_batch",
            batch,
            "at least 1 SAM point prompt per batch",
        )?;
        for (name, v) in [
            ("pred_iou_thresh", self.pred_iou_thresh),
            ("stability_score_thresh", self.stability_score_thresh),
            ("box_nms_thresh", self.box_nms_thresh),
        ] {
            let in_unit_interval = (0.0..=1.0).contains(&v);
            require(in_unit_interval, name, v, "a SAM threshold in [0, 1]")?;
        }
        for (name, v) in [
            ("stability_score_offset", self.stability_score_offset),
            ("mask_threshold", self.mask_threshold),
        ] {
            require(v.is_finite(), name, v, "a finite SAM logit offset")?;
        }
        Ok(())
    }
}

/// segment_anything's `build_point_grid(n)`: `n`² points in `[0, 1]²`, row-major (x fastest),
/// at `linspace(1/(2n), 1 - 1/(2n), n)`, as `(x, y)`.
pub fn build_point_grid(n: u32) -> Vec<[f64; 2]> {
    let n = n as usize;
    let offset = 1.0 / (2.0 * n as f64);
    // numpy.linspace: start + i * step, the last value set to stop exactly.
    let side: Vec<f64> = if n == 1 {
        vec![offset]
    } else {
        let step = (1.0 - 2.0 * offset) / (n - 1) as f64;
        (0..n)
            .map(|i| {
                if i == n - 1 {
                    1.0 - offset
                } else {
                    offset + i as f64 * step
                }
            })
            .collect()
    };
    let mut pts = Vec::with_capacity(n * n);
    for &y in &side {
        for &x in &side {
            pts.push([x, y]);
        }
    }
    pts
}

const ENCODER_INPUTS: &[TensorSpec] = &[TensorSpec::named(
    "pixel_values",
    ElemType::F32,
    &[1, 3, 1024, 1024],
)];
const ENCODER_OUTPUTS: &[TensorSpec] = &[TensorSpec::named(
    "image_embeddings",
    ElemType::F32,
    &[1, 256, 64, 64],
)];
const DECODER_INPUTS: &[TensorSpec] = &[
    TensorSpec::named("image_embeddings", ElemType::F32, &[1, 256, 64, 64]),
    TensorSpec::named("point_coords", ElemType::F32, &[-1, -1, 2]),
    TensorSpec::named("point_labels", ElemType::F32, &[-1, -1]),
    TensorSpec::named("mask_input", ElemType::F32, &[1, 1, 256, 256]),
    TensorSpec::named("has_mask_input", ElemType::F32, &[1]),
    TensorSpec::named("orig_im_size", ElemType::F32, &[2]),
];
const DECODER_OUTPUTS: &[TensorSpec] = &[
    TensorSpec::named("masks", ElemType::F32, &[-1, 4, -1, -1]),
    TensorSpec::named("iou_predictions", ElemType::F32, &[-1, 4]),
    TensorSpec::named("low_res_masks", ElemType::F32, &[-1, 4, 256, 256]),
];
/// The outputs of a decoder cut down to what [`MaskPostprocess::LowRes`] reads
/// (`scripts/sam-decoder-low-res.py`): without the full-resolution `masks`, which ONNX Runtime
/// would otherwise compute on every call.
const DECODER_OUTPUTS_LOW_RES: &[TensorSpec] = &[
    TensorSpec::named("iou_predictions", ElemType::F32, &[-1, 4]),
    TensorSpec::named("low_res_masks", ElemType::F32, &[-1, 4, 256, 256]),
];
/// The outputs of a low-resolution decoder cut with `--f16-multimask`: the multimask channels
/// 1..=3 only, in half precision.
const DECODER_OUTPUTS_LOW_RES_F16: &[TensorSpec] = &[
    TensorSpec::named("iou_predictions", ElemType::F32, &[-1, 4]),
    TensorSpec::named("low_res_masks", ElemType::F16, &[-1, 3, 256, 256]),
];

/// How a decoder lays out its `low_res_masks` (the 256 × 256 mask logits per prompt), read
/// from its signature when it is loaded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LowResLogits {
    /// `f32[P, 4, 256, 256]`: SamOnnxModel's own output (channel 0 is the single-mask output,
    /// which automatic mask generation does not use).
    F32AllChannels,
    /// `f16[P, 3, 256, 256]`: the multimask channels 1..=3 only, in half precision, from
    /// `scripts/sam-decoder-low-res.py --f16-multimask` on a decoder that computes its logits
    /// in f16 (`export-models.py sam --fp16-decoder`), so the values are the same and a
    /// quarter of the channels and half of each value's bytes never leave the GPU.
    F16Multimask,
}

impl LowResLogits {
    /// Channels per prompt in the output.
    fn channels(self) -> usize {
        match self {
            LowResLogits::F32AllChannels => 4,
            LowResLogits::F16Multimask => 3,
        }
    }
    /// Index of multimask channel `c` (1..=3) of prompt `i` in the output's map order.
    fn map_index(self, i: usize, c: usize) -> usize {
        match self {
            LowResLogits::F32AllChannels => i * 4 + c,
            LowResLogits::F16Multimask => i * 3 + c - 1,
        }
    }
}

/// A candidate mask that passed the score filters, kept bit-packed until NMS.
struct Candidate {
    bits: Vec<u64>,
    /// xyxy, inclusive max.
    bbox: [u32; 4],
    area: u32,
    iou: f32,
    stability: f32,
    point: [f64; 2],
    /// Multimask output channel (1..=3) that produced the candidate.
    channel: u8,
}

/// The SAM encoder and decoder sessions of one GPU (or of the CPU), shared by every
/// [`SamAutomaticMaskGenerator`] made with [`SamAutomaticMaskGenerator::share`]: one session per
/// model per GPU, whatever the number of front workers. Each session's runs are serialised by its
/// lock, held for the run alone (a decoder call's candidates are filtered after the lock is
/// released); the encoder of one image and the decoder of another run at the same time.
pub struct SamModels {
    encoder: Mutex<OnnxModel>,
    decoder: Mutex<OnnxModel>,
    /// Providers that actually run the encoder and decoder, and where (`cuda:0`).
    providers: (ExecutionProvider, ExecutionProvider),
    device: String,
    /// The decoder's `low_res_masks` layout.
    low_res_logits: LowResLogits,
}

impl SamModels {
    /// Providers that run the encoder and the decoder (never `Auto`).
    pub fn providers(&self) -> (ExecutionProvider, ExecutionProvider) {
        self.providers
    }
    /// Where they run: `cpu`, `cuda:0`, ...
    pub fn device(&self) -> &str {
        &self.device
    }
    /// The decoder's `low_res_masks` layout.
    pub fn low_res_logits(&self) -> LowResLogits {
        self.low_res_logits
    }
}

/// The image embedding between the encoder and the decoder: on the host (CPU provider), or left
/// on the GPU where the encoder wrote it (IO binding), so the decoder reads it without a copy.
enum ImageEmbedding {
    Host(Vec<f32>),
    Device(DynValue),
}

fn lock(m: &Mutex<OnnxModel>) -> std::sync::MutexGuard<'_, OnnxModel> {
    // A panic while holding the lock leaves the session itself intact.
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// SAM automatic mask generator over ONNX models (segment_anything 1.0 semantics, see the module
/// docs). Implements [`MaskGenerator`] with name `"sam"`. Cheap to [`share`](Self::share): every
/// front worker of a GPU holds one over the same [`SamModels`].
pub struct SamAutomaticMaskGenerator {
    models: Arc<SamModels>,
    params: SamParams,
}

impl SamAutomaticMaskGenerator {
    /// Loads and checks the encoder (`pixel_values f32[1,3,1024,1024] → image_embeddings
    /// f32[1,256,64,64]`) and the decoder (segment_anything `SamOnnxModel`,
    /// `return_single_mask=False`: `masks f32[P,4,H,W]`, `iou_predictions f32[P,4]`,
    /// `low_res_masks f32[P,4,256,256]`) on `ep`, GPU 0.
    ///
    /// `intra_threads` is ONNX Runtime's intra-op thread count (0 = its default).
    ///
    /// # Errors
    /// [`Error::Model`] for a missing/unloadable model or the wrong signature (e.g. a CLIP model
    /// passed as the encoder), [`Error::Inference`] when the provider fails,
    /// [`Error::Param`] for bad `params`.
    pub fn new(
        encoder: &Path,
        decoder: &Path,
        ep: ExecutionProvider,
        intra_threads: usize,
        params: SamParams,
    ) -> Result<Self> {
        Self::with_placement(
            encoder,
            decoder,
            &Placement::new(ep, 0, intra_threads),
            params,
        )
    }

    /// [`SamAutomaticMaskGenerator::new`] where `placement` says (provider, GPU, threads, arena
    /// cap).
    ///
    /// # Errors
    /// As [`SamAutomaticMaskGenerator::new`].
    pub fn with_placement(
        encoder: &Path,
        decoder: &Path,
        placement: &Placement,
        params: SamParams,
    ) -> Result<Self> {
        params.validate()?;
        // The decoder's session is built on a thread of its own while the encoder's is: on a
        // GPU even a tiny session takes most of a second (color-sam's two: 0.8–1.0 s on an
        // H200), so the decoder need not wait for SAM ViT-H's 1.3 GB encoder. The encoder's
        // error comes first.
        let (dec, enc) = onnx::side_by_side(
            "the SAM decoder's session setup",
            || OnnxModel::load(decoder, placement),
            || OnnxModel::load(encoder, placement),
        );
        let enc = enc?;
        onnx::check_signature(
            enc.session(),
            encoder,
            "SAM image encoder",
            ENCODER_INPUTS,
            ENCODER_OUTPUTS,
            "pass a SAM image encoder exported with input pixel_values f32[1,3,1024,1024] \
             (normalised, padded) and output image_embeddings f32[1,256,64,64] \
             (scripts/export-models.py sam)",
        )?;
        let dec = dec?;
        let low_res_logits = decoder_low_res(&dec, decoder, params.postprocess)?;
        let providers = (enc.provider(), dec.provider());
        let device = enc.device_label();
        Ok(SamAutomaticMaskGenerator {
            models: Arc::new(SamModels {
                encoder: Mutex::new(enc),
                decoder: Mutex::new(dec),
                providers,
                device,
                low_res_logits,
            }),
            params,
        })
    }

    /// Another generator over the same sessions (same GPU), for another front worker.
    pub fn share(&self) -> Self {
        SamAutomaticMaskGenerator {
            models: Arc::clone(&self.models),
            params: self.params.clone(),
        }
    }

    /// The sessions and where they run.
    pub fn models(&self) -> &SamModels {
        &self.models
    }

    /// The parameters in use.
    pub fn params(&self) -> &SamParams {
        &self.params
    }

    /// Runs the encoder on SAM's input of `image`: `f32[1,256,64,64]` image embeddings, left on
    /// the GPU when the encoder runs there.
    fn encode(&self, image: &RgbImage) -> Result<ImageEmbedding> {
        let (pixels, _) = sam_pixel_values(image)?;
        let s = SAM_IMAGE_SIZE as usize;
        let mut enc = lock(&self.models.encoder);
        let input = TensorRef::from_array_view(([1usize, 3, s, s], pixels.as_slice()))
            .map_err(|e| enc.error("cannot build the encoder input", &e))?;
        if let Some(mem) = enc.device_memory()? {
            let mut binding = enc
                .session()
                .create_binding()
                .map_err(|e| enc.error("cannot create the encoder's IO binding", &e))?;
            binding
                .bind_input("pixel_values", &input)
                .map_err(|e| enc.error("cannot bind the encoder input", &e))?;
            binding
                .bind_output_to_device("image_embeddings", &mem)
                .map_err(|e| enc.error("cannot bind the encoder output to the GPU", &e))?;
            let errs = enc.errors();
            let value = enc
                .session_mut()
                .run_binding(&binding)
                .map_err(|e| errs.error("encoder run", &e))?
                .remove("image_embeddings")
                .ok_or_else(|| errs.unexpected("the encoder returned no image_embeddings"))?;
            return Ok(ImageEmbedding::Device(value));
        }
        let errs = enc.errors();
        let outputs = enc
            .session_mut()
            .run(ort::inputs!["pixel_values" => input])
            .map_err(|e| errs.error("encoder run", &e))?;
        let (shape, data) = outputs["image_embeddings"]
            .try_extract_tensor::<f32>()
            .map_err(|e| errs.unexpected(format!("encoder output is not f32: {e}")))?;
        if **shape != [1, 256, 64, 64] {
            return Err(errs.unexpected(format!(
                "encoder returned image_embeddings of shape {shape:?}, expected [1,256,64,64]"
            )));
        }
        Ok(ImageEmbedding::Host(data.to_vec()))
    }

    /// Decodes one batch of prompts (points in the 1024 frame) and returns the candidates that pass
    /// the predicted-IoU and stability filters, in SAM order (prompt-major, then channel 1..=3).
    fn decode_batch(
        &self,
        embedding: &ImageEmbedding,
        points: &[[f64; 2]],
        transformed: &[[f32; 2]],
        (h, w): (u32, u32),
        upsampler: &LowResUpsampler,
    ) -> Result<(Vec<Candidate>, f64)> {
        let n = points.len();
        let low_res = self.params.postprocess == MaskPostprocess::LowRes;
        let (errs, [iou_value, masks_value], run_s) =
            self.run_decoder(embedding, transformed, (h, w), low_res)?;
        tracing::trace!(prompts = n, run_s, "SAM decoder batch");
        let (ishape, ious) = iou_value
            .try_extract_tensor::<f32>()
            .map_err(|e| errs.unexpected(format!("decoder iou_predictions are not f32: {e}")))?;
        if **ishape != [n as i64, 4] {
            return Err(errs.unexpected(format!(
                "decoder returned iou_predictions of shape {ishape:?}, expected [{n}, 4]"
            )));
        }
        let p = &self.params;
        let jobs: Vec<(usize, usize)> = (0..n)
            .flat_map(|i| (1..4).map(move |c| (i, c)))
            .filter(|&(i, c)| ious[i * 4 + c] > p.pred_iou_thresh)
            .collect();
        let (hu, wu) = (h as usize, w as usize);
        let plane = hu * wu;
        let tf = std::time::Instant::now();
        let cands: Vec<Option<Candidate>> = if low_res {
            let layout = self.models.low_res_logits;
            let lows = LowResMaps::extract(&masks_value, layout, n)
                .map_err(|m| errs.unexpected(format!("decoder low_res_masks: {m}")))?;
            jobs.par_iter()
                .map_init(
                    || (upsampler.scratch(), Vec::new()),
                    |(scratch, widened), &(i, c)| {
                        let low = lows.map(layout.map_index(i, c), widened);
                        upsampler.candidate(low, scratch, p, ious[i * 4 + c], points[i], c)
                    },
                )
                .collect()
        } else {
            let (mshape, masks) = masks_value
                .try_extract_tensor::<f32>()
                .map_err(|e| errs.unexpected(format!("decoder masks are not f32: {e}")))?;
            if **mshape != [n as i64, 4, i64::from(h), i64::from(w)] {
                return Err(errs.unexpected(format!(
                    "decoder returned masks of shape {mshape:?} for {n} prompts and orig_im_size \
                     [{h}, {w}]; expected [{n}, 4, {h}, {w}]: the decoder must upscale its masks \
                     to orig_im_size (SamOnnxModel.mask_postprocessing)"
                )));
            }
            jobs.par_iter()
                .map(|&(i, c)| {
                    let logits = &masks[(i * 4 + c) * plane..(i * 4 + c + 1) * plane];
                    candidate(logits, wu, p, ious[i * 4 + c], points[i], c)
                })
                .collect()
        };
        tracing::trace!(
            jobs = jobs.len(),
            filter_s = tf.elapsed().as_secs_f64(),
            "SAM candidates"
        );
        Ok((cands.into_iter().flatten().collect(), run_s))
    }

    /// Runs the prompt decoder on one batch of prompts (`transformed`: points in the 1024 frame)
    /// for an image of `(h, w)` pixels: the decoder's errors, its `[iou_predictions, masks]`
    /// (`low_res_masks` with `low_res`) and the run's seconds. The outputs own their host
    /// memory: the session is free for another front's call when this returns.
    ///
    /// Errors: [`Error::Inference`] when the run fails, [`Error::Model`] for a missing output.
    fn run_decoder(
        &self,
        embedding: &ImageEmbedding,
        transformed: &[[f32; 2]],
        (h, w): (u32, u32),
        low_res: bool,
    ) -> Result<(onnx::ModelErrors, [DynValue; 2], f64)> {
        let n = transformed.len();
        let mut coords = Vec::with_capacity(n * 4);
        let mut labels = Vec::with_capacity(n * 2);
        for p in transformed {
            coords.extend_from_slice(&[p[0], p[1], 0.0, 0.0]);
            labels.extend_from_slice(&[1.0f32, -1.0]);
        }
        let mask_input = vec![0f32; 256 * 256];
        let has_mask = [0f32];
        let orig = [h as f32, w as f32];
        let mut dec = lock(&self.models.decoder);
        let errs = dec.errors();
        let err = |e: ort::Error| errs.error("cannot build the decoder inputs", &e);
        let emb_input: ort::session::SessionInputValue<'_> = match embedding {
            ImageEmbedding::Host(v) => {
                TensorRef::from_array_view(([1usize, 256, 64, 64], v.as_slice()))
                    .map_err(err)?
                    .into()
            }
            ImageEmbedding::Device(v) => v.into(),
        };
        let inputs = ort::inputs![
            "image_embeddings" => emb_input,
            "point_coords" => TensorRef::from_array_view(([n, 2, 2], coords.as_slice())).map_err(err)?,
            "point_labels" => TensorRef::from_array_view(([n, 2], labels.as_slice())).map_err(err)?,
            "mask_input" => TensorRef::from_array_view(([1usize, 1, 256, 256], mask_input.as_slice())).map_err(err)?,
            "has_mask_input" => TensorRef::from_array_view(([1usize], &has_mask[..])).map_err(err)?,
            "orig_im_size" => TensorRef::from_array_view(([2usize], &orig[..])).map_err(err)?,
        ];
        let t = std::time::Instant::now();
        // The low-resolution path asks for two outputs only: ONNX Runtime then neither copies
        // the full-resolution masks back nor keeps them.
        let selector = if low_res {
            OutputSelector::no_default()
                .with("iou_predictions")
                .with("low_res_masks")
        } else {
            OutputSelector::default()
        };
        let options = RunOptions::new()
            .map_err(|e| errs.error("cannot create run options", &e))?
            .with_outputs(selector);
        let mut outputs = dec
            .session_mut()
            .run_with_options(inputs, &options)
            .map_err(|e| errs.error("decoder run", &e))?;
        let run_s = t.elapsed().as_secs_f64();
        let iou_value = outputs.remove("iou_predictions");
        let masks_value = outputs.remove(if low_res { "low_res_masks" } else { "masks" });
        drop(outputs);
        drop(dec);
        let missing = |name: &str| errs.unexpected(format!("the decoder returned no {name}"));
        let iou_value = iou_value.ok_or_else(|| missing("iou_predictions"))?;
        let masks_value = masks_value.ok_or_else(|| missing("masks"))?;
        Ok((errs, [iou_value, masks_value], run_s))
    }

    /// All masks of `image`, in SAM AMG order (NMS order: descending predicted IoU).
    ///
    /// # Errors
    /// [`Error::Invalid`] for an empty image, [`Error::Model`] / [`Error::Inference`] when a
    /// model fails or returns tensors of unexpected shapes.
    pub fn generate_masks(&mut self, image: &RgbImage) -> Result<Vec<Mask>> {
        let (w, h) = image.dimensions();
        if w == 0 || h == 0 {
            return Err(Error::Invalid("SAM cannot segment an empty image".into()));
        }
        let t0 = std::time::Instant::now();
        let embedding = self.encode(image)?;
        let t_encode = t0.elapsed();
        let (new_h, new_w) = sam_preprocess_shape(h, w, SAM_IMAGE_SIZE);
        let (sx, sy) = (
            f64::from(new_w) / f64::from(w),
            f64::from(new_h) / f64::from(h),
        );
        let points: Vec<[f64; 2]> = build_point_grid(self.params.points_per_side)
            .into_iter()
            .map(|[x, y]| [x * f64::from(w), y * f64::from(h)])
            .collect();
        let transformed: Vec<[f32; 2]> = points
            .iter()
            .map(|p| [(p[0] * sx) as f32, (p[1] * sy) as f32])
            .collect();
        let upsampler = LowResUpsampler::new((h, w), (new_h, new_w));
        let mut cands = Vec::new();
        let on_gpu = lock(&self.models.decoder).provider() != ExecutionProvider::Cpu;
        let bs = self.params.batch_for(h, w, on_gpu);
        let t1 = std::time::Instant::now();
        let mut decoder_run_s = 0.0;
        for (pts, tr) in points.chunks(bs).zip(transformed.chunks(bs)) {
            let (batch, run_s) = self.decode_batch(&embedding, pts, tr, (h, w), &upsampler)?;
            cands.extend(batch);
            decoder_run_s += run_s;
        }
        let t_decode = t1.elapsed();
        let t2 = std::time::Instant::now();
        let keep = nms(&cands, self.params.box_nms_thresh);
        let t_nms = t2.elapsed();
        let plane = w as usize * h as usize;
        let out: Vec<Mask> = keep
            .par_iter()
            .map(|&i| {
                let c = &cands[i];
                let mut pixels = vec![0u8; plane];
                for (chunk, &word) in pixels.chunks_mut(64).zip(&c.bits) {
                    if word != 0 {
                        for (k, px) in chunk.iter_mut().enumerate() {
                            *px = ((word >> k) & 1) as u8;
                        }
                    }
                }
                let [x0, y0, x1, y1] = c.bbox;
                Mask {
                    width: w,
                    height: h,
                    pixels,
                    bbox_xywh: [x0, y0, x1 - x0, y1 - y0],
                    area: c.area,
                    predicted_iou: c.iou,
                    stability_score: c.stability,
                    point: Some([c.point[0] as f32, c.point[1] as f32]),
                    level: Some(c.channel - 1),
                }
            })
            .collect();
        tracing::debug!(
            encode_s = t_encode.as_secs_f64(),
            decode_and_filter_s = t_decode.as_secs_f64(),
            decoder_run_s,
            nms_s = t_nms.as_secs_f64(),
            masks_s = (t2.elapsed() - t_nms).as_secs_f64(),
            candidates = cands.len(),
            kept = out.len(),
            "SAM automatic mask generation"
        );
        Ok(out)
    }
}

/// One full-resolution logit map (`H × W`, row-major) → a candidate, or `None` when its stability
/// score fails the filter (segment_anything's `calculate_stability_score`, mask, box).
fn candidate(
    logits: &[f32],
    w: usize,
    p: &SamParams,
    iou: f32,
    point: [f64; 2],
    channel: usize,
) -> Option<Candidate> {
    let (thr, off) = (p.mask_threshold, p.stability_score_offset);
    let (mut inter, mut union) = (0u32, 0u32);
    for &v in logits {
        inter += u32::from(v > thr + off);
        union += u32::from(v > thr - off);
    }
    let stability = stability_score(inter, union, p)?;
    let mut mask = MaskPixels::new(w, logits.len());
    for (y, row) in logits.chunks_exact(w).enumerate() {
        for (x, &v) in row.iter().enumerate() {
            if v > thr {
                mask.run(x, x + 1, y);
            }
        }
    }
    Some(mask.candidate(iou, stability, point, channel))
}

/// segment_anything's `calculate_stability_score` from the pixel counts above the upper
/// (`inter`) and the lower (`union`) threshold, or `None` when it fails
/// [`SamParams::stability_score_thresh`].
fn stability_score(inter: u32, union: u32, p: &SamParams) -> Option<f32> {
    // torch: int32 / int32 -> f32; 0 / 0 = NaN fails the `>=` filter like SAM's.
    let stability = inter as f32 / union as f32;
    (!stability.is_nan() && stability >= p.stability_score_thresh).then_some(stability)
}

/// A candidate's mask as its pixels are found: its bits (row-major, `w` per row), its box and
/// its area.
struct MaskPixels {
    w: usize,
    bits: Vec<u64>,
    /// Smallest and largest column inside.
    x: [u32; 2],
    /// Smallest and largest row inside.
    y: [u32; 2],
    area: u32,
}

impl MaskPixels {
    /// An empty mask of `pixels` pixels, `w` per row.
    fn new(w: usize, pixels: usize) -> Self {
        MaskPixels {
            w,
            bits: vec![0u64; pixels.div_ceil(64)],
            x: [u32::MAX, 0],
            y: [u32::MAX, 0],
            area: 0,
        }
    }

    /// Pixels `xa..xb` (`xa < xb`) of row `y` are inside the mask.
    fn run(&mut self, xa: usize, xb: usize, y: usize) {
        set_bits(&mut self.bits, y * self.w + xa, xb - xa);
        self.x = [self.x[0].min(xa as u32), self.x[1].max((xb - 1) as u32)];
        self.y = [self.y[0].min(y as u32), self.y[1].max(y as u32)];
        self.area += (xb - xa) as u32;
    }

    /// The candidate of this mask with its scores, from multimask output `channel`.
    fn candidate(self, iou: f32, stability: f32, point: [f64; 2], channel: usize) -> Candidate {
        // batched_mask_to_box gives [0,0,0,0] for an empty mask.
        let bbox = if self.area == 0 {
            [0; 4]
        } else {
            [self.x[0], self.y[0], self.x[1], self.y[1]]
        };
        Candidate {
            bits: self.bits,
            bbox,
            area: self.area,
            iou,
            stability,
            point,
            channel: channel as u8,
        }
    }
}

/// Taps of one output coordinate: up to four `(low-res index, weight)` pairs.
type Taps = ([u16; 4], [f32; 4]);

/// One output sample of the row pass: the taps `t` applied to the low-resolution row `src`.
#[inline]
fn row_tap(t: &Taps, src: &[f32]) -> f32 {
    let (idx, wt) = t;
    wt[0] * src[idx[0] as usize]
        + wt[1] * src[idx[1] as usize]
        + wt[2] * src[idx[2] as usize]
        + wt[3] * src[idx[3] as usize]
}

/// `SamOnnxModel.mask_postprocessing` on the host: 256 × 256 low-resolution logits → bilinear
/// (`align_corners=False`) to 1024 × 1024 → crop to the resized image `new_h × new_w` → bilinear
/// to `h × w`. Bilinear resampling is separable and the crop only selects rows and columns, so
/// each axis is one 4-tap filter (two taps of the second resize, each two taps of the first);
/// rows are filtered first (256 × `w`), then columns. The weights are PyTorch's
/// (`area_pixel_compute_source_index`: `src = (dst + 0.5) · in / out − 0.5`, clamped at 0;
/// the upper neighbour clamped to the last index), computed in f32.
pub struct LowResUpsampler {
    x: Vec<Taps>,
    y: Vec<Taps>,
    /// Per block of [`BLOCK`] output columns: the lowest and highest low-resolution column any
    /// of their taps reads.
    x_spans: Vec<(usize, usize)>,
    /// The same per block of [`BLOCK`] output rows.
    y_spans: Vec<(usize, usize)>,
}

/// Side of the square blocks of full-resolution pixels that
/// [`LowResUpsampler::candidate`] decides at once from their low-resolution taps.
const BLOCK: usize = 16;

/// Per block of [`BLOCK`] outputs, the lowest and highest low-resolution index of their taps.
fn tap_spans(taps: &[Taps]) -> Vec<(usize, usize)> {
    taps.chunks(BLOCK)
        .map(|block| {
            let idx = || {
                block
                    .iter()
                    .flat_map(|(i, _)| i.iter().map(|&v| usize::from(v)))
            };
            (idx().min().unwrap_or(0), idx().max().unwrap_or(0))
        })
        .collect()
}

/// The `low_res_masks` of one decoder call, borrowed from the output tensor.
enum LowResMaps<'a> {
    F32(&'a [f32]),
    F16(&'a [half::f16]),
}

impl<'a> LowResMaps<'a> {
    /// The maps of `value` for `n` prompts laid out as `layout`; the message says what differs.
    fn extract(
        value: &'a DynValue,
        layout: LowResLogits,
        n: usize,
    ) -> std::result::Result<Self, String> {
        let want = [n as i64, layout.channels() as i64, 256, 256];
        let (shape, maps) = match layout {
            LowResLogits::F32AllChannels => value
                .try_extract_tensor::<f32>()
                .map(|(s, d)| (s, LowResMaps::F32(d)))
                .map_err(|e| format!("not f32: {e}"))?,
            LowResLogits::F16Multimask => value
                .try_extract_tensor::<half::f16>()
                .map(|(s, d)| (s, LowResMaps::F16(d)))
                .map_err(|e| format!("not f16: {e}"))?,
        };
        if **shape != want {
            return Err(format!("shape {shape:?}, expected {want:?}"));
        }
        Ok(maps)
    }

    /// Map `k` (256 × 256) as f32: borrowed, or widened from f16 into `scratch` (exact).
    fn map<'s>(&'s self, k: usize, scratch: &'s mut Vec<f32>) -> &'s [f32] {
        const LP: usize = 256 * 256;
        match self {
            LowResMaps::F32(d) => &d[k * LP..(k + 1) * LP],
            LowResMaps::F16(d) => {
                scratch.clear();
                scratch.extend(d[k * LP..(k + 1) * LP].iter().map(|v| v.to_f32()));
                scratch
            }
        }
    }
}

/// Pixels of one logit map above the lower (`union`) and the upper (`inter`) threshold of the
/// stability score.
#[derive(Default)]
struct PixelCounts {
    union: u32,
    inter: u32,
}

/// Scratch of [`LowResUpsampler::candidate`], reused across the candidates of one thread.
struct CandidateScratch {
    /// The row pass (256 × `w`), filled lazily per (low-res row, block column).
    rows: Vec<f32>,
    /// Whether `rows` holds (low-res row, block column) for the current map: 256 × blocks.
    done: Vec<bool>,
    /// A full-resolution map (`h × w`), for maps with non-finite logits only.
    full: Vec<f32>,
}

/// PyTorch's linear taps for `out` samples over `in_` samples (`align_corners=False`).
fn linear_taps(in_: usize, out: usize) -> Vec<(usize, usize, f32)> {
    let scale = in_ as f32 / out as f32;
    (0..out)
        .map(|d| {
            let src = ((d as f32 + 0.5) * scale - 0.5).max(0.0);
            let i0 = (src as usize).min(in_ - 1);
            let i1 = (i0 + 1).min(in_ - 1);
            (i0, i1, src - i0 as f32)
        })
        .collect()
}

/// The composed taps of one axis: `256 → 1024`, keep the first `kept`, `kept → out`.
fn composed_taps(kept: usize, out: usize) -> Vec<Taps> {
    let first = linear_taps(256, 1024);
    linear_taps(kept, out)
        .into_iter()
        .map(|(a, b, l)| {
            let mut idx = [0u16; 4];
            let mut wt = [0f32; 4];
            for (k, (mid, lw)) in [(a, 1.0 - l), (b, l)].into_iter().enumerate() {
                let (c0, c1, m) = first[mid];
                idx[2 * k] = c0 as u16;
                idx[2 * k + 1] = c1 as u16;
                wt[2 * k] = lw * (1.0 - m);
                wt[2 * k + 1] = lw * m;
            }
            (idx, wt)
        })
        .collect()
}

impl LowResUpsampler {
    /// The filters for an image of `h × w` pixels whose SAM input was resized to `new_h × new_w`
    /// ([`sam_preprocess_shape`]).
    pub fn new((h, w): (u32, u32), (new_h, new_w): (u32, u32)) -> Self {
        let kept = |n: u32| (n as usize).clamp(1, SAM_IMAGE_SIZE as usize);
        let x = composed_taps(kept(new_w), w as usize);
        let y = composed_taps(kept(new_h), h as usize);
        LowResUpsampler {
            x_spans: tap_spans(&x),
            y_spans: tap_spans(&y),
            x,
            y,
        }
    }

    /// Empty scratch for [`LowResUpsampler::candidate`] (allocated on first use).
    fn scratch(&self) -> CandidateScratch {
        CandidateScratch {
            rows: Vec::new(),
            done: Vec::new(),
            full: Vec::new(),
        }
    }

    /// One low-resolution logit map (256 × 256) → its candidate, exactly as
    /// [`LowResUpsampler::upsample`] followed by the full-resolution filter would give it (same
    /// stability score, box, area and pixels, bit for bit), without upsampling most pixels.
    ///
    /// Each output pixel is a convex combination of at most 16 low-resolution logits. The image
    /// is cut into [`BLOCK`] × [`BLOCK`] blocks; a block whose taps' minimum lies above a
    /// threshold (or whose maximum lies below it) by more than a margin of 1e-4 relative to
    /// the logits' magnitude, far beyond f32 rounding of the 4 + 4 tap sums, is on one side of
    /// it at every pixel. Blocks decided for all three thresholds (`mask_threshold` and ±
    /// `stability_score_offset`) are counted whole; the others (the masks' borders) are
    /// upsampled with the same arithmetic as [`LowResUpsampler::upsample`]. A map with a
    /// non-finite logit is upsampled whole.
    fn candidate(
        &self,
        low: &[f32],
        scratch: &mut CandidateScratch,
        p: &SamParams,
        iou: f32,
        point: [f64; 2],
        channel: usize,
    ) -> Option<Candidate> {
        let (w, h) = (self.x.len(), self.y.len());
        if low.iter().any(|v| !v.is_finite()) {
            scratch.rows.resize(256 * w, 0.0);
            scratch.full.resize(h * w, 0.0);
            self.upsample(low, &mut scratch.rows, &mut scratch.full);
            return candidate(&scratch.full, w, p, iou, point, channel);
        }
        let (thr, off) = (p.mask_threshold, p.stability_score_offset);
        // union, mask, intersection: the comparisons of `candidate`.
        let levels = [thr - off, thr, thr + off];
        scratch.rows.resize(256 * w, 0.0);
        scratch.done.clear();
        scratch.done.resize(256 * self.x_spans.len(), false);
        let mut mask = MaskPixels::new(w, w * h);
        let mut counts = PixelCounts::default();
        for by in 0..self.y_spans.len() {
            let ys = by * BLOCK..((by + 1) * BLOCK).min(h);
            for bx in 0..self.x_spans.len() {
                let xs = bx * BLOCK..((bx + 1) * BLOCK).min(w);
                match self.block_sides(low, by, bx, &levels) {
                    Some(above) => {
                        let n = (ys.len() * xs.len()) as u32;
                        counts.union += if above[0] { n } else { 0 };
                        counts.inter += if above[2] { n } else { 0 };
                        if above[1] {
                            for y in ys.clone() {
                                mask.run(xs.start, xs.end, y);
                            }
                        }
                    }
                    None => {
                        self.row_pass(low, scratch, by, bx, xs.clone());
                        self.threshold_block(
                            &scratch.rows,
                            &levels,
                            (ys.clone(), xs),
                            &mut mask,
                            &mut counts,
                        );
                    }
                }
            }
        }
        let stability = stability_score(counts.inter, counts.union, p)?;
        Some(mask.candidate(iou, stability, point, channel))
    }

    /// Block `(by, bx)`'s side of each of the three `levels` when its taps' bounds decide it
    /// at every pixel (`true`: above), or `None` when any level must be computed pixel by pixel.
    fn block_sides(
        &self,
        low: &[f32],
        by: usize,
        bx: usize,
        levels: &[f32; 3],
    ) -> Option<[bool; 3]> {
        let ((ry0, ry1), (cx0, cx1)) = (self.y_spans[by], self.x_spans[bx]);
        let (mut mn, mut mx) = (f32::INFINITY, f32::NEG_INFINITY);
        for r in ry0..=ry1 {
            // All logits are finite here: plain comparisons are the minimum and maximum.
            for &v in &low[r * 256 + cx0..=r * 256 + cx1] {
                mn = if v < mn { v } else { mn };
                mx = if v > mx { v } else { mx };
            }
        }
        let margin = 1e-4 * (1.0 + mn.abs().max(mx.abs()));
        let above = levels.map(|t| mn - margin > t);
        let below = levels.map(|t| mx + margin < t);
        (0..3).all(|k| above[k] || below[k]).then_some(above)
    }

    /// The row pass of output columns `xs` (block column `bx`) over the low-resolution rows
    /// that block row `by` reads, into `scratch.rows`, for the rows not done yet.
    fn row_pass(
        &self,
        low: &[f32],
        scratch: &mut CandidateScratch,
        by: usize,
        bx: usize,
        xs: Range<usize>,
    ) {
        let (w, nbx) = (self.x.len(), self.x_spans.len());
        let (ry0, ry1) = self.y_spans[by];
        for r in ry0..=ry1 {
            if !std::mem::replace(&mut scratch.done[r * nbx + bx], true) {
                let src = &low[r * 256..(r + 1) * 256];
                let out = &mut scratch.rows[r * w..(r + 1) * w];
                for x in xs.clone() {
                    out[x] = row_tap(&self.x[x], src);
                }
            }
        }
    }

    /// The column pass of the block `(ys, xs)` from the row pass `rows`, each pixel compared
    /// with the three `levels`: counted into `counts`, and set in `mask` when above the middle
    /// one.
    fn threshold_block(
        &self,
        rows: &[f32],
        levels: &[f32; 3],
        (ys, xs): (Range<usize>, Range<usize>),
        mask: &mut MaskPixels,
        counts: &mut PixelCounts,
    ) {
        let w = self.x.len();
        let mut block = [0f32; BLOCK];
        for y in ys {
            let (idx, wt) = &self.y[y];
            let row = |k: usize| &rows[idx[k] as usize * w..][..w];
            let (r0, r1, r2, r3) = (row(0), row(1), row(2), row(3));
            for (o, x) in block.iter_mut().zip(xs.clone()) {
                *o = wt[0] * r0[x] + wt[1] * r1[x] + wt[2] * r2[x] + wt[3] * r3[x];
            }
            let mut run: Option<usize> = None;
            for (i, &v) in block[..xs.len()].iter().enumerate() {
                counts.union += u32::from(v > levels[0]);
                counts.inter += u32::from(v > levels[2]);
                match (v > levels[1], run) {
                    (true, None) => run = Some(xs.start + i),
                    (false, Some(a)) => {
                        mask.run(a, xs.start + i, y);
                        run = None;
                    }
                    _ => {}
                }
            }
            if let Some(a) = run {
                mask.run(a, xs.end, y);
            }
        }
    }

    /// Upsamples one 256 × 256 logit map into `full` (`h × w`), using `rows` (256 × `w`) as
    /// scratch.
    pub fn upsample(&self, low: &[f32], rows: &mut [f32], full: &mut [f32]) {
        let w = self.x.len();
        for (r, out) in rows.chunks_exact_mut(w).enumerate().take(256) {
            let src = &low[r * 256..(r + 1) * 256];
            for (o, t) in out.iter_mut().zip(&self.x) {
                *o = row_tap(t, src);
            }
        }
        for (out, (idx, wt)) in full.chunks_exact_mut(w).zip(&self.y) {
            let r = |k: usize| &rows[idx[k] as usize * w..(idx[k] as usize + 1) * w];
            let (r0, r1, r2, r3) = (r(0), r(1), r(2), r(3));
            for x in 0..w {
                out[x] = wt[0] * r0[x] + wt[1] * r1[x] + wt[2] * r2[x] + wt[3] * r3[x];
            }
        }
    }
}

/// Sets bits `start..start + len` of a row-major bitset.
fn set_bits(bits: &mut [u64], start: usize, len: usize) {
    let (mut k, end) = (start, start + len);
    while k < end {
        let (word, bit) = (k / 64, k % 64);
        let n = (64 - bit).min(end - k);
        let ones = if n == 64 {
            u64::MAX
        } else {
            ((1u64 << n) - 1) << bit
        };
        bits[word] |= ones;
        k += n;
    }
}

/// torchvision `nms` (CPU kernel) over xyxy boxes with scores = predicted IoU: indices kept, in
/// descending score order (stable sort).
fn nms(cands: &[Candidate], iou_thresh: f32) -> Vec<usize> {
    let mut order: Vec<usize> = (0..cands.len()).collect();
    order.sort_by(|&a, &b| cands[b].iou.total_cmp(&cands[a].iou));
    let boxes: Vec<[f32; 4]> = cands.iter().map(|c| c.bbox.map(|v| v as f32)).collect();
    let areas: Vec<f32> = boxes
        .iter()
        .map(|b| (b[2] - b[0]) * (b[3] - b[1]))
        .collect();
    let mut suppressed = vec![false; cands.len()];
    let mut keep = Vec::new();
    for (oi, &i) in order.iter().enumerate() {
        if suppressed[i] {
            continue;
        }
        keep.push(i);
        let bi = boxes[i];
        for &j in &order[oi + 1..] {
            if suppressed[j] {
                continue;
            }
            let bj = boxes[j];
            let ww = (bi[2].min(bj[2]) - bi[0].max(bj[0])).max(0.0);
            let hh = (bi[3].min(bj[3]) - bi[1].max(bj[1])).max(0.0);
            let inter = ww * hh;
            let ovr = inter / (areas[i] + areas[j] - inter);
            if f64::from(ovr) > f64::from(iou_thresh) {
                suppressed[j] = true;
            }
        }
    }
    keep
}

/// Signature step of [`SamAutomaticMaskGenerator::with_placement`]: the layout of the
/// low-resolution logits of the decoder at `decoder`, which is segment_anything's full
/// `SamOnnxModel` (`masks` included) or one cut down to `iou_predictions` and `low_res_masks`
/// (scripts/sam-decoder-low-res.py [--f16-multimask]).
///
/// # Errors
/// [`Error::Model`] for neither signature; [`Error::Param`] for a cut-down decoder with
/// [`MaskPostprocess::Graph`], which reads the full-resolution `masks`.
fn decoder_low_res(
    dec: &OnnxModel,
    decoder: &Path,
    postprocess: MaskPostprocess,
) -> Result<LowResLogits> {
    let low_res_as = |outputs| {
        onnx::check_signature(
            dec.session(),
            decoder,
            "SAM mask decoder",
            DECODER_INPUTS,
            outputs,
            "",
        )
        .is_ok()
    };
    let f16_multimask = low_res_as(DECODER_OUTPUTS_LOW_RES_F16);
    let low_res_only = f16_multimask || low_res_as(DECODER_OUTPUTS_LOW_RES);
    if !low_res_only {
        onnx::check_signature(
            dec.session(),
            decoder,
            "SAM mask decoder",
            DECODER_INPUTS,
            DECODER_OUTPUTS,
            "pass a SAM decoder exported with segment_anything's SamOnnxModel \
             (return_single_mask=False, dynamic point axes), e.g. scripts/export-models.py \
             sam, or one cut down to iou_predictions and low_res_masks by \
             scripts/sam-decoder-low-res.py [--f16-multimask]",
        )?;
    }
    if low_res_only && postprocess == MaskPostprocess::Graph {
        return Err(Error::param(
            "postprocess",
            "graph",
            format!(
                "the low-resolution post-processing: {} has no full-resolution `masks` \
                 output (cut down by scripts/sam-decoder-low-res.py); pass the full decoder \
                 for MaskPostprocess::Graph",
                decoder.display()
            ),
        ));
    }
    Ok(if f16_multimask {
        LowResLogits::F16Multimask
    } else {
        LowResLogits::F32AllChannels
    })
}

impl MaskGenerator for SamAutomaticMaskGenerator {
    fn name(&self) -> &str {
        "sam"
    }

    fn generate(&mut self, image: &RgbImage) -> Result<Vec<Mask>> {
        self.generate_masks(image)
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn point_grid_matches_segment_anything() {
        let g = build_point_grid(16);
        assert_eq!(g.len(), 256);
        assert_eq!(g[0], [1.0 / 32.0, 1.0 / 32.0]);
        assert_eq!(g[1][1], 1.0 / 32.0);
        assert!((g[1][0] - 3.0 / 32.0).abs() < 1e-15);
        assert_eq!(g[255], [31.0 / 32.0, 31.0 / 32.0]);
        // The reference's first mask came from grid point (31/32 * 990, ...).
        assert_eq!(g[15][0] * 990.0, 959.0625);
    }

    fn cand(bbox: [u32; 4], iou: f32) -> Candidate {
        Candidate {
            bits: vec![],
            bbox,
            area: 1,
            iou,
            stability: 1.0,
            point: [0.0; 2],
            channel: 1,
        }
    }

    #[test]
    fn nms_suppresses_overlaps_above_threshold_in_score_order() {
        let c = vec![
            cand([0, 0, 10, 10], 0.8),
            cand([0, 0, 10, 11], 0.9), // IoU 100/110 with the first: suppresses it
            cand([20, 20, 30, 30], 0.85),
            cand([0, 0, 10, 15], 0.95), // IoU with #1 = 110/150 = 0.733 > 0.7
        ];
        // #0 overlaps #3 at 100/150 = 0.667: kept at 0.7.
        assert_eq!(nms(&c, 0.7), vec![3, 2, 0]);
        // At 0.75 the 0.733 overlap survives, then #0 is suppressed by #1 (0.909).
        assert_eq!(nms(&c, 0.75), vec![3, 1, 2]);
    }

    #[test]
    fn decoder_batches_shrink_to_their_memory_budget() {
        let p = SamParams::default();
        assert_eq!(
            p.batch_for(742, 990, false),
            CPU_POINTS_PER_BATCH,
            "CPU: 64 by default"
        );
        assert_eq!(p.batch_for(742, 990, true), GPU_POINTS_PER_BATCH);
        let small = SamParams {
            points_per_side: 8,
            ..SamParams::default()
        };
        assert_eq!(
            small.batch_for(742, 990, true),
            64,
            "never more than the grid"
        );
        let asked = SamParams {
            points_per_batch: Some(100),
            ..SamParams::default()
        };
        assert_eq!(
            asked.batch_for(742, 990, true),
            100,
            "asked for: on any provider"
        );
        assert_eq!(asked.batch_for(742, 990, false), 100);
        let per = decoder_bytes_per_prompt(742, 990);
        assert_eq!(per, 32 * (742 * 990 + 1024 * 1024));
        let capped = |bytes| {
            SamParams {
                decoder_batch_bytes: Some(bytes),
                ..SamParams::default()
            }
            .batch_for(742, 990, false)
        };
        assert_eq!(capped(10 * per + 1), 10);
        assert_eq!(capped(0), 1, "at least one prompt");
        assert_eq!(capped(1000 * per), 64, "never above the batch asked for");
    }

    #[test]
    fn params_are_validated() {
        assert!(SamParams::default().validate().is_ok());
        let bad = SamParams {
            points_per_batch: Some(0),
            ..SamParams::default()
        };
        assert!(matches!(
            bad.validate(),
            Err(Error::Param {
                name: "points_per_batch",
                ..
            })
        ));
        let bad = SamParams {
            pred_iou_thresh: f32::NAN,
            ..SamParams::default()
        };
        assert!(matches!(
            bad.validate(),
            Err(Error::Param {
                name: "pred_iou_thresh",
                ..
            })
        ));
    }

    /// Deterministic uniform floats in [0, 1) (splitmix64).
    fn uniform(seed: u64) -> impl FnMut() -> f32 {
        let mut state = seed;
        move || {
            state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = state;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32
        }
    }

    /// A 256 × 256 logit map: blobs (smooth, SAM-like, ±20) or a sharp-edged step map with
    /// plateaus (color-sam-like), from `seed`.
    fn logit_map(seed: u64, sharp: bool) -> Vec<f32> {
        let mut u = uniform(seed);
        let blobs: Vec<[f32; 4]> = (0..6)
            .map(|_| [u() * 256.0, u() * 256.0, 8.0 + u() * 60.0, u() * 2.0 - 0.7])
            .collect();
        (0..256 * 256)
            .map(|k| {
                let (x, y) = ((k % 256) as f32, (k / 256) as f32);
                let v: f32 = blobs
                    .iter()
                    .map(|b| {
                        b[3] * (-((x - b[0]).powi(2) + (y - b[1]).powi(2)) / (b[2] * b[2])).exp()
                    })
                    .sum();
                if sharp {
                    if v > 0.1 { 12.0 } else { -12.0 }
                } else {
                    40.0 * v - 1.0
                }
            })
            .collect()
    }

    fn assert_same(a: Option<Candidate>, b: Option<Candidate>, what: &str) {
        match (a, b) {
            (None, None) => {}
            (Some(a), Some(b)) => {
                assert_eq!(a.bbox, b.bbox, "{what}: box");
                assert_eq!(a.area, b.area, "{what}: area");
                assert_eq!(
                    a.stability.to_bits(),
                    b.stability.to_bits(),
                    "{what}: stability"
                );
                assert!(a.bits == b.bits, "{what}: pixels");
                assert_eq!(
                    (a.iou, a.channel, a.point),
                    (b.iou, b.channel, b.point),
                    "{what}"
                );
            }
            (a, b) => panic!("{what}: kept {} vs {}", a.is_some(), b.is_some()),
        }
    }

    #[test]
    fn block_decided_candidates_equal_the_full_upsampling() {
        let params = |thr: f32, off: f32, stab: f32| SamParams {
            mask_threshold: thr,
            stability_score_offset: off,
            stability_score_thresh: stab,
            ..SamParams::default()
        };
        let mut maps: Vec<(String, Vec<f32>)> = (0..6)
            .map(|s| (format!("map {s}"), logit_map(s, s % 3 == 2)))
            .collect();
        for v in [0.0f32, 1.0, -1.0, 1e-6, 1.0 - 1e-6, 5.0] {
            maps.push((format!("constant {v}"), vec![v; 256 * 256]));
        }
        let mut ramp = logit_map(9, false);
        ramp[1234] = f32::NAN;
        maps.push(("NaN logit".into(), ramp));
        let mut inf = logit_map(10, true);
        inf[40_000] = f32::INFINITY;
        maps.push(("infinite logit".into(), inf));
        let sizes = [
            (742u32, 990u32),
            (990, 742),
            (1024, 1024),
            (17, 31),
            (1500, 2000),
            (1, 1),
        ];
        for (h, w) in sizes {
            let up = LowResUpsampler::new((h, w), sam_preprocess_shape(h, w, SAM_IMAGE_SIZE));
            let (mut rows, mut full) = (vec![0f32; 256 * w as usize], vec![0f32; (h * w) as usize]);
            let mut scratch = up.scratch();
            for p in [
                params(0.0, 1.0, 0.0),
                params(0.0, 1.0, 0.9),
                params(0.3, 0.0, 0.5),
                params(-2.0, 4.0, 0.0),
            ] {
                for (name, low) in &maps {
                    up.upsample(low, &mut rows, &mut full);
                    let want = candidate(&full, w as usize, &p, 0.9, [1.5, 2.5], 2);
                    let got = up.candidate(low, &mut scratch, &p, 0.9, [1.5, 2.5], 2);
                    let what = format!(
                        "{name}, {w}x{h}, threshold {} offset {}",
                        p.mask_threshold, p.stability_score_offset
                    );
                    assert_same(got, want, &what);
                }
            }
        }
    }
}
