//! Scoring text against per-Gaussian embeddings: cosine similarity (the paper's query rule, default
//! threshold 0.28) over L2-normalised vectors.

use rayon::prelude::*;

use crate::{Error, Result};

/// The paper's cosine threshold for "this Gaussian matches the prompt" (SLAG, Sec. IV).
pub const PAPER_THRESHOLD: f32 = 0.28;

/// Cosine similarity of every row of `vectors` (`[N * dim]`, rows L2-normalised) with `query`
/// (`[dim]`, any norm; it is normalised here). Returns `[N]` scores in [-1, 1].
///
/// Errors: `query.len() != dim`, a zero or non-finite query (a CLIP text tower can return a zero
/// vector for an empty prompt: the caller should reject the prompt, not rank noise).
pub fn cosine_scores(vectors: &[f32], dim: usize, query: &[f32]) -> Result<Vec<f32>> {
    if dim == 0 || query.len() != dim || vectors.len() % dim != 0 {
        return Err(Error::Invalid(format!(
            "query has {} components, embeddings have {dim} per row ({} values); use the text tower of the same CLIP model",
            query.len(),
            vectors.len()
        )));
    }
    let norm = query.iter().map(|&q| q as f64 * q as f64).sum::<f64>().sqrt();
    if !norm.is_finite() || norm < 1e-12 {
        return Err(Error::Invalid(
            "the text embedding is zero or not finite; rephrase the prompt".into(),
        ));
    }
    let q: Vec<f32> = query.iter().map(|&v| (v as f64 / norm) as f32).collect();
    Ok(vectors.par_chunks_exact(dim).map(|row| dot(row, &q)).collect())
}

/// Dot product with 8 independent accumulators (vectorises well).
pub fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for i in 0..8 {
            acc[i] += x[i] * y[i];
        }
    }
    let tail: f32 = ra.iter().zip(rb).map(|(x, y)| x * y).sum();
    acc.iter().sum::<f32>() + tail
}

/// Indices of the `k` highest scores, best first (ties by lower index). NaN scores are ignored.
pub fn top_k(scores: &[f32], k: usize) -> Vec<(usize, f32)> {
    let mut idx: Vec<(usize, f32)> =
        scores.iter().copied().enumerate().filter(|(_, s)| !s.is_nan()).collect();
    let k = k.min(idx.len());
    if k == 0 {
        return Vec::new();
    }
    let cmp = |a: &(usize, f32), b: &(usize, f32)| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0));
    if k < idx.len() {
        idx.select_nth_unstable_by(k - 1, cmp);
        idx.truncate(k);
    }
    idx.sort_unstable_by(cmp);
    idx
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cosine_matches_direct_computation() {
        let dim = 13;
        let rows: Vec<Vec<f32>> = (0..20)
            .map(|i| {
                let v: Vec<f32> = (0..dim).map(|d| ((i * 31 + d * 17) % 23) as f32 - 11.0).collect();
                let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
                v.into_iter().map(|x| x / n).collect()
            })
            .collect();
        let flat: Vec<f32> = rows.concat();
        let query: Vec<f32> = (0..dim).map(|d| d as f32 * 0.3 - 1.0).collect();
        let scores = cosine_scores(&flat, dim, &query).unwrap();
        let qn = query.iter().map(|x| x * x).sum::<f32>().sqrt();
        for (r, s) in rows.iter().zip(&scores) {
            let expect: f32 = r.iter().zip(&query).map(|(a, b)| a * b).sum::<f32>() / qn;
            assert!((expect - s).abs() < 1e-5);
        }
    }

    #[test]
    fn zero_query_and_wrong_dim_are_errors() {
        let flat = vec![1.0, 0.0, 0.0, 1.0];
        assert!(cosine_scores(&flat, 2, &[0.0, 0.0]).is_err());
        assert!(cosine_scores(&flat, 2, &[1.0, 0.0, 0.0]).is_err());
        assert!(cosine_scores(&flat, 2, &[f32::NAN, 1.0]).is_err());
    }

    #[test]
    fn top_k_orders_and_breaks_ties_by_index() {
        let s = [0.1, 0.9, f32::NAN, 0.9, -0.2, 0.5];
        assert_eq!(top_k(&s, 3), vec![(1, 0.9), (3, 0.9), (5, 0.5)]);
        assert_eq!(top_k(&s, 100).len(), 5);
        assert!(top_k(&s, 0).is_empty());
    }
}
