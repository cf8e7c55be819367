//! Mask erosion for lifting (`encode --mask-erode`): each mask shrunk by a square of radius `r`
//! image pixels for the pixel labels of the image stage, so that the pixels along a mask's
//! border — where a mask generator's assignment is least certain — no longer credit it: a pixel
//! credits those of its masks (after the overlap rule) that still hold it once eroded, or none
//! ([`super::image::stage_labels`]). The CLIP crop keeps the whole mask.
//!
//! A pixel stays in the eroded mask when every pixel within Chebyshev distance `r` (the
//! `(2r+1)²` square around it) is inside the mask or outside the image: the image's edge is not
//! a mask border (the mask goes on beyond the frame), so a mask is never eroded from there. A
//! mask that erosion would empty is kept whole, so that no mask loses all its weight. The
//! erosion is a separable min filter over the mask's bounding box, two passes of run lengths:
//! `O(box pixels)` per mask whatever `r`.

use rayon::prelude::*;

use super::image_mask::ImageMask;
use crate::masks::MaskMeta;
use crate::masks::compact::CompactMask;

/// Every mask of an image eroded by `radius` image pixels ([`erode_mask`]), in order, in
/// parallel (rayon).
pub fn erode_all<M: ImageMask>(masks: &[M], radius: u32) -> Vec<CompactMask> {
    masks.par_iter().map(|m| erode_mask(m, radius)).collect()
}

/// `mask` eroded by `radius` image pixels (see the module docs: square structuring element,
/// pixels beyond the image count as inside), as runs with the eroded box and area and the mask's
/// SAM scores (no point or level: the pixel labels read neither). When erosion leaves no pixel,
/// the mask itself comes back whole (its own pixels as runs). `radius` 0 gives the mask's
/// pixels unchanged.
pub fn erode_mask<M: ImageMask>(mask: &M, radius: u32) -> CompactMask {
    let (width, height) = mask.size();
    let [bx, by, bw, bh] = mask.bbox_xywh();
    let (predicted_iou, stability_score) = mask.scores();
    let mut out = if width == 0 || height == 0 || bx >= width || by >= height {
        grid_runs(&[], 1, [0, 0], (width, height))
    } else {
        // The box, inclusive, clipped to the image.
        let gw = (bw.min(width - 1 - bx) + 1) as usize;
        let gh = (bh.min(height - 1 - by) + 1) as usize;
        let mut inside = vec![false; gw * gh];
        for (y, row) in inside.chunks_exact_mut(gw).enumerate() {
            let cols = (0..gw).map(|x| (x, bx + x as u32));
            mask.row_hits(by + y as u32, cols, |x| row[x] = true);
        }
        let edges = Edges {
            left: bx == 0,
            right: bx as usize + gw == width as usize,
            top: by == 0,
            bottom: by as usize + gh == height as usize,
        };
        let eroded = erode_grid(&inside, gw, gh, radius as usize, edges);
        let kept = if eroded.contains(&true) {
            &eroded
        } else {
            &inside
        };
        grid_runs(kept, gw, [bx, by], (width, height))
    };
    out.predicted_iou = predicted_iou;
    out.stability_score = stability_score;
    out
}

/// Which sides of a box lie on the image's edge (beyond them: outside the image, counted as
/// inside the mask); beyond the other sides the image goes on outside the mask.
#[derive(Clone, Copy)]
struct Edges {
    left: bool,
    right: bool,
    top: bool,
    bottom: bool,
}

/// The `gw × gh` row-major grid eroded by a `(2r+1)²` square: rows, then columns, each a 1-D
/// min filter ([`erode_line`]).
fn erode_grid(grid: &[bool], gw: usize, gh: usize, r: usize, e: Edges) -> Vec<bool> {
    if r == 0 {
        return grid.to_vec();
    }
    let mut rows = vec![false; gw * gh];
    for (src, dst) in grid.chunks_exact(gw).zip(rows.chunks_exact_mut(gw)) {
        erode_line(src, dst, r, e.left, e.right);
    }
    let mut out = vec![false; gw * gh];
    let (mut col, mut col_out) = (vec![false; gh], vec![false; gh]);
    for x in 0..gw {
        col.iter_mut()
            .enumerate()
            .for_each(|(y, v)| *v = rows[y * gw + x]);
        erode_line(&col, &mut col_out, r, e.top, e.bottom);
        col_out
            .iter()
            .enumerate()
            .for_each(|(y, &v)| out[y * gw + x] = v);
    }
    out
}

/// 1-D erosion of `src` by radius `r` into `dst`: `dst[i]` is true when `src[i-r..=i+r]` is all
/// true, positions before the start (after the end) counting as true when `open_start`
/// (`open_end`), else as false. Two run-length scans, `O(len)`.
fn erode_line(src: &[bool], dst: &mut [bool], r: usize, open_start: bool, open_end: bool) {
    let n = src.len();
    // Inside pixels ending at i (capped at r + 1: enough to decide).
    let mut run = if open_start { r } else { 0 };
    for i in 0..n {
        run = if src[i] { (run + 1).min(r + 1) } else { 0 };
        dst[i] = run > r;
    }
    let mut run = if open_end { r } else { 0 };
    for i in (0..n).rev() {
        run = if src[i] { (run + 1).min(r + 1) } else { 0 };
        dst[i] &= run > r;
    }
}

/// The grid's inside pixels as a [`CompactMask`] of a `width × height` image, the grid's
/// top-left pixel at `origin`; box and area from the pixels (scores 1, no point or level).
fn grid_runs(
    grid: &[bool],
    gw: usize,
    [ox, oy]: [u32; 2],
    (width, height): (u32, u32),
) -> CompactMask {
    let mut runs = Vec::new();
    let (mut x0, mut y0, mut x1, mut y1) = (u32::MAX, u32::MAX, 0, 0);
    let mut area = 0u32;
    for (y, row) in grid.chunks_exact(gw).enumerate() {
        let mut x = 0;
        while x < gw {
            if !row[x] {
                x += 1;
                continue;
            }
            let start = x;
            while x < gw && row[x] {
                x += 1;
            }
            let (sx, sy) = (ox + start as u32, oy + y as u32);
            runs.push((sy * width + sx, (x - start) as u32));
            area += (x - start) as u32;
            (x0, x1) = (x0.min(sx), x1.max(ox + x as u32 - 1));
            (y0, y1) = (y0.min(sy), y1.max(sy));
        }
    }
    let bbox_xywh = if area == 0 {
        [0; 4]
    } else {
        [x0, y0, x1 - x0, y1 - y0]
    };
    CompactMask {
        runs,
        meta: MaskMeta::unscored(width, height, bbox_xywh, area),
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::masks::Mask;

    fn mask(w: u32, h: u32, f: impl Fn(u32, u32) -> bool) -> Mask {
        Mask::from_fn(w, h, f).unwrap()
    }

    /// Brute-force reference: every pixel of the `(2r+1)²` square inside the mask or outside
    /// the image.
    fn reference(m: &Mask, r: i64) -> Vec<u8> {
        let (w, h) = (i64::from(m.width), i64::from(m.height));
        let at = |x: i64, y: i64| {
            x < 0 || y < 0 || x >= w || y >= h || m.pixels[(y * w + x) as usize] != 0
        };
        (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .map(|(x, y)| {
                let all = (-r..=r).all(|dy| (-r..=r).all(|dx| at(x + dx, y + dy)));
                u8::from(all && m.pixels[(y * w + x) as usize] != 0)
            })
            .collect()
    }

    #[test]
    fn a_square_loses_exactly_its_border_of_width_r() {
        // 12×10 square at (5, 4) in a 30×20 image.
        let m = mask(30, 20, |x, y| (5..17).contains(&x) && (4..14).contains(&y));
        for r in [1u32, 2, 4] {
            let e = erode_mask(&m, r).expand();
            let want = mask(30, 20, |x, y| {
                (5 + r..17 - r).contains(&x) && (4 + r..14 - r).contains(&y)
            });
            assert_eq!(e.pixels, want.pixels, "r = {r}");
            assert_eq!(e.area, (12 - 2 * r) * (10 - 2 * r));
            assert_eq!(e.bbox_xywh, want.bbox_xywh);
        }
    }

    #[test]
    fn the_image_edge_is_not_a_mask_border() {
        // The bottom-left quarter of the image: eroded only from its top and right sides.
        let m = mask(20, 16, |x, y| x < 10 && y >= 8);
        let e = erode_mask(&m, 3).expand();
        let want = mask(20, 16, |x, y| x < 7 && y >= 11);
        assert_eq!(e.pixels, want.pixels);
        // A whole-image mask is kept whole.
        let full = mask(9, 7, |_, _| true);
        assert_eq!(erode_mask(&full, 5).expand().pixels, full.pixels);
    }

    #[test]
    fn a_mask_erosion_would_empty_is_kept_whole() {
        // A 3-pixel-thick bar: radius 2 removes it all, so it stays as it was.
        let m = mask(40, 20, |x, y| (5..35).contains(&x) && (8..11).contains(&y));
        let e = erode_mask(&m, 2).expand();
        assert_eq!(e.pixels, m.pixels);
        assert_eq!((e.area, e.bbox_xywh), (m.area, m.bbox_xywh));
        // Radius 1 keeps its middle row.
        let e = erode_mask(&m, 1).expand();
        assert_eq!(
            e.pixels,
            mask(40, 20, |x, y| (6..34).contains(&x) && y == 9).pixels
        );
    }

    #[test]
    fn irregular_masks_match_the_brute_force_erosion() {
        let mut state = 7u64;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 33) as u32
        };
        for _ in 0..30 {
            let (w, h) = (8 + next() % 24, 8 + next() % 24);
            // Blobs: a few filled discs, some touching the image edge.
            let discs: Vec<(i64, i64, i64)> = (0..3)
                .map(|_| {
                    (
                        i64::from(next() % w),
                        i64::from(next() % h),
                        2 + i64::from(next() % 6),
                    )
                })
                .collect();
            let m = mask(w, h, |x, y| {
                discs.iter().any(|&(cx, cy, rr)| {
                    (i64::from(x) - cx).pow(2) + (i64::from(y) - cy).pow(2) <= rr * rr
                })
            });
            for r in [0u32, 1, 2, 3] {
                let want = reference(&m, i64::from(r));
                let got = erode_mask(&m, r);
                if want.iter().any(|&v| v != 0) {
                    assert_eq!(got.expand().pixels, want, "r = {r}");
                    assert_eq!(got.area as usize, want.iter().filter(|&&v| v != 0).count());
                } else {
                    assert_eq!(got.expand().pixels, m.pixels, "kept whole, r = {r}");
                }
                // The compact form of the eroded mask gives its own box and runs back.
                let again = CompactMask::new(&got.expand());
                assert_eq!(
                    (again.runs.clone(), again.bbox_xywh),
                    (got.runs.clone(), got.bbox_xywh)
                );
            }
        }
    }

    #[test]
    fn compact_and_byte_masks_erode_alike_and_keep_their_scores() {
        let mut m = mask(25, 18, |x, y| (x + y) % 7 != 0 && x > 2 && y < 15);
        m.predicted_iou = 0.9;
        m.stability_score = 0.8;
        let a = erode_mask(&m, 1);
        let b = erode_mask(&CompactMask::new(&m), 1);
        assert_eq!(a, b);
        assert_eq!((a.predicted_iou, a.stability_score), (0.9, 0.8));
    }

    #[test]
    fn stage_labels_at_radius_0_are_the_overlap_labels_and_eroded_borders_credit_no_mask() {
        use crate::aggregate::{ImageStageParams, MaskOverlap, overlap_labels, stage_labels};
        // A floor (rows 15..) and an object above it, the object's mask also covering the
        // floor's top rows 15..21 (overlapping masks), at the raster size and at half of it.
        let floor = mask(40, 30, |_, y| y >= 15);
        let object = mask(40, 30, |x, y| (10..20).contains(&x) && (5..22).contains(&y));
        let masks = [floor, object];
        for overlap in [MaskOverlap::All, MaskOverlap::Finest] {
            for (w, h) in [(40, 30), (20, 15)] {
                let params = ImageStageParams {
                    overlap,
                    ..ImageStageParams::default()
                };
                assert_eq!(
                    stage_labels(&masks, w, h, params),
                    overlap_labels(&masks, w, h, overlap)
                );
            }
        }
        let params = ImageStageParams {
            overlap: MaskOverlap::Finest,
            mask_erode: 2,
            ..ImageStageParams::default()
        };
        let l = stage_labels(&masks, 40, 30, params);
        let at = |x: usize, y: usize| l.masks_of[l.labels[y * 40 + x] as usize].clone();
        // The floor's top rows 15, 16 and the object's border credit no mask...
        assert_eq!(at(30, 15), Vec::<u32>::new());
        assert_eq!(at(30, 16), Vec::<u32>::new());
        assert_eq!(at(10, 10), Vec::<u32>::new());
        // ...inside stays, and so does the floor along the image's edges.
        assert_eq!(at(30, 17), vec![0]);
        assert_eq!(at(0, 29), vec![0]);
        assert_eq!(at(39, 20), vec![0]);
        assert_eq!(at(15, 10), vec![1]);
        // Where both whole masks hold a pixel the object (the finest) has it while its eroded
        // mask holds it; in the object's eroded bottom rows it credits no mask rather than the
        // floor beneath (erosion only drops masks)...
        assert_eq!(at(15, 16), vec![1]);
        assert_eq!(at(15, 19), vec![1]);
        assert_eq!(at(15, 21), Vec::<u32>::new());
        // ...and under the paper's rule (every covering mask) the floor keeps it.
        let all = ImageStageParams {
            overlap: MaskOverlap::All,
            ..params
        };
        let l = stage_labels(&masks, 40, 30, all);
        let at = |x: usize, y: usize| l.masks_of[l.labels[y * 40 + x] as usize].clone();
        assert_eq!(at(15, 21), vec![0]);
        assert_eq!(at(15, 19), vec![0, 1]);
        assert_eq!(at(30, 16), Vec::<u32>::new());
    }
}
