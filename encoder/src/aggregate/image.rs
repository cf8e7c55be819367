//! The image stage of one view: pixels grouped by the set of masks covering them (signatures),
//! `a_kj = Σ_{p∈M_j} w_kp` summed per (Gaussian, signature) in f64 and expanded to every mask of the
//! signature, then optionally re-weighted per mask (SLAG Sec. III, "Parameter masking").

use rayon::prelude::*;
use rustc_hash::FxHashMap;
use slag_common::{Error, Result};

use crate::masks::Mask;
use crate::raster::PixelWeights;

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
pub fn restrict_to_finest(masks_of: &mut [Vec<u32>], masks: &[Mask]) {
    for set in masks_of.iter_mut() {
        let finest = set
            .iter()
            .copied()
            .filter_map(|j| masks.get(j as usize).map(|m| (m.area, j)))
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
    pub fn factor(self, mask: &Mask) -> f32 {
        match self {
            MaskWeighting::None => 1.0,
            MaskWeighting::Area => {
                (mask.width as f64 * mask.height as f64 / mask.area.max(1) as f64) as f32
            }
            MaskWeighting::SamScore => {
                let g = mask.predicted_iou * mask.stability_score;
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
    if weighting == MaskWeighting::None {
        return;
    }
    let g: Vec<f32> = masks.iter().map(|m| weighting.factor(m)).collect();
    for e in entries {
        if let Some(&f) = g.get(e.mask as usize) {
            e.weight *= f;
        }
    }
}

/// Resamples full-resolution masks onto the raster grid (`width` x `height`) by nearest sampling at
/// raster pixel centres, and returns per-pixel mask-membership bitsets (`words` u64 per pixel).
fn membership(masks: &[Mask], width: u32, height: u32) -> (usize, Vec<u64>) {
    let words = masks.len().div_ceil(64).max(1);
    let mut bits = vec![0u64; width as usize * height as usize * words];
    bits.par_chunks_mut(width as usize * words)
        .enumerate()
        .for_each(|(y, row)| {
            for (j, m) in masks.iter().enumerate() {
                let sy =
                    (((y as f64 + 0.5) * m.height as f64 / height as f64) as u32).min(m.height - 1);
                let [bx, by, bw, bh] = m.bbox_xywh;
                if sy < by || sy > by + bh {
                    continue;
                }
                // Raster columns whose centre can sample inside the bbox.
                let x0 = ((bx as f64 * width as f64 / m.width as f64) - 1.0).max(0.0) as usize;
                let x1 = ((((bx + bw + 1) as f64) * width as f64 / m.width as f64).ceil() as usize
                    + 1)
                .min(width as usize);
                for x in x0..x1 {
                    let sx = (((x as f64 + 0.5) * m.width as f64 / width as f64) as u32)
                        .min(m.width - 1);
                    if sx >= bx && sx <= bx + bw && m.pixels[(sy * m.width + sx) as usize] != 0 {
                        row[x * words + j / 64] |= 1u64 << (j % 64);
                    }
                }
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

/// The labels of the raster grid `width × height` for full-resolution `masks` (nearest sampling
/// at raster pixel centres, as [`image_contribution`] does). Labels are numbered in row-major
/// order of first appearance, so they are deterministic.
pub fn pixel_labels(masks: &[Mask], width: u32, height: u32) -> PixelLabels {
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
                masks_of.push(members);
                (masks_of.len() - 1) as u32
            })
        })
        .collect();
    PixelLabels { labels, masks_of }
}

/// [`pixel_labels`] under the overlap rule: with [`MaskOverlap::Finest`] each label's mask set
/// is cut to its finest mask ([`restrict_to_finest`]); with [`MaskOverlap::All`] it is kept whole.
/// The one place the rule is applied, for the host image stage ([`image_contribution`]) and for
/// labels summed on the rasterizer's device alike.
pub fn overlap_labels(
    masks: &[Mask],
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

/// Checks the image stage's inputs: one embedding of width `dim` per mask, masks of one size.
pub(crate) fn check_image_inputs(
    masks: &[Mask],
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
    if let Some(m) = masks
        .iter()
        .find(|m| (m.width, m.height) != (masks[0].width, masks[0].height))
    {
        return Err(Error::mismatch(
            slag_common::Mismatched::ImageSize,
            format!(
                "masks of one image differ in size ({}x{} vs {}x{})",
                m.width, m.height, masks[0].width, masks[0].height
            ),
        ));
    }
    Ok(())
}

/// `a_kj` from per-(Gaussian, label) sums sorted by (Gaussian, label): `a_kj = Σ_{s ∋ j} sum_ks`,
/// added in that order (deterministic), zero sums dropped; sorted by (Gaussian, mask).
pub(crate) fn expand_labels(
    sums: impl IntoIterator<Item = (u32, u32, f64)>,
    masks_of: &[Vec<u32>],
) -> Vec<Entry> {
    let mut per_kj: FxHashMap<u64, f64> = FxHashMap::default();
    for (k, s, v) in sums {
        for &j in masks_of.get(s as usize).map_or(&[][..], Vec::as_slice) {
            *per_kj
                .entry((u64::from(k) << 32) | u64::from(j))
                .or_insert(0.0) += v;
        }
    }
    let mut entries: Vec<Entry> = per_kj
        .into_iter()
        .filter(|&(_, v)| v > 0.0)
        .map(|(key, v)| Entry {
            gaussian: (key >> 32) as u32,
            mask: key as u32,
            weight: v as f32,
        })
        .collect();
    entries.par_sort_unstable_by_key(|e| (e.gaussian, e.mask));
    entries
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
    } = overlap_labels(masks, w, h, params.overlap);

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
        sums.into_iter()
            .map(|(key, v)| ((key >> 32) as u32, key as u32, v)),
        &masks_of,
    );
    weight_entries(&mut entries, masks, params.mask_weighting);
    Ok(ImageContribution {
        dim,
        mask_embeddings,
        entries,
    })
}
