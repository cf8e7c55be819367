//! Masks: the paper's segmentation step. Every generator returns full-resolution binary masks of one
//! image; masks may overlap (SAM) or partition the image (graph segmenter).
//!
//! - [`sam`]: SAM automatic mask generation over any SAM-family ONNX encoder/decoder pair
//!   (segment_anything 1.0 `SamAutomaticMaskGenerator`, `crop_n_layers = 0`).
//! - [`graph`]: Felzenszwalb-Huttenlocher graph segmentation, weight-free, CPU.
//! - [`compact`]: masks as they travel between the pipeline's stages (run-length encoded).
//! - [`timed`]: a timing model + mask model pair for benchmarks (cost of one SAM, masks of another).

use image::RgbImage;
use slag_common::Result;

pub mod compact;
pub mod graph;
pub mod sam;
pub mod timed;

/// What is known of one mask besides which pixels it covers: its image's size, its box and area,
/// and the generator's scores, point and level. Shared by the full mask ([`Mask`], a byte per
/// pixel) and the compact one ([`compact::CompactMask`], runs), which both dereference to it, so
/// that `mask.area` reads the same on either.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MaskMeta {
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Bounding box `[x, y, w, h]` in SAM's (COCO) convention: `x, y` = min column/row of the
    /// mask, `w = max_col - x`, `h = max_row - y` (the box is inclusive: the crop spans `w+1` columns).
    pub bbox_xywh: [u32; 4],
    /// Number of pixels inside the mask.
    pub area: u32,
    /// SAM's predicted IoU (1.0 for generators without a score).
    pub predicted_iou: f32,
    /// SAM's stability score (1.0 for generators without a score).
    pub stability_score: f32,
    /// The prompt point `(x, y)` in image pixels that produced the mask, if any.
    pub point: Option<[f32; 2]>,
    /// Granularity level, for generators that produce several per prompt: SAM's multimask
    /// output channel 1, 2, 3 as level 0, 1, 2 (by SAM's convention roughly subpart, part,
    /// whole; LangSplat's three levels). `None` for generators without levels (the graph
    /// segmenter, masks built from pixels).
    pub level: Option<u8>,
}

impl MaskMeta {
    /// The metadata of a mask from a generator without scores, prompts or levels (the graph
    /// segmenter, masks built from pixels, eroded masks): both scores 1.0, no point, no level.
    /// `bbox_xywh` and `area` as on [`MaskMeta`], in pixels of the `width × height` image.
    pub fn unscored(width: u32, height: u32, bbox_xywh: [u32; 4], area: u32) -> MaskMeta {
        MaskMeta {
            width,
            height,
            bbox_xywh,
            area,
            predicted_iou: 1.0,
            stability_score: 1.0,
            point: None,
            level: None,
        }
    }
}

/// One binary mask over an image of `width` x `height` pixels: its pixels and its metadata
/// ([`MaskMeta`], whose fields read and write through the mask: `mask.area`).
#[derive(Debug, Clone, PartialEq)]
pub struct Mask {
    /// `width * height` values, row-major, 1 = inside the mask, 0 = outside.
    pub pixels: Vec<u8>,
    /// Size, box, area, scores, point and level.
    pub meta: MaskMeta,
}

/// `Deref` and `DerefMut` of a mask type with a `meta: MaskMeta` field to that field, so that
/// `mask.area` reads and writes the metadata whatever holds the pixels.
macro_rules! deref_to_meta {
    ($mask:ty) => {
        impl std::ops::Deref for $mask {
            type Target = $crate::masks::MaskMeta;
            fn deref(&self) -> &$crate::masks::MaskMeta {
                &self.meta
            }
        }

        impl std::ops::DerefMut for $mask {
            fn deref_mut(&mut self) -> &mut $crate::masks::MaskMeta {
                &mut self.meta
            }
        }
    };
}
pub(crate) use deref_to_meta;

deref_to_meta!(Mask);

impl Mask {
    /// The mask of the pixels `(x, y)` of a `width × height` image where `inside(x, y)` holds
    /// ([`Mask::from_pixels`]); `None` when it holds nowhere. For tests.
    #[cfg(test)]
    pub(crate) fn from_fn(
        width: u32,
        height: u32,
        inside: impl Fn(u32, u32) -> bool,
    ) -> Option<Mask> {
        let pixels = (0..height)
            .flat_map(|y| (0..width).map(move |x| (x, y)))
            .map(|(x, y)| u8::from(inside(x, y)))
            .collect();
        Mask::from_pixels(width, height, pixels)
    }

    /// Builds a mask from a row-major 0/1 buffer, computing `area` and `bbox_xywh`.
    /// Returns `None` for an empty mask or a buffer whose length is not `width * height`.
    pub fn from_pixels(width: u32, height: u32, pixels: Vec<u8>) -> Option<Mask> {
        if pixels.len() != width as usize * height as usize {
            return None;
        }
        let (mut x0, mut y0, mut x1, mut y1, mut area) = (u32::MAX, u32::MAX, 0u32, 0u32, 0u32);
        for (i, &v) in pixels.iter().enumerate() {
            if v != 0 {
                let (x, y) = ((i % width as usize) as u32, (i / width as usize) as u32);
                x0 = x0.min(x);
                y0 = y0.min(y);
                x1 = x1.max(x);
                y1 = y1.max(y);
                area += 1;
            }
        }
        (area > 0).then(|| Mask {
            pixels,
            meta: MaskMeta::unscored(width, height, [x0, y0, x1 - x0, y1 - y0], area),
        })
    }

    /// Whether pixel `(x, y)` is inside the mask (false outside the image).
    pub fn contains(&self, x: u32, y: u32) -> bool {
        x < self.width && y < self.height && self.pixels[(y * self.width + x) as usize] != 0
    }
}

/// A source of masks for one image (the paper's SAM step, or a cheaper stand-in).
pub trait MaskGenerator: Send {
    /// Short name recorded in the run report (e.g. `"sam"`, `"graph"`).
    fn name(&self) -> &str;
    /// All masks of `image` (RGB, any size), in the generator's own order.
    fn generate(&mut self, image: &RgbImage) -> Result<Vec<Mask>>;
}
