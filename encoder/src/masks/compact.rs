//! Masks as they travel between the pipeline's stages: run-length encoded.
//!
//! A [`Mask`] holds one byte per image pixel (990 × 742 = 0.73 MB); SAM gives 60–100 overlapping
//! masks per image, 44–73 MB per image, and every image queued between the front stages (SAM,
//! CLIP) and the back stage (raster, `a_kj`) held that much. A [`CompactMask`] keeps the same
//! mask as row-major runs of inside pixels, 8 bytes a run: a mask of a few blobs costs a few
//! kB. [`CompactMask::expand`] gives back the identical [`Mask`], so whatever the back stage
//! computes from it is bit-identical.

use super::{Mask, MaskMeta};

/// One [`Mask`] as row-major runs of inside pixels, with its metadata unchanged (the same
/// [`MaskMeta`], whose fields read and write through the compact mask: `compact.area`).
#[derive(Debug, Clone, PartialEq)]
pub struct CompactMask {
    /// `(start, len)` of each run of inside pixels, `start` the row-major pixel index
    /// `y * width + x`; runs are ascending, non-empty, never adjacent and never cross a row end.
    pub runs: Vec<(u32, u32)>,
    /// Size, box, area, scores, point and level, as the [`Mask`]'s.
    pub meta: MaskMeta,
}

super::deref_to_meta!(CompactMask);

impl CompactMask {
    /// Encodes `mask` (any pixel value other than 0 is inside; [`CompactMask::expand`] writes 1).
    ///
    /// Every pixel is scanned (the box is not trusted); a mask whose `pixels` do not have
    /// `width * height` values is encoded over the values it has.
    pub fn new(mask: &Mask) -> Self {
        let w = mask.width as usize;
        let mut runs = Vec::new();
        if w > 0 {
            for (y, row) in mask.pixels.chunks(w).enumerate() {
                let mut x = 0;
                while x < row.len() {
                    if row[x] == 0 {
                        x += 1;
                        continue;
                    }
                    let start = x;
                    while x < row.len() && row[x] != 0 {
                        x += 1;
                    }
                    runs.push(((y * w + start) as u32, (x - start) as u32));
                }
            }
        }
        CompactMask {
            runs,
            meta: mask.meta,
        }
    }

    /// The [`Mask`] again: `width * height` bytes, 1 inside the runs, 0 elsewhere; metadata as
    /// encoded. Runs reaching past `width * height` (only from a hand-built value) are clipped.
    pub fn expand(&self) -> Mask {
        let n = self.width as usize * self.height as usize;
        let mut pixels = vec![0u8; n];
        for &(start, len) in &self.runs {
            let a = (start as usize).min(n);
            let b = (start as usize + len as usize).min(n);
            pixels[a..b].fill(1);
        }
        Mask {
            pixels,
            meta: self.meta,
        }
    }

    /// Bytes this mask holds on the heap and inline (what a queued image costs per mask).
    pub fn bytes(&self) -> usize {
        std::mem::size_of::<Self>() + self.runs.capacity() * std::mem::size_of::<(u32, u32)>()
    }
}

/// Encodes every mask of an image ([`CompactMask::new`]), in order, in parallel (rayon).
pub fn compact_all(masks: &[Mask]) -> Vec<CompactMask> {
    use rayon::prelude::*;
    masks.par_iter().map(CompactMask::new).collect()
}

/// Expands every mask of an image ([`CompactMask::expand`]), in order.
pub fn expand_all(masks: &[CompactMask]) -> Vec<Mask> {
    masks.iter().map(CompactMask::expand).collect()
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn mask(w: u32, h: u32, f: impl Fn(u32, u32) -> bool) -> Mask {
        let mut m = Mask::from_fn(w, h, f).unwrap();
        m.predicted_iou = 0.93;
        m.stability_score = 0.71;
        m.point = Some([3.5, 1.25]);
        m.level = Some(2);
        m
    }

    #[test]
    fn expand_gives_back_the_identical_mask() {
        let cases = [
            mask(7, 5, |x, y| (x + y) % 3 == 0),
            mask(9, 4, |x, _| x == 8),
            mask(9, 4, |x, _| x == 0),
            mask(6, 6, |_, _| true),
            mask(13, 11, |x, y| {
                (x as i32 - 6).pow(2) + (y as i32 - 5).pow(2) < 16
            }),
        ];
        for m in cases {
            let c = CompactMask::new(&m);
            assert_eq!(c.expand(), m);
            assert_eq!(
                c.runs.iter().map(|r| r.1).sum::<u32>(),
                m.area,
                "runs cover the area"
            );
            // Runs stay inside one row each.
            for &(s, l) in &c.runs {
                assert_eq!(s / m.width, (s + l - 1) / m.width);
            }
        }
        let all = vec![mask(4, 3, |x, _| x < 2), mask(4, 3, |_, y| y == 1)];
        assert_eq!(expand_all(&compact_all(&all)), all);
    }

    #[test]
    fn a_full_row_is_one_run_per_row_and_a_blob_costs_far_less_than_its_pixels() {
        let m = mask(990, 742, |x, y| {
            (200..600).contains(&x) && (100..500).contains(&y)
        });
        let c = CompactMask::new(&m);
        assert_eq!(c.runs.len(), 400);
        assert!(c.bytes() < m.pixels.len() / 100, "{} bytes", c.bytes());
        let full = mask(5, 3, |_, _| true);
        assert_eq!(CompactMask::new(&full).runs, vec![(0, 5), (5, 5), (10, 5)]);
    }

    #[test]
    fn out_of_range_runs_are_clipped_not_a_panic() {
        let mut c = CompactMask::new(&mask(4, 2, |x, _| x == 0));
        c.runs.push((6, 100));
        let m = c.expand();
        assert_eq!(m.pixels, vec![1, 0, 0, 0, 1, 0, 1, 1]);
    }
}
