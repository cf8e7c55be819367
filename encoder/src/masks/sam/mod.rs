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
//!
//! The files: [`params`] holds the parameters and the prompt grid; [`candidates`] the masks that
//! pass the filters and their NMS; [`low_res`] the decoder's low-resolution logits and their
//! upsampling on the host; this file the models and the generator that runs them.

mod candidates;
mod low_res;
mod params;
#[cfg(test)]
mod tests;

pub use low_res::{LowResLogits, LowResUpsampler};
pub use params::{
    CPU_POINTS_PER_BATCH, GPU_POINTS_PER_BATCH, MaskPostprocess, SamParams, build_point_grid,
    decoder_bytes_per_prompt,
};
use std::path::Path;
use std::sync::{Arc, Mutex};

use image::RgbImage;
use ort::session::{OutputSelector, RunOptions};
use ort::value::{DynValue, TensorRef};
use rayon::prelude::*;
use slag_common::onnx::{self, ElemType, ExecutionProvider, OnnxModel, Placement, TensorSpec};
use slag_common::{Error, Result};

use super::{Mask, MaskGenerator, MaskMeta};
use crate::preprocess::{SAM_IMAGE_SIZE, sam_pixel_values, sam_preprocess_shape};

use self::candidates::{Candidate, candidate, nms};
use self::low_res::LowResMaps;

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
                    pixels,
                    meta: MaskMeta {
                        width: w,
                        height: h,
                        bbox_xywh: [x0, y0, x1 - x0, y1 - y0],
                        area: c.area,
                        predicted_iou: c.iou,
                        stability_score: c.stability,
                        point: Some([c.point[0] as f32, c.point[1] as f32]),
                        level: Some(c.channel - 1),
                    },
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
