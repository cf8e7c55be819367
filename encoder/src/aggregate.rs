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

use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

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

/// Knobs of the image stage.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize)]
pub struct ImageStageParams {
    /// Keep only the `k` largest-weight contributors of each pixel (`None` = all, the paper's rule).
    pub top_k_per_pixel: Option<usize>,
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
    let (w, h) = (weights.width, weights.height);
    if masks.is_empty() || w == 0 || h == 0 {
        return Ok(ImageContribution {
            dim,
            mask_embeddings,
            entries: Vec::new(),
        });
    }
    let (words, bits) = membership(masks, w, h);

    // Signatures: distinct mask sets. Id 0 is reserved for "no mask" (skipped).
    let mut sig_of: FxHashMap<&[u64], u32> = FxHashMap::default();
    let mut sig_masks: Vec<Vec<u32>> = vec![Vec::new()];
    let pixel_sig: Vec<u32> = bits
        .chunks_exact(words)
        .map(|set| {
            if set.iter().all(|&b| b == 0) {
                return 0;
            }
            *sig_of.entry(set).or_insert_with(|| {
                let members = (0..masks.len() as u32)
                    .filter(|&j| set[j as usize / 64] >> (j % 64) & 1 == 1)
                    .collect();
                sig_masks.push(members);
                (sig_masks.len() - 1) as u32
            })
        })
        .collect();

    // Σ_p w_kp per (Gaussian, signature), row bands in parallel, f64 sums.
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
    // Expand signatures to masks: a_kj = Σ_{s ∋ j} acc[k, s].
    let mut per_kj: FxHashMap<u64, f64> = FxHashMap::default();
    for (key, v) in merged {
        let (k, s) = (key >> 32, (key & 0xffff_ffff) as usize);
        for &j in &sig_masks[s] {
            *per_kj.entry((k << 32) | j as u64).or_insert(0.0) += v;
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
    Ok(ImageContribution {
        dim,
        mask_embeddings,
        entries,
    })
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
}

impl Default for ReduceParams {
    fn default() -> Self {
        Self {
            min_total_weight: 1e-6,
            accumulator_budget_bytes: 2 << 30,
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
    out.chunks = reduce_each(store, n_gaussians, dim, params, |ids, vectors, weights| {
        out.ids.extend_from_slice(ids);
        out.vectors.extend_from_slice(vectors);
        out.total_weights.extend_from_slice(weights);
        Ok(())
    })?;
    Ok(out)
}

/// [`reduce`] without collecting: for each chunk of Gaussian ids (ascending), calls `sink` with
/// the chunk's observed ids `[B]`, unit vectors `[B * dim]` and `Σ a_kj` `[B]`, then frees the
/// chunk. Memory: the f64 accumulator (≤ `params.accumulator_budget_bytes`) plus one chunk's
/// output, whatever the scene size. Returns the number of chunks.
///
/// Errors: a contribution of another width ([`Error::Invalid`]); spill-file I/O; `sink`'s errors.
pub fn reduce_each(
    store: &ContributionStore,
    n_gaussians: usize,
    dim: usize,
    params: ReduceParams,
    mut sink: impl FnMut(&[u32], &[f32], &[f32]) -> Result<()>,
) -> Result<usize> {
    let per_gaussian = (dim + 1) * 8;
    let chunk = (params.accumulator_budget_bytes / per_gaussian).clamp(1024, n_gaussians.max(1024));
    let mut chunks = 0;
    let mut bad_dim = None;
    for start in (0..n_gaussians).step_by(chunk) {
        chunks += 1;
        let mut out = Reduced::default();
        let end = (start + chunk).min(n_gaussians);
        let mut num = vec![0f64; (end - start) * dim];
        let mut den = vec![0f64; end - start];
        const BLOCK: usize = 1024;
        store.for_each(|c| {
            if c.dim != dim {
                bad_dim = Some(c.dim);
                return;
            }
            num.par_chunks_mut(BLOCK * dim)
                .zip(den.par_chunks_mut(BLOCK))
                .enumerate()
                .for_each(|(b, (nb, db))| {
                    let g0 = (start + b * BLOCK) as u32;
                    let g1 = g0 + db.len() as u32;
                    let lo = c.entries.partition_point(|e| e.gaussian < g0);
                    let hi = c.entries.partition_point(|e| e.gaussian < g1);
                    for e in &c.entries[lo..hi] {
                        let r = (e.gaussian - g0) as usize;
                        let a = e.weight as f64;
                        db[r] += a;
                        let ej =
                            &c.mask_embeddings[e.mask as usize * dim..(e.mask as usize + 1) * dim];
                        for (acc, &v) in nb[r * dim..(r + 1) * dim].iter_mut().zip(ej) {
                            *acc += a * v as f64;
                        }
                    }
                });
        })?;
        if let Some(d) = bad_dim {
            return Err(Error::Invalid(format!(
                "contribution of dim {d}, expected {dim}"
            )));
        }
        for (r, &d) in den.iter().enumerate() {
            // NaN sums count as unobserved too.
            if d.is_nan() || d < params.min_total_weight {
                continue;
            }
            let row = &num[r * dim..(r + 1) * dim];
            let norm = row.iter().map(|v| v * v).sum::<f64>().sqrt();
            if !norm.is_finite() || norm <= 1e-9 * d {
                continue;
            }
            out.ids.push((start + r) as u32);
            out.vectors.extend(row.iter().map(|v| (v / norm) as f32));
            out.total_weights.push(d as f32);
        }
        drop((num, den));
        sink(&out.ids, &out.vectors, &out.total_weights)?;
    }
    Ok(chunks)
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
}
