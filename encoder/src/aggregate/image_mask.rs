//! What the image stage reads of a mask ([`ImageMask`]): the same answers from a full mask
//! ([`Mask`]) and a compact one ([`CompactMask`]), for the pixel labels ([`super::image`]) and
//! the erosion ([`super::erode`]).

use crate::masks::compact::CompactMask;
use crate::masks::{Mask, MaskMeta};

/// What the image stage reads of a mask at its image's full resolution: its size, box, area and
/// SAM scores (the [`MaskMeta`] it dereferences to), and which pixels of a row are inside. Implemented by
/// [`Mask`] (a byte per pixel) and [`CompactMask`] (runs), which give the same answers, so that
/// the labels of an image are made from the compact masks without expanding them.
pub trait ImageMask: std::ops::Deref<Target = MaskMeta> + Sync {
    /// `(width, height)` of the mask's image, pixels.
    fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }
    /// As [`MaskMeta::bbox_xywh`].
    fn bbox_xywh(&self) -> [u32; 4] {
        self.bbox_xywh
    }
    /// As [`MaskMeta::area`].
    fn area(&self) -> u32 {
        self.area
    }
    /// As [`MaskMeta::predicted_iou`] and [`MaskMeta::stability_score`].
    fn scores(&self) -> (f32, f32) {
        (self.predicted_iou, self.stability_score)
    }
    /// Calls `hit(x)` for each `(x, sx)` of `cols` (`sx` ascending, `< width`) whose pixel
    /// `(sx, sy)` is inside the mask (`sy < height`).
    fn row_hits(&self, sy: u32, cols: impl Iterator<Item = (usize, u32)>, hit: impl FnMut(usize));
}

impl ImageMask for Mask {
    fn row_hits(
        &self,
        sy: u32,
        cols: impl Iterator<Item = (usize, u32)>,
        mut hit: impl FnMut(usize),
    ) {
        let row = sy as usize * self.width as usize;
        for (x, sx) in cols {
            if self.pixels.get(row + sx as usize).is_some_and(|&v| v != 0) {
                hit(x);
            }
        }
    }
}

impl ImageMask for CompactMask {
    fn row_hits(
        &self,
        sy: u32,
        cols: impl Iterator<Item = (usize, u32)>,
        mut hit: impl FnMut(usize),
    ) {
        // Runs are ascending and never cross a row end: walk the row's runs with the columns.
        let row = u64::from(sy) * u64::from(self.width);
        let mut r = self
            .runs
            .partition_point(|&(start, len)| u64::from(start) + u64::from(len) <= row);
        for (x, sx) in cols {
            let p = row + u64::from(sx);
            while r < self.runs.len() && u64::from(self.runs[r].0) + u64::from(self.runs[r].1) <= p
            {
                r += 1;
            }
            match self.runs.get(r) {
                Some(&(start, _)) if u64::from(start) <= p => hit(x),
                Some(_) => {}
                None => break,
            }
        }
    }
}
