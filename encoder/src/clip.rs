//! CLIP image embeddings of mask crops (SLAG: `E_j` = CLIP embedding of mask `M_j`'s crop).
//!
//! The crop is the paper's: the mask's bounding box (inclusive, SAM/COCO `xywh`), pixels outside
//! the mask set to white (255). Each crop gets open_clip's preprocessing
//! ([`crate::preprocess::clip_pixel_values`]: shortest side 224 with PIL bicubic, centre crop,
//! CLIP mean/std), crops run through the visual tower in batches, and every output is
//! L2-normalised.

use std::path::{Path, PathBuf};

use image::RgbImage;
use ort::session::Session;
use ort::value::TensorRef;
use rayon::prelude::*;
use slag_common::onnx::{self, ElemType, ExecutionProvider, TensorSpec};
use slag_common::text::l2_normalize;
use slag_common::{Error, Result};

use crate::masks::Mask;
use crate::preprocess::{CLIP_IMAGE_SIZE, clip_pixel_values};

const VISUAL_INPUTS: &[TensorSpec] = &[TensorSpec::named(
    "pixel_values",
    ElemType::F32,
    &[-1, 3, 224, 224],
)];
const VISUAL_OUTPUTS: &[TensorSpec] = &[TensorSpec::any_name(ElemType::F32, &[-1, -1])];

/// The white-background bounding-box crop of `mask` in `image` (the paper's CLIP input):
/// `np.where(mask, image, 255)[y:y+h+1, x:x+w+1]` with `[x, y, w, h] = mask.bbox_xywh`, the box
/// clipped to the image.
///
/// # Errors
/// [`Error::Invalid`] when the mask and image sizes differ or the box lies outside the image.
pub fn crop(image: &RgbImage, mask: &Mask) -> Result<RgbImage> {
    if (mask.width, mask.height) != image.dimensions() {
        return Err(Error::Invalid(format!(
            "mask is {}x{} but the image is {}x{}: masks must be at full image resolution",
            mask.width,
            mask.height,
            image.width(),
            image.height()
        )));
    }
    if mask.pixels.len() != mask.width as usize * mask.height as usize {
        return Err(Error::Invalid(format!(
            "mask has {} pixels, expected {}x{}",
            mask.pixels.len(),
            mask.width,
            mask.height
        )));
    }
    let [x, y, w, h] = mask.bbox_xywh;
    let (iw, ih) = image.dimensions();
    if x >= iw || y >= ih {
        return Err(Error::Invalid(format!(
            "mask bbox [{x}, {y}, {w}, {h}] starts outside the {iw}x{ih} image"
        )));
    }
    let x1 = x.saturating_add(w).min(iw - 1);
    let y1 = y.saturating_add(h).min(ih - 1);
    let (cw, ch) = (x1 - x + 1, y1 - y + 1);
    let mut out = RgbImage::new(cw, ch);
    for yy in 0..ch {
        for xx in 0..cw {
            let (sx, sy) = (x + xx, y + yy);
            let inside = mask.pixels[(sy * iw + sx) as usize] != 0;
            let p = if inside {
                *image.get_pixel(sx, sy)
            } else {
                image::Rgb([255, 255, 255])
            };
            out.put_pixel(xx, yy, p);
        }
    }
    Ok(out)
}

/// The CLIP image tower over ONNX (`pixel_values f32[B,3,224,224] → one f32[B,D] output`, e.g.
/// open_clip's `encode_image` without normalisation).
pub struct ClipVisual {
    session: Session,
    path: PathBuf,
    batch_size: usize,
    input_name: String,
    model_id: String,
    dim: usize,
}

impl ClipVisual {
    /// Loads and checks the visual tower; crops are embedded `batch_size` at a time.
    ///
    /// # Errors
    /// [`Error::Invalid`] for `batch_size == 0`; [`Error::Model`] for a missing/unloadable model or
    /// the wrong signature (e.g. a SAM encoder or a text tower).
    pub fn new(model: &Path, ep: ExecutionProvider, batch_size: usize) -> Result<Self> {
        Self::with_threads(model, ep, batch_size, 0)
    }

    /// [`ClipVisual::new`] with an explicit ONNX Runtime intra-op thread count (0 = default).
    ///
    /// # Errors
    /// As [`ClipVisual::new`].
    pub fn with_threads(
        model: &Path,
        ep: ExecutionProvider,
        batch_size: usize,
        intra_threads: usize,
    ) -> Result<Self> {
        if batch_size == 0 {
            return Err(Error::Invalid("CLIP batch size must be at least 1".into()));
        }
        let session = onnx::load_session(model, ep, intra_threads)?;
        onnx::check_signature(
            &session,
            model,
            "CLIP image tower",
            VISUAL_INPUTS,
            VISUAL_OUTPUTS,
            "pass a CLIP visual model exported with input pixel_values f32[B,3,224,224] and one \
             output image_embeds f32[B,D] (e.g. open_clip encode_image)",
        )?;
        let input_name = session.inputs()[0].name().to_string();
        let declared = match session.outputs()[0].dtype() {
            ort::value::ValueType::Tensor { shape, .. } => shape.last().copied().filter(|&d| d > 0),
            _ => None,
        };
        let model_id = onnx::clip_pair_id(&session, model);
        let mut clip = ClipVisual {
            session,
            path: model.to_path_buf(),
            batch_size,
            input_name,
            model_id,
            dim: 0,
        };
        clip.dim = match declared {
            Some(d) => d as usize,
            // Dynamic width: one probe run on a mid-grey image.
            None => clip.embed_pixels(&vec![0.5f32; 3 * 224 * 224])?[0].len(),
        };
        Ok(clip)
    }

    /// Embedding width D (the model's output width).
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Model id recorded in outputs: the CLIP pair id ([`onnx::clip_pair_id`]: ONNX metadata
    /// `slag.clip_pair_id`, else the file stem without `-visual`, e.g. `color-clip`).
    pub fn model_id(&self) -> &str {
        &self.model_id
    }

    /// Embeds preprocessed pixels `f32[n,3,224,224]`: `n` L2-normalised rows of the model's width.
    ///
    /// # Errors
    /// [`Error::Invalid`] for a buffer that is not a whole number of images, [`Error::Model`]
    /// when the run fails or an embedding has zero norm.
    pub fn embed_pixels(&mut self, pixels: &[f32]) -> Result<Vec<Vec<f32>>> {
        let s = CLIP_IMAGE_SIZE as usize;
        let per = 3 * s * s;
        if !pixels.len().is_multiple_of(per) {
            return Err(Error::Invalid(format!(
                "CLIP pixel buffer of {} values is not a multiple of 3*224*224",
                pixels.len()
            )));
        }
        let n = pixels.len() / per;
        let path = &self.path;
        let input = TensorRef::from_array_view(([n, 3, s, s], pixels))
            .map_err(|e| Error::model(path, format!("cannot build the CLIP input: {e}")))?;
        let outputs = self
            .session
            .run(ort::inputs![self.input_name.as_str() => input])
            .map_err(|e| Error::model(path, format!("CLIP visual run failed: {e}")))?;
        let (shape, data) = outputs[0]
            .try_extract_tensor::<f32>()
            .map_err(|e| Error::model(path, format!("CLIP output is not f32: {e}")))?;
        if shape.len() != 2 || shape[0] != n as i64 || shape[1] <= 0 {
            return Err(Error::model(
                path,
                format!("CLIP visual returned shape {shape:?} for {n} images, expected [{n}, D]"),
            ));
        }
        let d = shape[1] as usize;
        let mut out: Vec<Vec<f32>> = data.chunks_exact(d).map(<[f32]>::to_vec).collect();
        for v in &mut out {
            l2_normalize(v, path)?;
        }
        Ok(out)
    }

    /// CLIP embeddings (L2-normalised, model width `D`) of the white-background crops of `masks`
    /// in `image`, in mask order. Crops are cut and preprocessed in parallel (rayon), then run in
    /// batches of the configured size.
    ///
    /// # Errors
    /// As [`crop`] and [`ClipVisual::embed_pixels`].
    pub fn embed_masks(&mut self, image: &RgbImage, masks: &[Mask]) -> Result<Vec<Vec<f32>>> {
        let s = CLIP_IMAGE_SIZE as usize;
        let per = 3 * s * s;
        let mut out = Vec::with_capacity(masks.len());
        for chunk in masks.chunks(self.batch_size) {
            let mut pixels = vec![0f32; chunk.len() * per];
            pixels
                .par_chunks_mut(per)
                .zip(chunk.par_iter())
                .try_for_each(|(buf, m)| clip_pixel_values(&crop(image, m)?, buf))?;
            out.extend(self.embed_pixels(&pixels)?);
        }
        Ok(out)
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn crop_is_inclusive_bbox_with_white_outside() {
        let img = RgbImage::from_fn(6, 5, |x, y| image::Rgb([x as u8, y as u8, 7]));
        let mut px = vec![0u8; 30];
        px[6 + 2] = 1; // (2,1)
        px[3 * 6 + 4] = 1; // (4,3)
        let m = Mask::from_pixels(6, 5, px).unwrap();
        assert_eq!(m.bbox_xywh, [2, 1, 2, 2]);
        let c = crop(&img, &m).unwrap();
        assert_eq!(c.dimensions(), (3, 3));
        assert_eq!(c.get_pixel(0, 0).0, [2, 1, 7]);
        assert_eq!(c.get_pixel(2, 2).0, [4, 3, 7]);
        assert_eq!(c.get_pixel(1, 1).0, [255, 255, 255]);
        assert_eq!(c.get_pixel(2, 0).0, [255, 255, 255]);
    }

    #[test]
    fn crop_clips_box_and_rejects_size_mismatch() {
        let img = RgbImage::new(4, 4);
        let mut m = Mask::from_pixels(4, 4, vec![1; 16]).unwrap();
        m.bbox_xywh = [2, 2, 10, 10];
        assert_eq!(crop(&img, &m).unwrap().dimensions(), (2, 2));
        let small = RgbImage::new(3, 4);
        assert!(matches!(crop(&small, &m), Err(Error::Invalid(_))));
    }
}
