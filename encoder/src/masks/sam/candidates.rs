//! Candidate masks: the full-resolution pixels of one decoder output that passed the score
//! filters, bit-packed with their box, area and scores, and the greedy box NMS that picks the
//! masks kept among them.

use super::params::SamParams;

/// A candidate mask that passed the score filters, kept bit-packed until NMS.
pub(super) struct Candidate {
    pub(super) bits: Vec<u64>,
    /// xyxy, inclusive max.
    pub(super) bbox: [u32; 4],
    pub(super) area: u32,
    pub(super) iou: f32,
    pub(super) stability: f32,
    pub(super) point: [f64; 2],
    /// Multimask output channel (1..=3) that produced the candidate.
    pub(super) channel: u8,
}

/// One full-resolution logit map (`H × W`, row-major) → a candidate, or `None` when its stability
/// score fails the filter (segment_anything's `calculate_stability_score`, mask, box).
pub(super) fn candidate(
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
pub(super) fn stability_score(inter: u32, union: u32, p: &SamParams) -> Option<f32> {
    // torch: int32 / int32 -> f32; 0 / 0 = NaN fails the `>=` filter like SAM's.
    let stability = inter as f32 / union as f32;
    (!stability.is_nan() && stability >= p.stability_score_thresh).then_some(stability)
}

/// A candidate's mask as its pixels are found: its bits (row-major, `w` per row), its box and
/// its area.
pub(super) struct MaskPixels {
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
    pub(super) fn new(w: usize, pixels: usize) -> Self {
        MaskPixels {
            w,
            bits: vec![0u64; pixels.div_ceil(64)],
            x: [u32::MAX, 0],
            y: [u32::MAX, 0],
            area: 0,
        }
    }

    /// Pixels `xa..xb` (`xa < xb`) of row `y` are inside the mask.
    pub(super) fn run(&mut self, xa: usize, xb: usize, y: usize) {
        set_bits(&mut self.bits, y * self.w + xa, xb - xa);
        self.x = [self.x[0].min(xa as u32), self.x[1].max((xb - 1) as u32)];
        self.y = [self.y[0].min(y as u32), self.y[1].max(y as u32)];
        self.area += (xb - xa) as u32;
    }

    /// The candidate of this mask with its scores, from multimask output `channel`.
    pub(super) fn candidate(
        self,
        iou: f32,
        stability: f32,
        point: [f64; 2],
        channel: usize,
    ) -> Candidate {
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

/// Sets bits `start..start + len` of a row-major bitset.
pub(super) fn set_bits(bits: &mut [u64], start: usize, len: usize) {
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
pub(super) fn nms(cands: &[Candidate], iou_thresh: f32) -> Vec<usize> {
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
