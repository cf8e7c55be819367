//! Parameter masking and aggregation: SLAG's per-Gaussian embedding
//!
//! ```text
//!   a_kj = Σ_{p ∈ M_j} w_kp                       (image stage, one image)
//!   E_k  = Σ_i Σ_j a_kj · E_j  /  Σ_i Σ_j a_kj    (reduction over all images)
//! ```
//!
//! The image stage ([`image_contribution`]) turns one image's per-pixel blend weights
//! ([`PixelWeights`]) and masks into the sparse non-zero `a_kj` ([`Entry`]); nothing dense leaves it.
//! Overlapping masks are handled exactly: pixels are grouped by the *set* of masks covering them
//! (a "signature"), weights are summed per (Gaussian, signature), then expanded to each mask of the
//! signature. The reduction ([`reduce`]) accumulates in f64, chunked over Gaussian ids so that the
//! accumulator stays within a memory budget however large the scene, and declares a Gaussian
//! *unobserved* (no embedding) when `Σ a_kj` is below a threshold or the weighted mean vanishes.
//! [`reduce_mixture`] runs the same reduction but keeps each `E_k` as a sparse mixture of the
//! shared mask embeddings (`slag_common::mixture`), the compressed storage form.

use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

use rayon::prelude::*;
use rustc_hash::FxHashMap;
use slag_common::camera::{Intrinsics, WorldToCamera};
use slag_common::embeddings::EmbeddingsWriter;
use slag_common::mixture::{MixtureEmbeddings, SparseMixture};
use slag_common::{Error, Result};

use crate::masks::Mask;
use crate::raster::{PixelWeights, WeightRasterizer};

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
/// every covering mask); `slag-encoder encode`'s default is `--overlap finest` (issue 17's
/// held-out measurement, docs/tradeoffs.md).
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize)]
pub struct ImageStageParams {
    /// Keep only the `k` largest-weight contributors of each pixel (`None` = all, the paper's rule).
    pub top_k_per_pixel: Option<usize>,
    /// Specificity weighting of each mask's `a_kj` (default: none, the paper's rule).
    pub mask_weighting: MaskWeighting,
    /// Which of the masks covering a pixel receive its weights (default: all, the paper's
    /// rule; [`crate::levels::MaskOverlap`]).
    pub overlap: crate::levels::MaskOverlap,
}

/// Specificity weighting of the image stage (`encode --mask-weighting`): every `a_kj` of mask `j`
/// is multiplied by a factor `g_j` before the reduction, so that
/// `E_k = Σ g_j a_kj E_j / Σ g_j a_kj` (and the stored total weight is `Σ g_j a_kj`). Training
/// free and single pass: `g_j` depends only on the mask.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, clap::ValueEnum)]
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
fn weight_entries(entries: &mut [Entry], masks: &[Mask], weighting: MaskWeighting) {
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

/// Checks the image stage's inputs: one embedding of width `dim` per mask, masks of one size.
fn check_image_inputs(masks: &[Mask], mask_embeddings: &[f32], dim: usize) -> Result<()> {
    if mask_embeddings.len() != masks.len() * dim {
        return Err(Error::Invalid(format!(
            "{} masks but {} embedding values for dim {dim}",
            masks.len(),
            mask_embeddings.len()
        )));
    }
    if let Some(m) = masks
        .iter()
        .find(|m| (m.width, m.height) != (masks[0].width, masks[0].height))
    {
        return Err(Error::Invalid(format!(
            "masks of one image differ in size ({}x{} vs {}x{})",
            m.width, m.height, masks[0].width, masks[0].height
        )));
    }
    Ok(())
}

/// `a_kj` from per-(Gaussian, label) sums sorted by (Gaussian, label): `a_kj = Σ_{s ∋ j} sum_ks`,
/// added in that order (deterministic), zero sums dropped; sorted by (Gaussian, mask).
fn expand_labels(
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
        mut masks_of,
    } = pixel_labels(masks, w, h);
    if params.overlap == crate::levels::MaskOverlap::Finest {
        crate::levels::restrict_to_finest(&mut masks_of, masks);
    }

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

/// What [`view_contribution`] measured of one view.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ViewStats {
    /// Seconds in the rasterizer (with label sums: the GPU pass and its readback).
    pub raster_s: f64,
    /// Seconds in the host side of the image stage (labels, expansion, or the host sums).
    pub aggregate_s: f64,
    /// Raster pixels.
    pub pixels: usize,
    /// (pixel, Gaussian) contributions: all of them on the list path, those of pixels covered by
    /// a mask on the label-sum path.
    pub contributions: u64,
    /// Pixels the contributions were counted over (all, or the labelled ones).
    pub counted_pixels: usize,
    /// Whether the rasterizer summed per label on its device ([`WeightRasterizer::label_sums`]).
    pub device_sums: bool,
}

/// Raster + image stage of one view: the [`ImageContribution`] of `masks` (full resolution) and
/// their embeddings. Without `top_k_per_pixel` and with a rasterizer that sums per label on its
/// device (the GPU rasterizer), only the per-(Gaussian, label) sums leave the device (SLAG's
/// `a_kj = Σ_{p∈M_j} w_kp` with masks expanded from labels on the host); otherwise the per-pixel
/// lists are rasterized and summed by [`image_contribution`]. Both give the same `a_kj` up to
/// the device path's 2^-32 fixed point per weight.
///
/// Errors: as [`image_contribution`] and the rasterizer's.
pub fn view_contribution(
    rasterizer: &mut dyn WeightRasterizer,
    intrinsics: &Intrinsics,
    world_to_camera: &WorldToCamera,
    masks: &[Mask],
    mask_embeddings: Vec<f32>,
    dim: usize,
    params: ImageStageParams,
) -> Result<(ImageContribution, ViewStats)> {
    check_image_inputs(masks, &mask_embeddings, dim)?;
    let pixels = intrinsics.width as usize * intrinsics.height as usize;
    if params.top_k_per_pixel.is_none() && !masks.is_empty() {
        let t0 = Instant::now();
        let mut labels = pixel_labels(masks, intrinsics.width, intrinsics.height);
        if params.overlap == crate::levels::MaskOverlap::Finest {
            crate::levels::restrict_to_finest(&mut labels.masks_of, masks);
        }
        let t1 = Instant::now();
        if let Some(sums) = rasterizer.label_sums(intrinsics, world_to_camera, &labels.labels)? {
            let t2 = Instant::now();
            let mut entries = expand_labels(
                sums.sums.iter().map(|e| (e.gaussian, e.label, e.weight())),
                &labels.masks_of,
            );
            weight_entries(&mut entries, masks, params.mask_weighting);
            let stats = ViewStats {
                raster_s: (t2 - t1).as_secs_f64(),
                aggregate_s: (t1 - t0).as_secs_f64() + t2.elapsed().as_secs_f64(),
                pixels,
                contributions: sums.contributions,
                counted_pixels: labels.labels.iter().filter(|&&l| l != 0).count(),
                device_sums: true,
            };
            let c = ImageContribution {
                dim,
                mask_embeddings,
                entries,
            };
            return Ok((c, stats));
        }
    }
    let t0 = Instant::now();
    let weights = rasterizer.rasterize(intrinsics, world_to_camera)?;
    let t1 = Instant::now();
    let c = image_contribution(&weights, masks, mask_embeddings, dim, params)?;
    let stats = ViewStats {
        raster_s: (t1 - t0).as_secs_f64(),
        aggregate_s: t1.elapsed().as_secs_f64(),
        pixels,
        contributions: weights.ids.len() as u64,
        counted_pixels: pixels,
        device_sums: false,
    };
    Ok((c, stats))
}

/// Holds image contributions until the reduction, in memory up to a budget and spilled to files
/// in `spill_dir` beyond it (little-endian raw records), so scenes of any size complete.
pub struct ContributionStore {
    budget_bytes: usize,
    used_bytes: usize,
    in_memory: Vec<ImageContribution>,
    spilled: Vec<PathBuf>,
    spill_dir: PathBuf,
}

impl ContributionStore {
    /// A store keeping up to `budget_bytes` in memory, spilling the rest into `spill_dir`
    /// (created on first spill; its files are removed when the store is dropped).
    pub fn new(budget_bytes: usize, spill_dir: PathBuf) -> Self {
        Self {
            budget_bytes,
            used_bytes: 0,
            in_memory: Vec::new(),
            spilled: Vec::new(),
            spill_dir,
        }
    }

    /// Number of contributions held.
    pub fn len(&self) -> usize {
        self.in_memory.len() + self.spilled.len()
    }
    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Contributions written to disk so far.
    pub fn spilled(&self) -> usize {
        self.spilled.len()
    }
    /// Total `a_kj` entries held in memory.
    pub fn entries_in_memory(&self) -> usize {
        self.in_memory.iter().map(|c| c.entries.len()).sum()
    }

    /// Adds one image's contribution.
    pub fn push(&mut self, c: ImageContribution) -> Result<()> {
        if self.used_bytes + c.bytes() <= self.budget_bytes {
            self.used_bytes += c.bytes();
            self.in_memory.push(c);
            return Ok(());
        }
        std::fs::create_dir_all(&self.spill_dir).map_err(|e| Error::io(&self.spill_dir, e))?;
        let path = self
            .spill_dir
            .join(format!("contribution-{:06}.bin", self.spilled.len()));
        let io = |e| Error::io(&path, e);
        let mut f = BufWriter::new(std::fs::File::create(&path).map_err(io)?);
        let mut put = |v: u64| f.write_all(&v.to_le_bytes());
        put(c.dim as u64).map_err(io)?;
        put(c.mask_embeddings.len() as u64).map_err(io)?;
        put(c.entries.len() as u64).map_err(io)?;
        for v in &c.mask_embeddings {
            f.write_all(&v.to_le_bytes()).map_err(io)?;
        }
        for e in &c.entries {
            f.write_all(&e.gaussian.to_le_bytes()).map_err(io)?;
            f.write_all(&e.mask.to_le_bytes()).map_err(io)?;
            f.write_all(&e.weight.to_le_bytes()).map_err(io)?;
        }
        f.flush().map_err(io)?;
        self.spilled.push(path);
        Ok(())
    }

    fn read_spilled(path: &Path) -> Result<ImageContribution> {
        let io = |e| Error::io(path, e);
        let mut r = BufReader::new(std::fs::File::open(path).map_err(io)?);
        let mut b8 = [0u8; 8];
        let mut get = |r: &mut BufReader<std::fs::File>| -> Result<u64> {
            r.read_exact(&mut b8).map_err(io)?;
            Ok(u64::from_le_bytes(b8))
        };
        let (dim, ne, nn) = (
            get(&mut r)? as usize,
            get(&mut r)? as usize,
            get(&mut r)? as usize,
        );
        let mut buf = vec![0u8; ne * 4];
        r.read_exact(&mut buf).map_err(io)?;
        let mask_embeddings = buf
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        let mut buf = vec![0u8; nn * 12];
        r.read_exact(&mut buf).map_err(io)?;
        let u = |c: &[u8]| u32::from_le_bytes([c[0], c[1], c[2], c[3]]);
        let entries = buf
            .chunks_exact(12)
            .map(|c| Entry {
                gaussian: u(&c[0..4]),
                mask: u(&c[4..8]),
                weight: f32::from_bits(u(&c[8..12])),
            })
            .collect();
        Ok(ImageContribution {
            dim,
            mask_embeddings,
            entries,
        })
    }

    /// Calls `f` on every contribution (spilled ones are read back one at a time).
    pub fn for_each(&self, mut f: impl FnMut(&ImageContribution)) -> Result<()> {
        self.in_memory.iter().for_each(&mut f);
        for p in &self.spilled {
            f(&Self::read_spilled(p)?);
        }
        Ok(())
    }
}

impl Drop for ContributionStore {
    fn drop(&mut self) {
        for p in &self.spilled {
            let _ = std::fs::remove_file(p);
        }
        let _ = std::fs::remove_dir(&self.spill_dir);
    }
}

/// Knobs of the reduction.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct ReduceParams {
    /// A Gaussian whose `Σ a_kj` is below this is *unobserved* and gets no embedding.
    pub min_total_weight: f64,
    /// Upper bound on the f64 accumulator, bytes; the Gaussians are processed in chunks that fit.
    pub accumulator_budget_bytes: usize,
    /// Use the image-major loop (the spilled path's) even when every contribution is in memory.
    /// Same values bit for bit, only slower; kept so that benchmarks can measure the two orders
    /// against each other in one run (`slag-bench reduce`).
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub image_major: bool,
}

impl Default for ReduceParams {
    fn default() -> Self {
        Self {
            min_total_weight: 1e-6,
            accumulator_budget_bytes: 2 << 30,
            image_major: false,
        }
    }
}

/// Result of the reduction: the observed Gaussians with their `E_k`.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Reduced {
    /// Observed Gaussian indices, ascending.
    pub ids: Vec<u32>,
    /// `[ids.len() * dim]`, rows L2-normalised `E_k`.
    pub vectors: Vec<f32>,
    /// `Σ_i Σ_j a_kj` per observed Gaussian.
    pub total_weights: Vec<f32>,
    /// Number of chunks the reduction used.
    pub chunks: usize,
}

impl Reduced {
    /// Runs in ascending id order joined into one (`chunks` summed).
    pub fn concat(parts: Vec<Reduced>) -> Reduced {
        let rows: usize = parts.iter().map(|p| p.ids.len()).sum();
        let values: usize = parts.iter().map(|p| p.vectors.len()).sum();
        let mut out = Reduced {
            ids: Vec::with_capacity(rows),
            vectors: Vec::with_capacity(values),
            total_weights: Vec::with_capacity(rows),
            chunks: 0,
        };
        for p in parts {
            out.ids.extend_from_slice(&p.ids);
            out.vectors.extend_from_slice(&p.vectors);
            out.total_weights.extend_from_slice(&p.total_weights);
            out.chunks += p.chunks;
        }
        out
    }
}

/// `E_k = Σ a_kj E_j / Σ a_kj` over every stored contribution, for Gaussians `0..n_gaussians`,
/// normalised to unit length (cosine queries). f64 accumulation; chunked over Gaussian ids.
/// Unobserved: `Σ a < min_total_weight`, or the weighted mean's norm below 1e-9 of `Σ a`
/// (mask embeddings that cancel out carry no direction).
pub fn reduce(
    store: &ContributionStore,
    n_gaussians: usize,
    dim: usize,
    params: ReduceParams,
) -> Result<Reduced> {
    let mut out = Reduced::default();
    out.chunks = reduce_each(store, n_gaussians, dim, params, |parts| {
        let part = Reduced::concat(parts);
        out.ids.extend_from_slice(&part.ids);
        out.vectors.extend_from_slice(&part.vectors);
        out.total_weights.extend_from_slice(&part.total_weights);
        Ok(())
    })?;
    Ok(out)
}

/// [`reduce`] without collecting: for each chunk of Gaussian ids (ascending), hands `sink` the
/// chunk's observed rows as consecutive [`Reduced`] runs in ascending id order (observed ids
/// `[B]`, unit vectors `[B * dim]`, `Σ a_kj` `[B]`, `chunks` 0; one run per block of Gaussians), owned, so
/// that a sink may pass them to a writer thread and overlap the write with the next chunk's
/// accumulation. Memory: the f64 accumulators (one chunk's, ≤ `params.accumulator_budget_bytes`,
/// on the image-major path; one block's per thread otherwise) plus one chunk's output, whatever
/// the scene size. Returns the number of chunks.
///
/// Errors: a contribution of another width ([`Error::Invalid`]); spill-file I/O; `sink`'s errors.
pub fn reduce_each(
    store: &ContributionStore,
    n_gaussians: usize,
    dim: usize,
    params: ReduceParams,
    mut sink: impl FnMut(Vec<Reduced>) -> Result<()>,
) -> Result<usize> {
    let per_gaussian = (dim + 1) * 8;
    let mut chunk =
        (params.accumulator_budget_bytes / per_gaussian).clamp(1024, n_gaussians.max(1024));
    if store.spilled() == 0 && !params.image_major {
        // The block-major loop needs no chunk-wide accumulator: smaller chunks (at least 8 of
        // them, of at least 64 Ki Gaussians) only let the writer overlap more of the work.
        chunk = chunk.min(n_gaussians.div_ceil(8).max(1 << 16));
    }
    accumulate(
        store,
        n_gaussians,
        dim,
        chunk,
        params.image_major,
        |_, _, _| Ok(0),
        |_: &mut (), _, _| {},
        |sums| {
            let mut out = Reduced {
                chunks: 0,
                ..Default::default()
            };
            for (r, row, norm, d) in sums.observed(params.min_total_weight) {
                out.ids.push((sums.start + r) as u32);
                out.vectors.extend(row.iter().map(|v| (v / norm) as f32));
                out.total_weights.push(d as f32);
            }
            out
        },
        &mut sink,
    )
}

/// What [`reduce_to_writer`] leaves: the writer with every observed row pushed (call
/// [`EmbeddingsWriter::finish`]), the number of chunks, and the reduction's wall time in seconds
/// until its last chunk was handed to the writer thread.
pub struct Streamed {
    /// The writer, all rows pushed, not yet finished.
    pub writer: EmbeddingsWriter,
    /// Chunks the reduction used.
    pub chunks: usize,
    /// Seconds from the start until the last chunk was handed on (the rest of the call's time
    /// is the writer finishing its last chunk).
    pub reduce_s: f64,
}

/// [`reduce_each`] streamed into `writer` (the encoder's tail): a writer thread converts and
/// writes the runs of chunk c while chunk c + 1 is accumulated; at most one chunk waits in
/// between, so memory stays at the accumulators plus two chunks' output. `means` are all
/// Gaussian centres (`[N]`, world frame, `.ply` order), written beside each row.
///
/// Errors: those of [`reduce_each`]; the writer's (I/O, non-finite rows), which take precedence
/// over the reduction's "writer stopped" error they cause.
pub fn reduce_to_writer(
    store: &ContributionStore,
    means: &[[f32; 3]],
    dim: usize,
    params: ReduceParams,
    writer: EmbeddingsWriter,
) -> Result<Streamed> {
    let t0 = std::time::Instant::now();
    std::thread::scope(|s| {
        let (tx, rx) = std::sync::mpsc::sync_channel::<Vec<Reduced>>(1);
        let handle = s.spawn(move || -> Result<EmbeddingsWriter> {
            let mut writer = writer;
            let mut run_means: Vec<[f32; 3]> = Vec::new();
            for run in rx.into_iter().flatten() {
                run_means.clear();
                for &k in &run.ids {
                    run_means.push(*means.get(k as usize).ok_or_else(|| {
                        Error::Invalid(format!("Gaussian {k} has no mean ({} given)", means.len()))
                    })?);
                }
                writer.push(&run.ids, &run_means, &run.vectors, &run.total_weights)?;
            }
            Ok(writer)
        });
        let reduced = reduce_each(store, means.len(), dim, params, |runs| {
            tx.send(runs)
                .map_err(|_| Error::Invalid("the embeddings writer stopped early".into()))
        });
        let reduce_s = t0.elapsed().as_secs_f64();
        drop(tx);
        let writer = handle
            .join()
            .map_err(|_| Error::internal("the embeddings writer thread panicked"))??;
        Ok(Streamed {
            writer,
            chunks: reduced?,
            reduce_s,
        })
    })
}

/// One run of Gaussian ids (a chunk, or a block of one) after every contribution was added:
/// `Σ_i Σ_j a_kj E_j` and `Σ_i Σ_j a_kj` in f64 for Gaussians `start..start + den.len()`, plus a
/// per-Gaussian extra (`T`) that the entry hook of [`accumulate`] filled.
struct ChunkSums<T> {
    /// First Gaussian id of the chunk.
    start: usize,
    /// Embedding width D.
    dim: usize,
    /// `[B * D]` weighted sums `Σ a_kj E_j`.
    num: Vec<f64>,
    /// `[B]` total weights `Σ a_kj`.
    den: Vec<f64>,
    /// `[B]` per-Gaussian extras.
    extra: Vec<T>,
}

impl<T: Clone + Default> ChunkSums<T> {
    /// Zeroed sums for Gaussians `start..start + len`, reusing the buffers.
    fn reset(&mut self, start: usize, len: usize) {
        self.start = start;
        self.num.clear();
        self.num.resize(len * self.dim, 0.0);
        self.den.clear();
        self.den.resize(len, 0.0);
        self.extra.clear();
        self.extra.resize(len, T::default());
    }

    /// The observed Gaussians of the chunk, ascending: `(row r, Σ a E [D], its L2 norm, Σ a)`.
    /// Unobserved (skipped): `Σ a` NaN or below `min_total_weight`, or the norm not finite or
    /// at most `1e-9 · Σ a` (mask embeddings that cancel out carry no direction).
    fn observed(&self, min_total_weight: f64) -> impl Iterator<Item = (usize, &[f64], f64, f64)> {
        self.den.iter().enumerate().filter_map(move |(r, &d)| {
            // NaN sums count as unobserved too.
            if d.is_nan() || d < min_total_weight {
                return None;
            }
            let row = &self.num[r * self.dim..(r + 1) * self.dim];
            let norm = row.iter().map(|v| v * v).sum::<f64>().sqrt();
            if !norm.is_finite() || norm <= 1e-9 * d {
                return None;
            }
            Some((r, row, norm, d))
        })
    }
}

/// The f64 accumulation shared by [`reduce_each`] and [`reduce_mixture`]: for each chunk of
/// `chunk` Gaussian ids, visits every contribution ([`ContributionStore::for_each`] order) and adds
/// `a_kj` to `Σ a` and `a_kj · E_j` to `Σ a E` of its Gaussian; `finish` turns each run of final
/// sums into a part (in parallel), and `done` receives the chunk's parts in ascending id order.
/// Within a Gaussian the sums always run in contribution, then entry order, so every caller and
/// both loop orders below get bit-identical f64 values.
///
/// Loop order ([`ReduceParams::image_major`]):
/// - *Gaussian-block-major* (default when no contribution is spilled): rayon over blocks of
///   [`REDUCE_BLOCK`] Gaussians, each block visiting every image's entries of its id range into
///   its thread's accumulator (`REDUCE_BLOCK × D` f64, 512 KiB at D = 512, reused from block to
///   block), which stays in the core's cache while all images are added; `finish` runs per
///   block. The memory traffic is one read of the entries and mask embeddings.
/// - *Image-major* (spilled contributions, streamed from disk one at a time): a chunk-sized
///   accumulator; for each image, rayon over blocks of 1024 Gaussians; every entry reads and
///   writes its Gaussian's f64 row in memory; `finish` runs once on the whole chunk.
///
/// Hooks: `on_image(first_chunk, image, c)` runs once per contribution and chunk, in visit order,
/// before its entries are added (after the width check; `image` counts the contributions of this
/// chunk's visit from 0) and returns a tag passed to `on_entry` (the mixture's codebook offset);
/// `on_entry(extra, entry, tag)` sees every entry with its Gaussian's extra, in the per-Gaussian
/// order above. The first error of a width mismatch or `on_image` is returned and no part of
/// that chunk is handed on (spill-file I/O errors come first). Returns the number of chunks.
#[allow(clippy::too_many_arguments)]
fn accumulate<T: Clone + Default + Send, B: Send>(
    store: &ContributionStore,
    n_gaussians: usize,
    dim: usize,
    chunk: usize,
    image_major: bool,
    mut on_image: impl FnMut(bool, usize, &ImageContribution) -> Result<u32>,
    on_entry: impl Fn(&mut T, &Entry, u32) + Sync,
    finish: impl Fn(&ChunkSums<T>) -> B + Sync,
    mut done: impl FnMut(Vec<B>) -> Result<()>,
) -> Result<usize> {
    let width_check = |c: &ImageContribution| {
        if c.dim != dim {
            return Err(Error::Invalid(format!(
                "contribution of dim {}, expected {dim}",
                c.dim
            )));
        }
        Ok(())
    };
    let empty = || ChunkSums {
        start: 0,
        dim,
        num: Vec::new(),
        den: Vec::new(),
        extra: Vec::new(),
    };
    let mut chunks = 0;
    for start in (0..n_gaussians).step_by(chunk) {
        chunks += 1;
        let end = (start + chunk).min(n_gaussians);
        if store.spilled() == 0 && !image_major {
            let images = &store.in_memory;
            let mut tags = Vec::with_capacity(images.len());
            for (image, c) in images.iter().enumerate() {
                width_check(c)?;
                tags.push(on_image(start == 0, image, c)?);
            }
            let parts: Vec<B> = (start..end)
                .step_by(REDUCE_BLOCK)
                .collect::<Vec<_>>()
                .into_par_iter()
                .map_init(empty, |sums, g0| {
                    sums.reset(g0, REDUCE_BLOCK.min(end - g0));
                    for (c, &tag) in images.iter().zip(&tags) {
                        let (num, den, extra) = (&mut sums.num, &mut sums.den, &mut sums.extra);
                        add_entries(c, g0 as u32, dim, num, den, extra, tag, &on_entry);
                    }
                    finish(sums)
                })
                .collect();
            done(parts)?;
        } else {
            const BLOCK: usize = 1024;
            let mut sums = empty();
            sums.reset(start, end - start);
            let mut failure: Option<Error> = None;
            let mut image = 0usize;
            store.for_each(|c| {
                if failure.is_some() {
                    return;
                }
                let tag = match width_check(c).and_then(|()| on_image(start == 0, image, c)) {
                    Ok(tag) => tag,
                    Err(e) => {
                        failure = Some(e);
                        return;
                    }
                };
                image += 1;
                sums.num
                    .par_chunks_mut(BLOCK * dim)
                    .zip(sums.den.par_chunks_mut(BLOCK))
                    .zip(sums.extra.par_chunks_mut(BLOCK))
                    .enumerate()
                    .for_each(|(b, ((num, den), extra))| {
                        let g0 = (start + b * BLOCK) as u32;
                        add_entries(c, g0, dim, num, den, extra, tag, &on_entry);
                    });
            })?;
            if let Some(e) = failure {
                return Err(e);
            }
            done(vec![finish(&sums)])?;
        }
    }
    Ok(chunks)
}

/// Gaussians per task of the Gaussian-block-major reduction ([`accumulate`]).
const REDUCE_BLOCK: usize = 128;

/// Adds one image's entries for Gaussians `g0..g0 + db.len()` (its entries are sorted by
/// Gaussian) to that block's sums: `db[r] += a`, `nb[r·D..(r+1)·D] += a · E_j`, in entry order.
#[allow(clippy::too_many_arguments)]
#[inline]
fn add_entries<T>(
    c: &ImageContribution,
    g0: u32,
    dim: usize,
    nb: &mut [f64],
    db: &mut [f64],
    xb: &mut [T],
    tag: u32,
    on_entry: &(impl Fn(&mut T, &Entry, u32) + Sync),
) {
    let g1 = g0 + db.len() as u32;
    let lo = c.entries.partition_point(|e| e.gaussian < g0);
    let hi = lo + c.entries[lo..].partition_point(|e| e.gaussian < g1);
    for e in &c.entries[lo..hi] {
        let r = (e.gaussian - g0) as usize;
        let a = e.weight as f64;
        db[r] += a;
        let ej = &c.mask_embeddings[e.mask as usize * dim..(e.mask as usize + 1) * dim];
        for (acc, &v) in nb[r * dim..(r + 1) * dim].iter_mut().zip(ej) {
            *acc += a * v as f64;
        }
        on_entry(&mut xb[r], e, tag);
    }
}

/// The same reduction as [`reduce`], kept in mixture form ([`MixtureEmbeddings`]): a shared
/// codebook of every image's mask embeddings `E_j` plus, per observed Gaussian, its `keep`
/// largest `a_kj` over all images, so that `E_k ≈ Σ_{kept} a_kj E_j / ‖Σ_{kept} a_kj E_j‖`.
///
/// Codebook ids: the mask embeddings of the images are concatenated in the order
/// [`ContributionStore::for_each`] visits them (the in-memory images, then the spilled ones, each
/// in push order), so mask `j` of image `i` is row `offset_i + j`; rows no kept atom uses are then
/// dropped and the rest renumbered in that order ([`MixtureEmbeddings::from_sparse`]).
///
/// The observed Gaussians are exactly those of [`reduce`] with the same `params` (same f64
/// sums in the same order, same unobserved rule on the full `Σ a_kj` and `‖Σ a_kj E_j‖`); with
/// `keep` at least a Gaussian's number of non-zero `a_kj` its reconstruction equals [`reduce`]'s
/// `E_k` up to f16 rounding of the codebook and weights. Ties between equal `a_kj` keep the lower
/// codebook row. Memory: the f64 accumulator of [`reduce`] plus up to `keep` `(a, row)` pairs per
/// Gaussian of a chunk, chunked over Gaussian ids within `params.accumulator_budget_bytes`, plus
/// the whole `M × D` f32 codebook; the result holds `N × S` slots with
/// `S = min(keep, most non-zero a_kj of any observed Gaussian)` (the `[N, S]` layout pays `S`
/// slots for every Gaussian, so a heavy tail of atom counts makes a large `keep` expensive).
///
/// `means` are all `n_gaussians` centres (world frame, source `.ply` order); `model_id` is the
/// CLIP visual model id recorded in the output.
///
/// Errors ([`Error::Invalid`]): `keep == 0`, `means.len() != n_gaussians`, a contribution of
/// another width than `dim`, more than `u32::MAX - 1` mask embeddings in all, a kept mixture that
/// [`MixtureEmbeddings::from_sparse`] cannot store (mask embeddings that nearly cancel); I/O
/// errors of spilled contributions.
pub fn reduce_mixture(
    store: &ContributionStore,
    n_gaussians: usize,
    dim: usize,
    params: ReduceParams,
    keep: usize,
    model_id: &str,
    means: &[[f32; 3]],
) -> Result<MixtureEmbeddings> {
    if keep == 0 {
        return Err(Error::Invalid(
            "mixture keep is 0; keep at least 1 mask embedding per Gaussian".into(),
        ));
    }
    if means.len() != n_gaussians {
        return Err(Error::Invalid(format!(
            "{} means for {n_gaussians} Gaussians",
            means.len()
        )));
    }
    let slots_estimate = keep.min(64);
    let per_gaussian = (dim + 1) * 8 + std::mem::size_of::<Vec<(f32, u32)>>() + slots_estimate * 8;
    let chunk = (params.accumulator_budget_bytes / per_gaussian).clamp(1024, n_gaussians.max(1024));
    let mut codebook: Vec<f32> = Vec::new();
    let mut image_offsets: Vec<u32> = Vec::new();
    let mut parts = SparseMixture {
        dim,
        model_id: model_id.to_string(),
        offsets: vec![0],
        ..Default::default()
    };
    accumulate(
        store,
        n_gaussians,
        dim,
        chunk,
        params.image_major,
        |first_chunk, image, c| {
            if first_chunk {
                let rows = codebook.len() / dim.max(1);
                if rows + c.mask_embeddings.len() / dim.max(1) >= u32::MAX as usize {
                    return Err(Error::Invalid(format!(
                        "more than {} mask embeddings in all: too many for u32 codebook ids",
                        u32::MAX - 1
                    )));
                }
                image_offsets.push(rows as u32);
                codebook.extend_from_slice(&c.mask_embeddings);
            }
            image_offsets.get(image).copied().ok_or_else(|| {
                Error::Invalid("the contribution store changed during the reduction".into())
            })
        },
        |top: &mut Vec<(f32, u32)>, e, offset| push_top(top, keep, e.weight, offset + e.mask),
        // Per run: the observed Gaussians with their kept (a, atom), in id order.
        |sums| {
            sums.observed(params.min_total_weight)
                .map(|(r, _, _, _)| (sums.start + r, sums.extra[r].clone()))
                .collect::<Vec<_>>()
        },
        |runs| {
            for (k, top) in runs.into_iter().flatten() {
                parts.gaussian_ids.push(k as u32);
                parts.means.push(means[k]);
                for (a, atom) in top {
                    parts.atoms.push(atom);
                    parts.weights.push(a as f64);
                }
                parts.offsets.push(parts.atoms.len());
            }
            Ok(())
        },
    )?;
    parts.codebook = codebook;
    MixtureEmbeddings::from_sparse(parts)
}

/// Keeps the `keep` largest `(a, atom)` of one Gaussian (ties: the lower atom). Atoms arrive in
/// increasing order, so an equal `a` never displaces a kept one.
fn push_top(top: &mut Vec<(f32, u32)>, keep: usize, a: f32, atom: u32) {
    if top.len() < keep {
        top.push((a, atom));
        return;
    }
    let weakest = top
        .iter()
        .enumerate()
        .min_by(|x, y| x.1.0.total_cmp(&y.1.0).then(y.1.1.cmp(&x.1.1)));
    if let Some((i, &(wa, watom))) = weakest
        && (a > wa || (a == wa && atom < watom))
    {
        top[i] = (a, atom);
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn mask(w: u32, h: u32, f: impl Fn(u32, u32) -> bool) -> Mask {
        let px = (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .map(|(x, y)| f(x, y) as u8)
            .collect();
        Mask::from_pixels(w, h, px).unwrap()
    }

    /// Random-ish PixelWeights with 0..4 contributors per pixel.
    fn weights(w: u32, h: u32, n: u32, seed: u64) -> PixelWeights {
        let mut s = seed;
        let mut next = || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            s
        };
        let mut pw = PixelWeights {
            width: w,
            height: h,
            offsets: vec![0],
            ..Default::default()
        };
        for _ in 0..w * h {
            let c = next() % 5;
            for _ in 0..c {
                pw.ids.push((next() % n as u64) as u32);
                pw.weights.push((next() % 1000) as f32 / 4000.0 + 1e-3);
            }
            pw.offsets.push(pw.ids.len() as u32);
        }
        pw
    }

    /// Brute force straight from the paper's formula.
    fn brute(pw: &PixelWeights, masks: &[Mask]) -> FxHashMap<(u32, u32), f64> {
        let mut m = FxHashMap::default();
        for (j, mk) in masks.iter().enumerate() {
            for y in 0..pw.height {
                for x in 0..pw.width {
                    if mk.contains(x, y) {
                        let (ids, ws) = pw.pixel(x, y);
                        for (&k, &w) in ids.iter().zip(ws) {
                            *m.entry((k, j as u32)).or_insert(0.0) += w as f64;
                        }
                    }
                }
            }
        }
        m
    }

    #[test]
    fn mask_weighting_scales_each_masks_a_kj() {
        let (w, h, n) = (37, 23, 50);
        let pw = weights(w, h, n, 0x51ed);
        let mut masks = vec![
            mask(w, h, |x, _| x < 20),
            mask(w, h, |x, y| x > 10 && y > 5),
            mask(w, h, |_, _| true),
        ];
        masks[0].predicted_iou = 0.5;
        masks[0].stability_score = 0.8;
        masks[1].predicted_iou = f32::NAN;
        let expect = brute(&pw, &masks);
        for weighting in [MaskWeighting::Area, MaskWeighting::SamScore] {
            let params = ImageStageParams {
                mask_weighting: weighting,
                ..ImageStageParams::default()
            };
            let c = image_contribution(&pw, &masks, vec![0.0; 3 * 2], 2, params).unwrap();
            assert_eq!(c.entries.len(), expect.len());
            for e in &c.entries {
                let m = &masks[e.mask as usize];
                let g = match weighting {
                    MaskWeighting::Area => (w * h) as f64 / m.area as f64,
                    _ if e.mask == 0 => 0.4,
                    _ if e.mask == 1 => f32::MIN_POSITIVE as f64,
                    _ => 1.0,
                };
                let v = g * expect[&(e.gaussian, e.mask)];
                assert!(
                    (v - e.weight as f64).abs() < 1e-5 * v.max(1e-30),
                    "{weighting:?} {e:?} vs {v}"
                );
            }
        }
        assert_eq!(MaskWeighting::None.factor(&masks[1]), 1.0);
        assert_eq!(MaskWeighting::Area.factor(&masks[2]), 1.0);
    }

    #[test]
    fn image_stage_matches_brute_force_with_overlapping_masks() {
        let (w, h, n) = (37, 23, 50);
        let pw = weights(w, h, n, 0x9e3779b97f4a7c15);
        let masks = vec![
            mask(w, h, |x, _| x < 20),
            mask(w, h, |x, y| x > 10 && y > 5),
            mask(w, h, |x, y| (x + y) % 3 == 0),
            mask(w, h, |_, _| true),
        ];
        let c = image_contribution(
            &pw,
            &masks,
            vec![0.0; 4 * 2],
            2,
            ImageStageParams::default(),
        )
        .unwrap();
        let expect = brute(&pw, &masks);
        assert_eq!(c.entries.len(), expect.len());
        for e in &c.entries {
            let v = expect[&(e.gaussian, e.mask)];
            assert!(
                (v - e.weight as f64).abs() < 1e-5 * v.max(1.0),
                "{e:?} vs {v}"
            );
        }
        assert!(
            c.entries
                .windows(2)
                .all(|p| (p[0].gaussian, p[0].mask) < (p[1].gaussian, p[1].mask))
        );
    }

    #[test]
    fn masks_are_resampled_to_a_smaller_raster() {
        // Full-res masks 40x20, raster 20x10: raster pixel (x, y) samples mask pixel (2x+1, 2y+1).
        let masks = vec![mask(40, 20, |x, _| x >= 20)];
        let mut pw = PixelWeights {
            width: 20,
            height: 10,
            offsets: vec![0],
            ..Default::default()
        };
        for p in 0..200u32 {
            pw.ids.push(p);
            pw.weights.push(0.5);
            pw.offsets.push(pw.ids.len() as u32);
        }
        let c = image_contribution(&pw, &masks, vec![1.0], 1, ImageStageParams::default()).unwrap();
        assert_eq!(c.entries.len(), 100);
        assert!(
            c.entries
                .iter()
                .all(|e| e.gaussian % 20 >= 10 && e.weight == 0.5)
        );
    }

    #[test]
    fn top_k_keeps_largest_contributors() {
        let masks = vec![mask(1, 1, |_, _| true)];
        let pw = PixelWeights {
            width: 1,
            height: 1,
            offsets: vec![0, 4],
            ids: vec![0, 1, 2, 3],
            weights: vec![0.1, 0.4, 0.05, 0.3],
        };
        let c = image_contribution(
            &pw,
            &masks,
            vec![1.0],
            1,
            ImageStageParams {
                top_k_per_pixel: Some(2),
                ..ImageStageParams::default()
            },
        )
        .unwrap();
        let kept: Vec<u32> = c.entries.iter().map(|e| e.gaussian).collect();
        assert_eq!(kept, vec![1, 3]);
    }

    #[test]
    fn reduction_is_the_weighted_mean_and_flags_unobserved() {
        let dim = 3;
        let mut store = ContributionStore::new(usize::MAX, std::env::temp_dir().join("unused"));
        // Image 1: masks e_x and e_y. Gaussian 0: a=1 in both; Gaussian 2: a=3 in e_y only.
        store
            .push(ImageContribution {
                dim,
                mask_embeddings: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0],
                entries: vec![
                    Entry {
                        gaussian: 0,
                        mask: 0,
                        weight: 1.0,
                    },
                    Entry {
                        gaussian: 0,
                        mask: 1,
                        weight: 1.0,
                    },
                    Entry {
                        gaussian: 2,
                        mask: 1,
                        weight: 3.0,
                    },
                    Entry {
                        gaussian: 3,
                        mask: 0,
                        weight: 1e-9,
                    },
                ],
            })
            .unwrap();
        // Image 2: mask e_z. Gaussian 0: a=2.
        store
            .push(ImageContribution {
                dim,
                mask_embeddings: vec![0.0, 0.0, 1.0],
                entries: vec![Entry {
                    gaussian: 0,
                    mask: 0,
                    weight: 2.0,
                }],
            })
            .unwrap();
        let r = reduce(&store, 5, dim, ReduceParams::default()).unwrap();
        assert_eq!(r.ids, vec![0, 2]); // 1 and 4 unseen, 3 below the threshold
        let n = (1.0f64 + 1.0 + 4.0).sqrt();
        let e0: Vec<f32> = [1.0 / n, 1.0 / n, 2.0 / n]
            .iter()
            .map(|&v| v as f32)
            .collect();
        for (a, b) in r.vectors[..3].iter().zip(&e0) {
            assert!((a - b).abs() < 1e-6);
        }
        assert_eq!(&r.vectors[3..6], &[0.0, 1.0, 0.0]);
        assert_eq!(r.total_weights, vec![4.0, 3.0]);
    }

    #[test]
    fn chunked_and_spilled_reduction_equals_single_pass() {
        let dim = 4;
        let n = 5000;
        let make = |seed: u64| {
            let pw = weights(30, 20, n, seed);
            let masks = vec![mask(30, 20, |x, _| x < 15), mask(30, 20, |_, y| y < 12)];
            let emb: Vec<f32> = (0..8)
                .map(|i| ((i * 7 + seed as usize) % 5) as f32 - 2.0)
                .collect();
            image_contribution(&pw, &masks, emb, dim, ImageStageParams::default()).unwrap()
        };
        let dir = tempfile::tempdir().unwrap();
        let mut all_mem = ContributionStore::new(usize::MAX, dir.path().join("a"));
        let mut spilling = ContributionStore::new(0, dir.path().join("b"));
        for seed in 1..6 {
            all_mem.push(make(seed)).unwrap();
            spilling.push(make(seed)).unwrap();
        }
        assert_eq!(spilling.spilled(), 5);
        let one = reduce(&all_mem, n as usize, dim, ReduceParams::default()).unwrap();
        let tight = ReduceParams {
            accumulator_budget_bytes: 1024 * (dim + 1) * 8,
            ..Default::default()
        };
        let many = reduce(&spilling, n as usize, dim, tight).unwrap();
        assert_eq!(one.chunks, 1);
        assert!(many.chunks >= 4);
        assert_eq!(one.ids, many.ids);
        assert!(!one.ids.is_empty());
        for (a, b) in one.vectors.iter().zip(&many.vectors) {
            assert!((a - b).abs() < 1e-6);
        }
        drop(spilling);
        assert!(!dir.path().join("b").exists());
    }
    /// Unit rows from a xorshift stream.
    fn unit_rows(m: usize, dim: usize, seed: u64) -> Vec<f32> {
        let mut s = seed | 1;
        let mut out = Vec::new();
        for _ in 0..m {
            let v: Vec<f32> = (0..dim)
                .map(|_| {
                    s ^= s << 13;
                    s ^= s >> 7;
                    s ^= s << 17;
                    (s >> 40) as f32 / (1u64 << 23) as f32 - 1.0
                })
                .collect();
            let n = v.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-12);
            out.extend(v.iter().map(|x| x / n));
        }
        out
    }

    /// Images with overlapping masks over `n` Gaussians, unit mask embeddings of width `dim`.
    fn mixture_store(n: u32, dim: usize, budget: usize, dir: &Path) -> ContributionStore {
        let mut store = ContributionStore::new(budget, dir.to_path_buf());
        for seed in 1..5u64 {
            let pw = weights(30, 20, n, seed);
            let masks = vec![
                mask(30, 20, |x, _| x < 15),
                mask(30, 20, |_, y| y < 12),
                mask(30, 20, |x, y| (x + 2 * y) % 5 < 2),
            ];
            let emb = unit_rows(masks.len(), dim, seed * 31);
            let c = image_contribution(&pw, &masks, emb, dim, ImageStageParams::default()).unwrap();
            store.push(c).unwrap();
        }
        store
    }

    #[test]
    fn mixture_with_every_atom_kept_reproduces_reduce() {
        let (n, dim) = (3000u32, 16);
        let dir = tempfile::tempdir().unwrap();
        let means: Vec<[f32; 3]> = (0..n).map(|k| [k as f32, 1.0, -2.0]).collect();
        let store = mixture_store(n, dim, usize::MAX, &dir.path().join("a"));
        let exact = reduce(&store, n as usize, dim, ReduceParams::default()).unwrap();
        let mix = reduce_mixture(
            &store,
            n as usize,
            dim,
            ReduceParams::default(),
            usize::MAX,
            "m",
            &means,
        )
        .unwrap();
        assert_eq!(mix.gaussian_ids, exact.ids);
        assert!(mix.len() > 1000);
        assert_eq!(mix.model_id, "m");
        // 4 images x 3 overlapping masks: up to 12 atoms, all of them used by someone.
        assert_eq!(mix.codebook_len(), 12);
        assert!(mix.keep > 3 && mix.keep <= 12);
        for (i, &k) in mix.gaussian_ids.iter().enumerate() {
            assert_eq!(mix.means[i], means[k as usize]);
        }
        let dense = mix.to_dense();
        let max = dense
            .iter()
            .zip(&exact.vectors)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max);
        // f16 rounding of codebook values and weights of magnitude <= 1: <= 2^-11 each.
        assert!(max < 1e-3, "max |Δ| {max}");
        assert!(max > 0.0, "f16 storage should not be bit-exact against f32");

        // Chunked and spilled: the same mixture.
        let spilling = mixture_store(n, dim, 0, &dir.path().join("b"));
        assert_eq!(spilling.spilled(), 4);
        let tight = ReduceParams {
            accumulator_budget_bytes: 1024 * (dim + 1) * 8,
            ..Default::default()
        };
        let again =
            reduce_mixture(&spilling, n as usize, dim, tight, usize::MAX, "m", &means).unwrap();
        assert_eq!(again, mix);
    }

    #[test]
    fn both_loop_orders_give_the_same_sums_bit_for_bit() {
        // 3000 Gaussians = 23.4 blocks of REDUCE_BLOCK: a partial last block, and with the tight
        // budget 3 chunks whose edges fall inside blocks of the image-major loop.
        let (n, dim) = (3000u32, 16);
        let dir = tempfile::tempdir().unwrap();
        let means: Vec<[f32; 3]> = (0..n).map(|k| [k as f32, 0.0, 0.0]).collect();
        let store = mixture_store(n, dim, usize::MAX, &dir.path().join("a"));
        assert_eq!(store.spilled(), 0);
        for budget in [usize::MAX / 2, 1024 * (dim + 1) * 8] {
            let block_major = ReduceParams {
                accumulator_budget_bytes: budget,
                ..Default::default()
            };
            let image_major = ReduceParams {
                image_major: true,
                ..block_major
            };
            let a = reduce(&store, n as usize, dim, block_major).unwrap();
            let b = reduce(&store, n as usize, dim, image_major).unwrap();
            assert!(a.ids.len() > 1000);
            // Exact equality of the f32 outputs of the f64 sums, not a tolerance.
            assert_eq!(a, b, "budget {budget}");
            let ma = reduce_mixture(&store, n as usize, dim, block_major, 4, "m", &means).unwrap();
            let mb = reduce_mixture(&store, n as usize, dim, image_major, 4, "m", &means).unwrap();
            assert_eq!(ma, mb, "budget {budget}");
        }
        // A contribution of another width fails in both orders, before any sum is handed on.
        let mut bad = mixture_store(n, dim, usize::MAX, &dir.path().join("b"));
        bad.push(ImageContribution {
            dim: dim + 1,
            mask_embeddings: vec![0.0; dim + 1],
            entries: vec![],
        })
        .unwrap();
        for image_major in [false, true] {
            let p = ReduceParams {
                image_major,
                ..Default::default()
            };
            let mut handed = 0;
            let e = reduce_each(&bad, n as usize, dim, p, |_| {
                handed += 1;
                Ok(())
            })
            .unwrap_err();
            assert!(e.to_string().contains("dim 17"), "{e}");
            assert_eq!(handed, 0);
        }
    }

    #[test]
    fn mixture_observes_what_reduce_observes_and_rejects_bad_input() {
        let dim = 3;
        let mut store = ContributionStore::new(usize::MAX, std::env::temp_dir().join("unused"));
        // Gaussian 0: a=1 on e_x and on -e_x (cancels: unobserved); 1: tiny weight; 2: e_y.
        store
            .push(ImageContribution {
                dim,
                mask_embeddings: vec![1.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0, 0.0],
                entries: vec![
                    Entry {
                        gaussian: 0,
                        mask: 0,
                        weight: 1.0,
                    },
                    Entry {
                        gaussian: 0,
                        mask: 1,
                        weight: 1.0,
                    },
                    Entry {
                        gaussian: 1,
                        mask: 2,
                        weight: 1e-9,
                    },
                    Entry {
                        gaussian: 2,
                        mask: 2,
                        weight: 2.0,
                    },
                    Entry {
                        gaussian: 2,
                        mask: 0,
                        weight: 0.5,
                    },
                ],
            })
            .unwrap();
        let means = vec![[0.0; 3]; 4];
        let p = ReduceParams::default();
        let exact = reduce(&store, 4, dim, p).unwrap();
        let mix = reduce_mixture(&store, 4, dim, p, 1, "m", &means).unwrap();
        assert_eq!(exact.ids, vec![2]);
        assert_eq!(mix.gaussian_ids, vec![2]);
        // keep 1: only the e_y atom (a=2) survives, and the unused codebook rows are dropped.
        assert_eq!(mix.codebook, vec![0.0, 1.0, 0.0]);
        assert_eq!(
            (mix.keep, mix.atoms.clone(), mix.weights.clone()),
            (1, vec![0], vec![1.0])
        );
        assert!(matches!(
            reduce_mixture(&store, 4, dim, p, 0, "m", &means),
            Err(Error::Invalid(_))
        ));
        assert!(matches!(
            reduce_mixture(&store, 4, dim, p, 2, "m", &means[..3]),
            Err(Error::Invalid(_))
        ));
        assert!(matches!(
            reduce_mixture(&store, 4, 4, p, 2, "m", &means),
            Err(Error::Invalid(_))
        ));
    }

    mod mixture_props {
        use super::*;
        use proptest::prelude::*;

        /// Random sparse contributions: per image, random masks and random (gaussian, mask, a).
        fn random_store(n: u32, images: usize, dim: usize, seed: u64) -> Vec<ImageContribution> {
            let mut s = seed | 1;
            let mut next = move || {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                s
            };
            (0..images)
                .map(|i| {
                    let m = 1 + (next() % 5) as u32;
                    let mut entries = Vec::new();
                    for g in 0..n {
                        for j in 0..m {
                            if next() % 3 == 0 {
                                // Coarse weights so that ties happen and test the tie rule.
                                let weight = (1 + next() % 40) as f32 / 8.0;
                                entries.push(Entry {
                                    gaussian: g,
                                    mask: j,
                                    weight,
                                });
                            }
                        }
                    }
                    ImageContribution {
                        dim,
                        mask_embeddings: unit_rows(m as usize, dim, seed ^ ((i as u64 + 1) * 77)),
                        entries,
                    }
                })
                .collect()
        }

        proptest! {
            #![proptest_config(ProptestConfig::with_cases(40))]
            #[test]
            fn mixture_scores_and_top_atom(
                n in 1u32..40, images in 1usize..5, dim in 2usize..12, keep in 1usize..6,
                seed in any::<u64>(),
            ) {
                let contribs = random_store(n, images, dim, seed);
                let mut store =
                    ContributionStore::new(usize::MAX, std::env::temp_dir().join("unused"));
                for c in &contribs {
                    store.push(c.clone()).unwrap();
                }
                let means = vec![[0.5f32; 3]; n as usize];
                let p = ReduceParams::default();
                let exact = reduce(&store, n as usize, dim, p).unwrap();
                // Random embeddings may cancel at some keep: then the mixture refuses, typed.
                let mix = match reduce_mixture(&store, n as usize, dim, p, keep, "m", &means) {
                    Ok(m) => m,
                    Err(e) => {
                        prop_assert!(matches!(e, Error::Invalid(_)));
                        return Ok(());
                    }
                };
                prop_assert_eq!(&mix.gaussian_ids, &exact.ids);
                prop_assert!(mix.keep <= keep);
                // Scores equal dense cosine scores of the reconstruction.
                let q = unit_rows(1, dim, seed ^ 0xabc);
                let s = mix.scores(&q).unwrap();
                let dense = slag_common::similarity::cosine_scores(&mix.to_dense(), dim, &q).unwrap();
                for (a, b) in s.iter().zip(&dense) {
                    prop_assert!((a - b).abs() < 1e-5, "{} vs {}", a, b);
                }
                // The first slot holds the largest a_kj (ties: first image, then lower mask).
                for (i, &k) in mix.gaussian_ids.iter().enumerate() {
                    let mut best: Option<(f32, &[f32])> = None;
                    for c in &contribs {
                        for e in c.entries.iter().filter(|e| e.gaussian == k) {
                            if best.is_none_or(|(a, _)| e.weight > a) {
                                let j = e.mask as usize;
                                best = Some((e.weight, &c.mask_embeddings[j * dim..(j + 1) * dim]));
                            }
                        }
                    }
                    let (_, want) = best.unwrap();
                    let atom = mix.atoms[i * mix.keep];
                    let row = &mix.codebook[atom as usize * dim..(atom as usize + 1) * dim];
                    for (a, b) in row.iter().zip(want) {
                        prop_assert_eq!(*a, half::f16::from_f32(*b).to_f32());
                    }
                    if keep == 1 {
                        // One atom: the reconstruction is that mask embedding (weight 1/‖E‖ ≈ 1).
                        prop_assert!((mix.weights[i] - 1.0).abs() < 2e-3);
                    }
                }
            }
        }
    }
}
