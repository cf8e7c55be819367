//! The image stage of one view: pixels grouped by the set of masks covering them (signatures),
//! `a_kj = Σ_{p∈M_j} w_kp` summed per (Gaussian, signature) in f64 and expanded to every mask of the
//! signature, then optionally re-weighted per mask (SLAG Sec. III, "Parameter masking").

use rayon::prelude::*;
use rustc_hash::FxHashMap;
use slag_common::{Error, Result};

use super::image_mask::ImageMask;
use crate::masks::Mask;
use crate::raster::{LabelSums, PixelWeights};

/// One non-zero `a_kj` of an image: Gaussian `gaussian` received total blend weight `weight`
/// (units: pixels at the raster resolution) inside mask `mask`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Entry {
    /// Gaussian index (source `.ply` order).
    pub gaussian: u32,
    /// Mask index within the image.
    pub mask: u32,
    /// `a_kj = Σ_{p∈M_j} w_kp`.
    pub weight: f32,
}

/// Test shorthand: `(gaussian, mask, weight)` triples as [`Entry`]s, in the order given.
#[cfg(test)]
pub(crate) fn entries(triples: &[(u32, u32, f32)]) -> Vec<Entry> {
    triples
        .iter()
        .map(|&(gaussian, mask, weight)| Entry {
            gaussian,
            mask,
            weight,
        })
        .collect()
}

/// Everything one image contributes to the reduction.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ImageContribution {
    /// Embedding width D.
    pub dim: usize,
    /// `[M * D]` mask embeddings `E_j` (L2-normalised CLIP crop embeddings).
    pub mask_embeddings: Vec<f32>,
    /// Non-zero `a_kj`, sorted by (gaussian, mask), no duplicates.
    pub entries: Vec<Entry>,
}

impl ImageContribution {
    /// Bytes held in memory.
    pub fn bytes(&self) -> usize {
        self.mask_embeddings.len() * 4 + self.entries.len() * std::mem::size_of::<Entry>()
    }
}

/// Knobs of the image stage. `Default` is the paper's rule (all contributors, no weighting,
/// every covering mask); `slag-encoder encode`'s default is `--overlap finest` (better
/// held-out mIoU at the same cost, docs/results/tradeoffs.md).
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize)]
pub struct ImageStageParams {
    /// Keep only the `k` largest-weight contributors of each pixel (`None` = all, the paper's rule).
    pub top_k_per_pixel: Option<usize>,
    /// Specificity weighting of each mask's `a_kj` (default: none, the paper's rule).
    pub mask_weighting: MaskWeighting,
    /// Which of the masks covering a pixel receive its weights (default: all, the paper's
    /// rule; [`MaskOverlap`]).
    pub overlap: MaskOverlap,
    /// Erode every mask by this many image pixels before its pixels credit it (default 0: the
    /// whole mask, the paper's rule; [`crate::aggregate::erode`]): a mask's border pixels then
    /// credit only the masks that still hold them after erosion, or none. The CLIP crop is not
    /// affected.
    pub mask_erode: u32,
}

/// How a pixel covered by several masks contributes (`encode --overlap`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MaskOverlap {
    /// To every mask that covers it (the paper's `a_kj = Σ_{p∈M_j} w_kp`).
    #[default]
    All,
    /// Only to the smallest covering mask (fewest pixels; ties: the lower mask index).
    Finest,
}

/// Restricts every pixel label's mask set to its smallest mask ([`MaskOverlap::Finest`]).
///
/// `masks_of[s]` lists the masks covering the pixels of label `s` (as
/// [`crate::aggregate::PixelLabels`] holds them); afterwards each non-empty set holds exactly one
/// mask: the one of least [`Mask::area`] (ties: the lower index). Mask indices outside `masks`
/// are dropped.
pub fn restrict_to_finest<M: ImageMask>(masks_of: &mut [Vec<u32>], masks: &[M]) {
    for set in masks_of.iter_mut() {
        let finest = set
            .iter()
            .copied()
            .filter_map(|j| masks.get(j as usize).map(|m| (m.area(), j)))
            .min();
        set.clear();
        if let Some((_, j)) = finest {
            set.push(j);
        }
    }
}

/// Specificity weighting of the image stage (`encode --mask-weighting`): every `a_kj` of mask `j`
/// is multiplied by a factor `g_j` before the reduction, so that
/// `E_k = Σ g_j a_kj E_j / Σ g_j a_kj` (and the stored total weight is `Σ g_j a_kj`). Training
/// free and single pass: `g_j` depends only on the mask.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MaskWeighting {
    /// `g_j = 1`: the paper's mean.
    #[default]
    None,
    /// `g_j = image pixels / mask area` (≥ 1): small, specific masks (parts) outweigh large
    /// ones (wholes, background) covering the same Gaussian.
    Area,
    /// `g_j = SAM predicted IoU × stability score` (both 1 for generators without scores, e.g.
    /// the graph segmenter): confident masks outweigh doubtful ones.
    SamScore,
}

impl MaskWeighting {
    /// The factor `g_j` of `mask` (finite, > 0; non-finite or non-positive SAM scores give
    /// `f32::MIN_POSITIVE`).
    pub fn factor(self, mask: &impl ImageMask) -> f32 {
        match self {
            MaskWeighting::None => 1.0,
            MaskWeighting::Area => {
                let (w, h) = mask.size();
                (w as f64 * h as f64 / mask.area().max(1) as f64) as f32
            }
            MaskWeighting::SamScore => {
                let (iou, stability) = mask.scores();
                let g = iou * stability;
                if g.is_finite() && g > 0.0 {
                    g
                } else {
                    f32::MIN_POSITIVE
                }
            }
        }
    }
}

/// Multiplies every entry's `a_kj` by its mask's [`MaskWeighting::factor`].
pub(crate) fn weight_entries(entries: &mut [Entry], masks: &[Mask], weighting: MaskWeighting) {
    apply_mask_factors(entries, &mask_factors(masks, weighting));
}

/// Every mask's [`MaskWeighting::factor`] (`[M]`), or nothing for [`MaskWeighting::None`].
pub(crate) fn mask_factors<M: ImageMask>(masks: &[M], weighting: MaskWeighting) -> Vec<f32> {
    if weighting == MaskWeighting::None {
        return Vec::new();
    }
    masks.iter().map(|m| weighting.factor(m)).collect()
}

/// Multiplies every entry's `a_kj` by `factors[mask]` ([`mask_factors`]; empty: unchanged).
pub(crate) fn apply_mask_factors(entries: &mut [Entry], factors: &[f32]) {
    if factors.is_empty() {
        return;
    }
    for e in entries {
        if let Some(&f) = factors.get(e.mask as usize) {
            e.weight *= f;
        }
    }
}

/// Resamples full-resolution masks onto the raster grid (`width` x `height`) by nearest sampling at
/// raster pixel centres, and returns per-pixel mask-membership bitsets (`words` u64 per pixel).
fn membership<M: ImageMask>(masks: &[M], width: u32, height: u32) -> (usize, Vec<u64>) {
    let words = masks.len().div_ceil(64).max(1);
    let mut bits = vec![0u64; width as usize * height as usize * words];
    bits.par_chunks_mut(width as usize * words)
        .enumerate()
        .for_each(|(y, row)| {
            for (j, m) in masks.iter().enumerate() {
                let (mw, mh) = m.size();
                let sy = (((y as f64 + 0.5) * mh as f64 / height as f64) as u32).min(mh - 1);
                let [bx, by, bw, bh] = m.bbox_xywh();
                if sy < by || sy > by + bh {
                    continue;
                }
                // Raster columns whose centre can sample inside the bbox.
                let x0 = ((bx as f64 * width as f64 / mw as f64) - 1.0).max(0.0) as usize;
                let x1 = ((((bx + bw + 1) as f64) * width as f64 / mw as f64).ceil() as usize + 1)
                    .min(width as usize);
                let cols = (x0..x1)
                    .map(|x| {
                        let sx = (((x as f64 + 0.5) * mw as f64 / width as f64) as u32).min(mw - 1);
                        (x, sx)
                    })
                    .filter(|&(_, sx)| sx >= bx && sx <= bx + bw);
                m.row_hits(sy, cols, |x| row[x * words + j / 64] |= 1u64 << (j % 64));
            }
        });
    (words, bits)
}

/// Every raster pixel's *label*: the id of the distinct set of masks covering it (its
/// signature; 0 = no mask), so that `a_kj = Σ_{s ∋ j} Σ_{p: label(p) = s} w_kp`: the image stage
/// sums weights per (Gaussian, label) — on the host or on the GPU
/// ([`WeightRasterizer::label_sums`]) — and expands labels to masks once per image.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PixelLabels {
    /// `[height × width]` row-major label of each raster pixel.
    pub labels: Vec<u32>,
    /// `masks_of[s]`: the mask indices of label `s` (ascending; `masks_of[0]` is empty).
    pub masks_of: Vec<Vec<u32>>,
}

impl PixelLabels {
    /// The same labelling with labels of equal mask sets merged into one (numbered in label
    /// order; a label of no mask becomes 0), so that every label stands for a distinct set. The
    /// `a_kj` are the same sums over the same pixels; under [`MaskOverlap::Finest`] (every set one
    /// mask) there is then one label per mask that owns a pixel, instead of one per signature:
    /// fewer labels per tile and fewer (Gaussian, label) sums on the device. Labels from
    /// [`pixel_labels`] alone are distinct sets already and come back unchanged.
    pub fn merged(self) -> PixelLabels {
        let PixelLabels {
            mut labels,
            masks_of: sets,
        } = self;
        let mut remap = vec![0u32; sets.len()];
        let mut ids: FxHashMap<&[u32], u32> = FxHashMap::default();
        let mut masks_of = vec![Vec::new()];
        for (s, set) in sets.iter().enumerate().skip(1) {
            if set.is_empty() {
                continue;
            }
            remap[s] = *ids
                .entry(set.as_slice())
                .or_insert_with(|| new_label(&mut masks_of, set.clone()));
        }
        labels
            .par_iter_mut()
            .for_each(|l| *l = remap.get(*l as usize).copied().unwrap_or(0));
        PixelLabels { labels, masks_of }
    }
}

/// Appends the mask set `set` to `masks_of` as a new label and returns that label; an empty set
/// gets none and is label 0 (no mask).
fn new_label(masks_of: &mut Vec<Vec<u32>>, set: Vec<u32>) -> u32 {
    if set.is_empty() {
        return 0;
    }
    masks_of.push(set);
    (masks_of.len() - 1) as u32
}

/// The labels of the raster grid `width × height` for full-resolution `masks` (nearest sampling
/// at raster pixel centres, as [`image_contribution`] does). Labels are numbered in row-major
/// order of first appearance, so they are deterministic.
pub fn pixel_labels<M: ImageMask>(masks: &[M], width: u32, height: u32) -> PixelLabels {
    if masks.is_empty() || width == 0 || height == 0 {
        return PixelLabels {
            labels: vec![0; width as usize * height as usize],
            masks_of: vec![Vec::new()],
        };
    }
    let (words, bits) = membership(masks, width, height);
    let mut sig_of: FxHashMap<&[u64], u32> = FxHashMap::default();
    let mut masks_of: Vec<Vec<u32>> = vec![Vec::new()];
    let labels = bits
        .chunks_exact(words)
        .map(|set| {
            if set.iter().all(|&b| b == 0) {
                return 0;
            }
            *sig_of.entry(set).or_insert_with(|| {
                let members = (0..masks.len() as u32)
                    .filter(|&j| set[j as usize / 64] >> (j % 64) & 1 == 1)
                    .collect();
                new_label(&mut masks_of, members)
            })
        })
        .collect();
    PixelLabels { labels, masks_of }
}

/// [`pixel_labels`] under the overlap rule: with [`MaskOverlap::Finest`] each label's mask set
/// is cut to its finest mask ([`restrict_to_finest`]); with [`MaskOverlap::All`] it is kept whole.
/// The one place the rule is applied, for the host image stage ([`image_contribution`]) and for
/// labels summed on the rasterizer's device alike.
pub fn overlap_labels<M: ImageMask>(
    masks: &[M],
    width: u32,
    height: u32,
    overlap: MaskOverlap,
) -> PixelLabels {
    let mut labels = pixel_labels(masks, width, height);
    if overlap == MaskOverlap::Finest {
        restrict_to_finest(&mut labels.masks_of, masks);
    }
    labels
}

/// The pixel labels the image stage sums over under `params`: [`overlap_labels`] of the whole
/// masks, each pixel then keeping only those of its masks that still hold it once eroded by
/// [`ImageStageParams::mask_erode`] ([`crate::aggregate::erode::erode_all`]). Erosion only ever
/// drops a pixel's masks: under [`MaskOverlap::Finest`] a pixel in the eroded border of its
/// finest mask credits no mask, rather than the larger mask beneath it. At 0 these are
/// [`overlap_labels`] of `masks`. Used by the host image stage and for the labels summed on the
/// rasterizer's device alike.
pub fn stage_labels<M: ImageMask>(
    masks: &[M],
    width: u32,
    height: u32,
    params: ImageStageParams,
) -> PixelLabels {
    let whole = overlap_labels(masks, width, height, params.overlap);
    if params.mask_erode == 0 || masks.is_empty() {
        return whole;
    }
    let eroded = pixel_labels(
        &super::erode::erode_all(masks, params.mask_erode),
        width,
        height,
    );
    // One label per (whole, eroded) pair met, numbered in row-major order of first appearance;
    // 0 where no mask is left.
    let mut ids: FxHashMap<(u32, u32), u32> = FxHashMap::default();
    let mut masks_of: Vec<Vec<u32>> = vec![Vec::new()];
    let labels = whole
        .labels
        .iter()
        .zip(&eroded.labels)
        .map(|(&a, &b)| {
            *ids.entry((a, b)).or_insert_with(|| {
                let held = &eroded.masks_of[b as usize];
                let set: Vec<u32> = whole.masks_of[a as usize]
                    .iter()
                    .copied()
                    .filter(|j| held.binary_search(j).is_ok())
                    .collect();
                new_label(&mut masks_of, set)
            })
        })
        .collect();
    PixelLabels { labels, masks_of }
}

/// Checks the image stage's inputs: one embedding of width `dim` per mask, masks of one size.
pub(crate) fn check_image_inputs<M: ImageMask>(
    masks: &[M],
    mask_embeddings: &[f32],
    dim: usize,
) -> Result<()> {
    if mask_embeddings.len() != masks.len() * dim {
        return Err(Error::internal(format!(
            "{} masks but {} embedding values for dim {dim}",
            masks.len(),
            mask_embeddings.len()
        )));
    }
    if let Some(m) = masks.iter().find(|m| m.size() != masks[0].size()) {
        let ((w, h), (w0, h0)) = (m.size(), masks[0].size());
        return Err(Error::mismatch(
            slag_common::Mismatched::ImageSize,
            format!("masks of one image differ in size ({w}x{h} vs {w0}x{h0})"),
        ));
    }
    Ok(())
}

/// `a_kj` from per-(Gaussian, label) sums sorted by (Gaussian, label), one per key:
/// `a_kj = Σ_{s ∋ j} sum_ks`, added in label order (deterministic), zero sums dropped; sorted by
/// (Gaussian, mask). `sum_of(&sums[i])` gives the i-th `(Gaussian, label, sum)`.
///
/// Every Gaussian's labels expand into a small per-Gaussian list, so there is no image-wide
/// table; runs of whole Gaussians are expanded in parallel and joined in order, so the result
/// does not depend on the number of threads.
pub(crate) fn expand_labels<T: Sync>(
    sums: &[T],
    sum_of: impl Fn(&T) -> (u32, u32, f64) + Sync,
    masks_of: &[Vec<u32>],
) -> Vec<Entry> {
    // Chunk starts at Gaussian boundaries, about 64k sums each.
    const CHUNK: usize = 1 << 16;
    let gaussian = |i: usize| sum_of(&sums[i]).0;
    let mut starts = vec![0usize];
    let mut at = CHUNK;
    while at < sums.len() {
        let g = gaussian(at - 1);
        while at < sums.len() && gaussian(at) == g {
            at += 1;
        }
        if at < sums.len() {
            starts.push(at);
        }
        at += CHUNK;
    }
    starts.push(sums.len());
    let parts: Vec<Vec<Entry>> = starts
        .par_windows(2)
        .map(|w| {
            let mut out = Vec::with_capacity(w[1] - w[0]);
            let mut per_mask: Vec<(u32, f64)> = Vec::new();
            let mut i = w[0];
            while i < w[1] {
                let k = gaussian(i);
                per_mask.clear();
                while i < w[1] && gaussian(i) == k {
                    let (_, s, v) = sum_of(&sums[i]);
                    for &j in masks_of.get(s as usize).map_or(&[][..], Vec::as_slice) {
                        per_mask.push((j, v));
                    }
                    i += 1;
                }
                // Stable: one mask's terms keep their label order.
                per_mask.sort_by_key(|&(j, _)| j);
                for run in per_mask.chunk_by(|a, b| a.0 == b.0) {
                    let a = run.iter().fold(0.0f64, |acc, &(_, v)| acc + v);
                    if a > 0.0 {
                        out.push(Entry {
                            gaussian: k,
                            mask: run[0].0,
                            weight: a as f32,
                        });
                    }
                }
            }
            out
        })
        .collect();
    parts.concat()
}

/// `a_kj` from a rasterizer's label-sum records ([`LabelSums::records`]: any order, a key
/// repeated once per tile): the records are sorted and the sums of one key added (exact
/// integers, [`LabelSums::reduced`]), then expanded as [`expand_labels`] does.
pub(crate) fn expand_label_records(sums: LabelSums, masks_of: &[Vec<u32>]) -> Vec<Entry> {
    let records = sums.reduced();
    expand_labels(&records, |r| (r.gaussian, r.label, r.weight()), masks_of)
}

/// The image stage: `a_kj = Σ_{p∈M_j} w_kp` for every Gaussian k and mask j of one image.
///
/// `weights` is the raster output at any resolution; `masks` are at the image's full resolution
/// (all the same size) and are resampled to the raster grid. `mask_embeddings` is `[M * dim]`.
/// Errors: mask/embedding count mismatch, masks of different sizes.
pub fn image_contribution(
    weights: &PixelWeights,
    masks: &[Mask],
    mask_embeddings: Vec<f32>,
    dim: usize,
    params: ImageStageParams,
) -> Result<ImageContribution> {
    check_image_inputs(masks, &mask_embeddings, dim)?;
    let (w, h) = (weights.width, weights.height);
    if masks.is_empty() || w == 0 || h == 0 {
        return Ok(ImageContribution {
            dim,
            mask_embeddings,
            entries: Vec::new(),
        });
    }
    let PixelLabels {
        labels: pixel_sig,
        masks_of,
    } = stage_labels(masks, w, h, params);

    // Σ_p w_kp per (Gaussian, label), row bands in parallel, f64 sums.
    let band = (h as usize)
        .div_ceil(rayon::current_num_threads() * 4)
        .max(1);
    let partial: Vec<FxHashMap<u64, f64>> = (0..h as usize)
        .step_by(band)
        .collect::<Vec<_>>()
        .into_par_iter()
        .map(|y0| {
            let mut acc: FxHashMap<u64, f64> = FxHashMap::default();
            let mut scratch: Vec<(u32, f32)> = Vec::new();
            for y in y0..(y0 + band).min(h as usize) {
                for x in 0..w as usize {
                    let p = y * w as usize + x;
                    let s = pixel_sig[p];
                    if s == 0 {
                        continue;
                    }
                    let (a, b) = (weights.offsets[p] as usize, weights.offsets[p + 1] as usize);
                    let ids = &weights.ids[a..b];
                    let ws = &weights.weights[a..b];
                    let mut add = |k: u32, wk: f32| {
                        *acc.entry(((k as u64) << 32) | s as u64).or_insert(0.0) += wk as f64;
                    };
                    match params.top_k_per_pixel {
                        Some(k) if ids.len() > k => {
                            scratch.clear();
                            scratch.extend(ids.iter().copied().zip(ws.iter().copied()));
                            scratch.select_nth_unstable_by(k - 1, |l, r| r.1.total_cmp(&l.1));
                            scratch[..k].iter().for_each(|&(g, wk)| add(g, wk));
                        }
                        _ => ids.iter().zip(ws).for_each(|(&g, &wk)| add(g, wk)),
                    }
                }
            }
            acc
        })
        .collect();
    let mut merged: FxHashMap<u64, f64> = FxHashMap::default();
    for part in partial {
        for (key, v) in part {
            *merged.entry(key).or_insert(0.0) += v;
        }
    }
    let mut sums: Vec<(u64, f64)> = merged.into_iter().collect();
    sums.par_sort_unstable_by_key(|e| e.0);
    let mut entries = expand_labels(
        &sums,
        |&(key, v)| ((key >> 32) as u32, key as u32, v),
        &masks_of,
    );
    weight_entries(&mut entries, masks, params.mask_weighting);
    Ok(ImageContribution {
        dim,
        mask_embeddings,
        entries,
    })
}

#[cfg(test)]
mod expand_tests {
    use std::collections::BTreeMap;

    use super::*;
    use crate::masks::compact::CompactMask;
    use crate::raster::LabelSum;

    /// A small deterministic generator (xorshift), so the test needs no seed crate.
    fn next(state: &mut u64) -> u64 {
        *state ^= *state << 13;
        *state ^= *state >> 7;
        *state ^= *state << 17;
        *state
    }

    /// Label-sum records in shuffled order, keys repeated (as the GPU's per-tile records are),
    /// over enough Gaussians that the expansion runs in several parallel chunks, against a
    /// sequential reference: per (Gaussian, mask), the f64 sums of the reduced label sums added
    /// in label order.
    #[test]
    fn label_records_expand_like_the_sequential_reference_in_any_order() {
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        // Labels 1..=40 over 12 masks, each label a set of 1–3 masks (overlapping masks).
        let mut masks_of = vec![Vec::new()];
        for _ in 0..40 {
            let mut set: Vec<u32> = (0..1 + next(&mut state) % 3)
                .map(|_| (next(&mut state) % 12) as u32)
                .collect();
            set.sort_unstable();
            set.dedup();
            masks_of.push(set);
        }
        let mut records = Vec::new();
        for gaussian in 0..60_000u32 {
            for _ in 0..next(&mut state) % 5 {
                let label = 1 + (next(&mut state) % 40) as u32;
                // 1–3 records of the key, some with a zero sum.
                for _ in 0..1 + next(&mut state) % 3 {
                    let sum = if next(&mut state).is_multiple_of(7) {
                        0
                    } else {
                        next(&mut state) % (1 << 36)
                    };
                    records.push(LabelSum {
                        gaussian,
                        label,
                        sum,
                    });
                }
            }
        }
        assert!(records.len() > 2 * (1 << 16), "several chunks");
        // Reference: exact integer sums per key, then masks in (Gaussian, label) order.
        let mut per_key: BTreeMap<(u32, u32), u64> = BTreeMap::new();
        for r in &records {
            *per_key.entry((r.gaussian, r.label)).or_insert(0) += r.sum;
        }
        let mut per_kj: BTreeMap<(u32, u32), f64> = BTreeMap::new();
        for (&(k, s), &sum) in &per_key {
            let v = sum as f64 / 4_294_967_296.0;
            for &j in &masks_of[s as usize] {
                *per_kj.entry((k, j)).or_insert(0.0) += v;
            }
        }
        let expected: Vec<Entry> = per_kj
            .into_iter()
            .filter(|&(_, v)| v > 0.0)
            .map(|((gaussian, mask), v)| Entry {
                gaussian,
                mask,
                weight: v as f32,
            })
            .collect();
        // Shuffle (Fisher–Yates) so that the order the records arrive in is arbitrary.
        for i in (1..records.len()).rev() {
            records.swap(i, (next(&mut state) % (i as u64 + 1)) as usize);
        }
        let sums = LabelSums {
            records,
            contributions: 0,
            sorted: false,
        };
        let got = expand_label_records(sums, &masks_of);
        assert_eq!(got.len(), expected.len());
        for (g, e) in got.iter().zip(&expected) {
            assert_eq!((g.gaussian, g.mask), (e.gaussian, e.mask));
            assert_eq!(g.weight.to_bits(), e.weight.to_bits(), "{g:?} vs {e:?}");
        }
    }

    /// A `w × h` mask of the box `[x0, y0, width, height]` (pixels, clipped to the image).
    fn box_mask(w: u32, h: u32, [x0, y0, mw, mh]: [u32; 4]) -> Mask {
        let pixels = (0..w * h)
            .map(|p| u8::from((x0..x0 + mw).contains(&(p % w)) && (y0..y0 + mh).contains(&(p / w))))
            .collect();
        Mask::from_pixels(w, h, pixels).expect("non-empty box")
    }

    /// `count` [`box_mask`]s of `w × h` drawn from the generator seeded with `seed`, each at a
    /// random corner `(x0, y0)` with `x0 < at[0]`, `y0 < at[1]`, of random size
    /// `(min + r % span[0], min + r % span[1])`.
    fn random_boxes(
        seed: u64,
        count: usize,
        [w, h]: [u32; 2],
        at: [u64; 2],
        min: u32,
        span: [u64; 2],
    ) -> Vec<Mask> {
        let mut state = seed;
        (0..count)
            .map(|_| {
                let (x0, y0) = (
                    (next(&mut state) % at[0]) as u32,
                    (next(&mut state) % at[1]) as u32,
                );
                let (mw, mh) = (
                    min + (next(&mut state) % span[0]) as u32,
                    min + (next(&mut state) % span[1]) as u32,
                );
                box_mask(w, h, [x0, y0, mw, mh])
            })
            .collect()
    }

    /// Pixel labels against a sequential reference at the masks' own size (each pixel's set is
    /// the masks covering it; labels numbered by row-major first appearance).
    #[test]
    fn pixel_labels_number_sets_in_row_major_order_of_first_appearance() {
        let (w, h) = (37u32, 301u32);
        let masks = random_boxes(0x0dd5_eed5_1234_5678, 70, [w, h], [30, 290], 1, [12, 60]);
        let mut ids: std::collections::HashMap<Vec<u32>, u32> = Default::default();
        let mut masks_of = vec![Vec::new()];
        let labels: Vec<u32> = (0..(w * h) as usize)
            .map(|p| {
                let set: Vec<u32> = (0..masks.len() as u32)
                    .filter(|&j| masks[j as usize].pixels[p] != 0)
                    .collect();
                if set.is_empty() {
                    return 0;
                }
                *ids.entry(set.clone())
                    .or_insert_with(|| new_label(&mut masks_of, set))
            })
            .collect();
        assert!(masks_of.len() > 50, "many distinct sets");
        assert_eq!(pixel_labels(&masks, w, h), PixelLabels { labels, masks_of });
    }

    /// Merged labels cover every pixel with the same mask set as before, no two labels share a
    /// set, and under the finest rule there is one label per mask that owns a pixel.
    #[test]
    fn merged_labels_keep_each_pixels_masks_and_number_the_distinct_sets() {
        let (w, h) = (64u32, 48u32);
        let masks = random_boxes(0x51ed_270b_c0ff_ee11, 30, [w, h], [56, 40], 2, [30, 30]);
        for overlap in [MaskOverlap::All, MaskOverlap::Finest] {
            let labels = overlap_labels(&masks, w, h, overlap);
            let merged = labels.clone().merged();
            assert_eq!(merged.labels.len(), labels.labels.len());
            for (m, l) in merged.labels.iter().zip(&labels.labels) {
                assert_eq!(
                    merged.masks_of[*m as usize], labels.masks_of[*l as usize],
                    "{overlap:?}"
                );
            }
            let distinct: std::collections::HashSet<&Vec<u32>> = merged.masks_of.iter().collect();
            assert_eq!(
                distinct.len(),
                merged.masks_of.len(),
                "{overlap:?}: sets repeat"
            );
            match overlap {
                // Signatures are distinct sets already.
                MaskOverlap::All => assert_eq!(merged, labels),
                MaskOverlap::Finest => {
                    let owners: std::collections::HashSet<u32> =
                        labels.masks_of.iter().flatten().copied().collect();
                    assert_eq!(merged.masks_of.len(), owners.len() + 1);
                    assert!(merged.masks_of.len() < labels.masks_of.len(), "some merged");
                }
            }
        }
    }

    /// No sums, or sums whose labels have no masks: no entries.
    #[test]
    fn empty_and_maskless_label_sums_give_no_entries() {
        let none: Vec<(u32, u32, f64)> = Vec::new();
        assert!(expand_labels(&none, |&t| t, &[Vec::new()]).is_empty());
        let maskless = [(3, 1, 0.5), (4, 2, 0.25)];
        assert!(expand_labels(&maskless, |&t| t, &[Vec::new(), Vec::new()]).is_empty());
    }

    /// Labels made from run-length masks equal those made from the expanded masks, at raster
    /// sizes below, at and above the masks' (odd sizes, masks touching the borders, overlaps),
    /// and so do the finest-mask rule and the weighting factors that read the same fields.
    #[test]
    fn compact_masks_label_like_expanded_masks() {
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let (w, h) = (97u32, 61u32);
        let masks: Vec<Mask> = (0..70)
            .map(|i| {
                let (cx, cy) = (
                    (next(&mut state) % 97) as i64,
                    (next(&mut state) % 61) as i64,
                );
                let r = 3 + (next(&mut state) % 30) as i64;
                let pixels = (0..h as i64)
                    .flat_map(|y| (0..w as i64).map(move |x| (x, y)))
                    .map(|(x, y)| {
                        // Discs, and every 5th mask a ring with holes in it.
                        let d = (x - cx).pow(2) + (y - cy).pow(2);
                        u8::from(d <= r * r && (i % 5 != 0 || d >= (r / 2).pow(2)))
                    })
                    .collect();
                let mut m = Mask::from_pixels(w, h, pixels).expect("non-empty disc");
                m.predicted_iou = 0.5 + (i as f32) / 200.0;
                m.stability_score = 0.9;
                m
            })
            .collect();
        let compact: Vec<CompactMask> = masks.iter().map(CompactMask::new).collect();
        for (rw, rh) in [(48, 30), (97, 61), (131, 90), (7, 5)] {
            for overlap in [MaskOverlap::All, MaskOverlap::Finest] {
                assert_eq!(
                    overlap_labels(&compact, rw, rh, overlap),
                    overlap_labels(&masks, rw, rh, overlap),
                    "{rw}x{rh} {overlap:?}"
                );
            }
        }
        for weighting in [MaskWeighting::Area, MaskWeighting::SamScore] {
            assert_eq!(
                mask_factors(&compact, weighting),
                mask_factors(&masks, weighting)
            );
        }
    }
}
