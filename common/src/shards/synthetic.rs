//! Deterministic synthetic scenes: clustered means on a 2.5D ground plane and random unit
//! vectors, for tests and scale measurements while real encoder output is not at hand.

use super::GaussianSource;
use crate::embeddings::Embeddings;
use crate::rng::splitmix64 as splitmix;

fn uniform(s: &mut u64) -> f32 {
    (splitmix(s) >> 40) as f32 / (1u64 << 24) as f32
}

fn normal(s: &mut u64) -> f32 {
    let u1 = uniform(s).max(1e-7);
    let u2 = uniform(s);
    (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
}

/// Model id of stores made from synthetic vectors (`partition --synthetic`): no CLIP model made
/// them, so any text tower of the right width may query them.
pub const SYNTHETIC_MODEL_ID: &str = "synthetic";

/// A synthetic scene: `n` Gaussians whose means lie in `clusters` Gaussian blobs (σ 0.5..8 m)
/// scattered over a `extent`×`extent` m ground plane with a little height (z up, world frame),
/// plus 10 % uniform background; vectors are generated from `(seed, i)` on demand.
#[derive(Debug, Clone)]
pub struct SyntheticScene {
    /// Ids `0..n` spaced by 2 (every other `.ply` Gaussian "observed").
    pub ids: Vec<u32>,
    /// Means, world frame, z up.
    pub means: Vec<[f32; 3]>,
    /// Embedding width.
    pub dim: usize,
    /// Seed of the vectors.
    pub seed: u64,
}

impl SyntheticScene {
    /// Generates the means (vectors stay implicit).
    pub fn new(n: usize, dim: usize, clusters: usize, extent: f32, seed: u64) -> SyntheticScene {
        let mut s = seed ^ 0x5EED;
        let centres: Vec<([f32; 2], f32)> = (0..clusters.max(1))
            .map(|_| {
                (
                    [uniform(&mut s) * extent, uniform(&mut s) * extent],
                    0.5 + 7.5 * uniform(&mut s),
                )
            })
            .collect();
        let means = (0..n)
            .map(|_| {
                let z = 0.3 * normal(&mut s) + 1.0;
                if uniform(&mut s) < 0.1 {
                    [uniform(&mut s) * extent, uniform(&mut s) * extent, z]
                } else {
                    let k = (splitmix(&mut s) % centres.len() as u64) as usize;
                    let (c, sigma) = centres[k];
                    [
                        c[0] + sigma * normal(&mut s),
                        c[1] + sigma * normal(&mut s),
                        z,
                    ]
                }
            })
            .collect();
        SyntheticScene {
            ids: (0..n as u32).map(|i| i.wrapping_mul(2)).collect(),
            means,
            dim,
            seed,
        }
    }

    /// Materialises the vectors into an [`Embeddings`] (small scenes only: N·D·4 bytes).
    pub fn to_embeddings(&self) -> Embeddings {
        let mut vectors = vec![0.0f32; self.means.len() * self.dim];
        for (i, row) in vectors.chunks_exact_mut(self.dim.max(1)).enumerate() {
            self.vector_into(i, row);
        }
        Embeddings {
            ids: self.ids.clone(),
            means: self.means.clone(),
            dim: self.dim,
            vectors,
            total_weights: vec![1.0; self.means.len()],
            model: SYNTHETIC_MODEL_ID.into(),
            scene_gaussians: 2 * self.means.len() as u64,
            source_ply: "synthetic".into(),
        }
    }
}

impl GaussianSource for SyntheticScene {
    super::columns_from_fields!(ids: ids, model = "synthetic");
    fn vector_into(&self, i: usize, out: &mut [f32]) {
        let mut s = self.seed.wrapping_mul(0x100_0000_01B3) ^ (i as u64).wrapping_mul(0x9E37_79B9);
        let mut norm = 0.0f32;
        for x in out.iter_mut() {
            // Uniform in [-1, 1): cheap and enough for a unit direction in tests.
            *x = uniform(&mut s) * 2.0 - 1.0;
            norm += *x * *x;
        }
        let inv = if norm > 0.0 { norm.sqrt().recip() } else { 0.0 };
        out.iter_mut().for_each(|x| *x *= inv);
    }
}
