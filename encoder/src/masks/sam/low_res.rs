//! The decoder's low-resolution logits (`low_res_masks`, 256 × 256 per prompt and channel):
//! their layout ([`LowResLogits`]) and `SamOnnxModel.mask_postprocessing` done on the host
//! ([`LowResUpsampler`]), deciding whole blocks of full-resolution pixels from their taps.

use std::ops::Range;

use ort::value::DynValue;

use super::candidates::{Candidate, MaskPixels, candidate, stability_score};
use super::params::SamParams;
use crate::preprocess::SAM_IMAGE_SIZE;

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
    pub(super) fn channels(self) -> usize {
        match self {
            LowResLogits::F32AllChannels => 4,
            LowResLogits::F16Multimask => 3,
        }
    }
    /// Index of multimask channel `c` (1..=3) of prompt `i` in the output's map order.
    pub(super) fn map_index(self, i: usize, c: usize) -> usize {
        match self {
            LowResLogits::F32AllChannels => i * 4 + c,
            LowResLogits::F16Multimask => i * 3 + c - 1,
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
pub(super) enum LowResMaps<'a> {
    F32(&'a [f32]),
    F16(&'a [half::f16]),
}

impl<'a> LowResMaps<'a> {
    /// The maps of `value` for `n` prompts laid out as `layout`; the message says what differs.
    pub(super) fn extract(
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
    pub(super) fn map<'s>(&'s self, k: usize, scratch: &'s mut Vec<f32>) -> &'s [f32] {
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
pub(super) struct CandidateScratch {
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
    pub(super) fn scratch(&self) -> CandidateScratch {
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
    pub(super) fn candidate(
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
