//! A robust per-Gaussian embedding: the weighted *mode* of the
//! mask embeddings that cover a Gaussian instead of their weighted mean.
//!
//! The paper's `E_k = Σ a_kj E_j / Σ a_kj` lets every mask that covers Gaussian `k` pull on it,
//! including masks that only graze it (a background mask bleeding over an object's edge, a whole
//! whose crop is dominated by other parts). The mode keeps the mean's weights but lets the masks
//! that agree with the current estimate count more, a few steps of weighted mean shift on the
//! unit sphere with a von Mises-Fisher kernel of concentration `κ`:
//!
//! ```text
//!   m_0     = Σ a_kj E_j / ‖·‖                                   (the paper's E_k)
//!   m_{t+1} = Σ a_kj exp(κ (cos(E_j, m_t) − 1)) E_j / ‖·‖
//! ```
//!
//! Training free and single pass over the images: it runs per Gaussian on the `(a_kj, E_j)` it
//! already gathered (here the mixture form's atoms).

use rayon::prelude::*;
use slag_common::mixture::{MixtureEmbeddings, UNUSED};
use slag_common::{Error, Result};

/// Mean-shift steps after the mean (the mode settles within a few on color-clip and CLIP-like
/// embeddings; each step costs `S × D` per Gaussian).
pub const MODE_ITERATIONS: usize = 3;

/// One Gaussian's mode from its atoms: `rows[s]` the unit mask embeddings (`[D]` each), `weights`
/// their `a_kj` (any positive scale). Returns the unit mode (`[D]`), or `None` when the weighted
/// sum vanishes.
pub fn mode_of(
    rows: &[&[f32]],
    weights: &[f32],
    kappa: f32,
    iterations: usize,
) -> Option<Vec<f32>> {
    let dim = rows.first()?.len();
    let mut m = vec![0f32; dim];
    let unit = |v: &mut Vec<f32>| {
        let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        if n.is_finite() && n > 0.0 {
            v.iter_mut().for_each(|x| *x /= n);
            true
        } else {
            false
        }
    };
    for (r, &w) in rows.iter().zip(weights) {
        m.iter_mut().zip(*r).for_each(|(a, &b)| *a += w * b);
    }
    if !unit(&mut m) {
        return None;
    }
    for _ in 0..iterations {
        let mut next = vec![0f32; dim];
        for (r, &w) in rows.iter().zip(weights) {
            let c: f32 = r.iter().zip(&m).map(|(a, b)| a * b).sum();
            let g = w * (kappa * (c - 1.0)).exp();
            next.iter_mut().zip(*r).for_each(|(a, &b)| *a += g * b);
        }
        if !unit(&mut next) {
            break;
        }
        m = next;
    }
    Some(m)
}

/// The mode ([`mode_of`]) of every Gaussian of a mixture, from its kept atoms and weights:
/// `[N × D]` row-major unit vectors in the mixture's Gaussian order.
///
/// Errors: `kappa` not finite or negative ([`Error::Param`] `kappa`), a Gaussian whose atoms
/// cancel ([`Error::Invalid`]).
pub fn mixture_modes(m: &MixtureEmbeddings, kappa: f32, iterations: usize) -> Result<Vec<f32>> {
    if !(kappa.is_finite() && kappa >= 0.0) {
        return Err(Error::param(
            "kappa",
            kappa,
            "a finite mode concentration κ ≥ 0 (0 = the mean)",
        ));
    }
    let (dim, keep) = (m.dim, m.keep);
    let rows: Vec<Option<Vec<f32>>> = m
        .atoms
        .par_chunks_exact(keep)
        .zip(m.weights.par_chunks_exact(keep))
        .map(|(atoms, ws)| {
            let (rows, w): (Vec<&[f32]>, Vec<f32>) = atoms
                .iter()
                .zip(ws)
                .filter(|&(&a, _)| a != UNUSED)
                .map(|(&a, &w)| (&m.codebook[a as usize * dim..(a as usize + 1) * dim], w))
                .unzip();
            mode_of(&rows, &w, kappa, iterations)
        })
        .collect();
    let mut out = Vec::with_capacity(m.len() * dim);
    for (i, r) in rows.into_iter().enumerate() {
        let r = r.ok_or_else(|| {
            Error::Invalid(format!(
                "Gaussian {} has mask embeddings that cancel: no mode",
                m.gaussian_ids.get(i).copied().unwrap_or(u32::MAX)
            ))
        })?;
        out.extend(r);
    }
    Ok(out)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)] // tests fail loudly on purpose
mod tests {
    use super::*;

    #[test]
    fn mode_follows_the_agreeing_majority_and_zero_kappa_is_the_mean() {
        let a = [1.0f32, 0.0, 0.0];
        let b = [0.0f32, 1.0, 0.0];
        let near_a = [0.8f32, 0.6, 0.0];
        let rows: Vec<&[f32]> = vec![&a, &near_a, &b];
        // b outweighs a alone, but a and near_a agree.
        let w = [1.0, 1.0, 1.5];
        let mean = mode_of(&rows, &w, 0.0, 3).unwrap();
        let mode = mode_of(&rows, &w, 10.0, 3).unwrap();
        // The mean leans to b (y > x), the mode to the a cluster (x > y).
        assert!(mean[1] > mean[0], "{mean:?}");
        assert!(mode[0] > mode[1], "{mode:?}");
        let n: f32 = mode.iter().map(|v| v * v).sum();
        assert!((n - 1.0).abs() < 1e-5);
        let c = [-1.0f32, 0.0, 0.0];
        assert!(mode_of(&[&a, &c], &[1.0, 1.0], 5.0, 3).is_none());
    }
}
