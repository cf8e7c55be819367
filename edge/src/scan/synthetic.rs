//! Deterministic synthetic data for tests and the benchmark (`slag-edge bench`): random cluster
//! directions, the generators behind [`VectorStore::synthetic`], and a synthetic mixture store
//! ([`synthetic_mixture`]). The same seed gives the same values on every machine and thread count.

use half::f16;
use rayon::prelude::*;
use slag_common::Error;
use slag_common::rng::splitmix64 as splitmix;
use slag_common::shards::{Aabb, Dtype, MIXTURE_SHARD_FORMAT_VERSION, MixtureShard, ShardHeader};

use super::VectorStore;

/// Rows generated (and pushed) per block of [`synthetic_mixture`].
const BLOCK: usize = 1 << 16;

/// A synthetic mixture store of `n` rows over `atoms` codebook rows of width `dim`: atom `j`
/// lies in cluster `j mod clusters` (`normalise(centre + 0.75 · g / √D)`, as the dense synthetic
/// rows), each row mixes `slots` distinct atoms of one random cluster with random weights in
/// [0.05, 1) (f16, decreasing); means uniform in a 100 m cube, ids `0..n`.
///
/// Errors: [`Error::Param`] `atoms` for no clusters or fewer atoms than `clusters × slots`; as
/// [`VectorStore::new_mixture`] and [`VectorStore::push_mixture_shard`].
pub fn synthetic_mixture(
    n: usize,
    dim: usize,
    atoms: usize,
    slots: usize,
    centres: &[f32],
    clusters: usize,
    seed: u64,
) -> Result<VectorStore, Error> {
    if clusters == 0 || atoms < clusters * slots {
        return Err(Error::param(
            "atoms",
            atoms,
            format!("at least {clusters} clusters × {slots} slots (and at least one cluster)"),
        ));
    }
    let book = mixture_codebook(atoms, dim, centres, clusters, seed);
    let mut store = VectorStore::new_mixture(dim, slots, book, 0)?;
    store.reserve(n)?;
    let per_cluster = atoms / clusters;
    for start in (0..n).step_by(BLOCK) {
        let end = (start + BLOCK).min(n);
        let rows: Vec<(Vec<u32>, Vec<f16>, [f32; 3])> = (start..end)
            .into_par_iter()
            .map(|i| {
                let mut s = seed ^ (i as u64).wrapping_mul(0xD6E8_FEB8_6659_FD93) ^ 0x313;
                let c = (splitmix(&mut s) % clusters as u64) as usize;
                let mut picked: Vec<u32> = Vec::with_capacity(slots);
                while picked.len() < slots {
                    let r = (splitmix(&mut s) % per_cluster as u64) as usize;
                    let a = (c + clusters * r) as u32;
                    if !picked.contains(&a) {
                        picked.push(a);
                    }
                }
                let mut w: Vec<f32> = (0..slots).map(|_| 0.05 + 0.95 * uniform(&mut s)).collect();
                w.sort_by(|x, y| y.total_cmp(x));
                let mean = [0, 1, 2].map(|_| 100.0 * uniform(&mut s) - 50.0);
                (picked, w.into_iter().map(f16::from_f32).collect(), mean)
            })
            .collect();
        let shard = mixture_block(start, dim, slots, rows);
        store.push_mixture_shard(shard)?;
    }
    Ok(store)
}

/// The codebook of [`synthetic_mixture`], `[atoms][dim]`: atom `j` is
/// `normalise(centre_{j mod clusters} + 0.75 · g / √D)`, rounded through f16.
fn mixture_codebook(
    atoms: usize,
    dim: usize,
    centres: &[f32],
    clusters: usize,
    seed: u64,
) -> Vec<f32> {
    let mut book = vec![0.0f32; atoms * dim];
    book.par_chunks_mut(dim).enumerate().for_each(|(j, row)| {
        let mut s = seed ^ (j as u64).wrapping_mul(0xA24B_AED4_963E_E407) ^ 0xB00C;
        let c = j % clusters;
        let sigma = 0.75 / (dim as f32).sqrt();
        for (x, &m) in row.iter_mut().zip(&centres[c * dim..(c + 1) * dim]) {
            *x = m + sigma * fast_normal(&mut s);
        }
        let norm = row.iter().map(|x| x * x).sum::<f32>().sqrt();
        row.iter_mut()
            .for_each(|x| *x = f16::from_f32(*x / norm).to_f32());
    });
    book
}

/// The mixture shard of one block of [`synthetic_mixture`]'s rows, the first being row `start`
/// (tile `start / BLOCK`): each row's `slots` atoms, f16 weights and mean (scene frame).
fn mixture_block(
    start: usize,
    dim: usize,
    slots: usize,
    rows: Vec<(Vec<u32>, Vec<f16>, [f32; 3])>,
) -> MixtureShard {
    let end = start + rows.len();
    let mut shard = MixtureShard {
        header: ShardHeader {
            version: MIXTURE_SHARD_FORMAT_VERSION,
            scene_id: "synthetic".into(),
            model: "synthetic".into(),
            dim: dim as u32,
            dtype: Dtype::F16,
            count: (end - start) as u32,
            aabb: Aabb::default(),
            tile_id: (start / BLOCK) as u64,
        },
        slots: slots as u32,
        codebook_crc: 0,
        ids: (start as u32..end as u32).collect(),
        means: Vec::with_capacity(end - start),
        atoms: Vec::with_capacity((end - start) * slots),
        weights: Vec::with_capacity((end - start) * slots),
        scales: None,
        opacities: None,
        rotations: None,
        sh_dc: None,
        segments: None,
    };
    for (a, w, m) in rows {
        shard.atoms.extend(a);
        shard.weights.extend(w);
        shard.means.push(m);
    }
    shard
}

/// `clusters` random unit directions `[clusters * dim]`.
pub fn random_centres(dim: usize, clusters: usize, seed: u64) -> Vec<f32> {
    let mut s = seed ^ 0xC3C3_5EED;
    let mut c = vec![0.0f32; dim * clusters];
    for row in c.chunks_exact_mut(dim) {
        let mut norm = 0.0f32;
        for x in row.iter_mut() {
            *x = normal(&mut s);
            norm += *x * *x;
        }
        let inv = norm.sqrt().recip();
        row.iter_mut().for_each(|x| *x *= inv);
    }
    c
}

/// Uniform in `[0, 1)` with 24 random bits.
pub fn uniform(s: &mut u64) -> f32 {
    (splitmix(s) >> 40) as f32 / (1u64 << 24) as f32
}

/// Approximately standard normal (Irwin–Hall sum of 4 uniforms from one SplitMix64 draw,
/// rescaled to unit variance): cheap enough to generate gigabytes of rows.
pub fn fast_normal(s: &mut u64) -> f32 {
    let z = splitmix(s);
    let sum: u32 = (0..4).map(|k| ((z >> (16 * k)) & 0xFFFF) as u32).sum();
    // Mean of 4 U(0,1) is 2, variance 4/12.
    (sum as f32 / 65536.0 - 2.0) * 3.0f32.sqrt()
}

/// Standard normal (Box–Muller, one of the pair).
pub fn normal(s: &mut u64) -> f32 {
    let u1 = uniform(s).max(1e-7);
    let u2 = uniform(s);
    (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
}
