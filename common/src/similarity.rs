//! Scoring text against per-Gaussian embeddings: cosine similarity (the paper's query rule, default
//! threshold 0.28) over L2-normalised vectors.

use rayon::prelude::*;

use crate::{Error, Result};

/// Smallest L2 norm a vector may have and still be normalised ([`normalize_in_place`]).
pub const MIN_NORM: f64 = 1e-12;

/// A vector whose L2 norm is below [`MIN_NORM`] or not finite (zero, subnormal, NaN or infinite
/// components): it has no direction, and dividing by its norm would put NaN into cosine scores.
/// Each caller turns it into the error its user can act on (a prompt to rephrase, a model to
/// check).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DegenerateNorm(
    /// The norm found (computed in f64).
    pub f64,
);

impl std::fmt::Display for DegenerateNorm {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "norm {} (zero or not finite): no direction", self.0)
    }
}

/// Scales `v` in place to unit L2 norm, the one normalisation slag uses for image embeddings
/// (`E_j`), prompt embeddings and queries: the norm is summed in f64, then every component is
/// multiplied by the f32 reciprocal. Returns the norm.
///
/// Errors: [`DegenerateNorm`] when the norm is below [`MIN_NORM`] or not finite; `v` is then left
/// unchanged.
pub fn normalize_in_place(v: &mut [f32]) -> std::result::Result<f64, DegenerateNorm> {
    let norm = v
        .iter()
        .map(|&x| f64::from(x) * f64::from(x))
        .sum::<f64>()
        .sqrt();
    if !(norm.is_finite() && norm >= MIN_NORM) {
        return Err(DegenerateNorm(norm));
    }
    let inv = (1.0 / norm) as f32;
    v.iter_mut().for_each(|x| *x *= inv);
    Ok(norm)
}

/// A unit copy of a query (prompt) embedding, or [`Error::Query`] (field `text`) telling the user
/// to rephrase the prompt (a CLIP text tower can return a zero vector for an empty prompt).
pub fn unit_query(query: &[f32]) -> Result<Vec<f32>> {
    let mut q = query.to_vec();
    normalize_in_place(&mut q).map_err(|d| {
        Error::query(
            "text",
            format!(
                "the prompt's text embedding has {d}, so it cannot be compared with the Gaussians; \
             rephrase the prompt, or check the text model"
            ),
        )
    })?;
    Ok(q)
}

/// The paper's cosine threshold for "this Gaussian matches the prompt" (SLAG, Sec. IV).
pub const PAPER_THRESHOLD: f32 = 0.28;

/// Cosine similarity of every row of `vectors` (`[N * dim]`, rows L2-normalised) with `query`
/// (`[dim]`, any norm; it is normalised here). Returns `[N]` scores in [-1, 1].
///
/// Errors: `query.len() != dim`, a zero or non-finite query (a CLIP text tower can return a zero
/// vector for an empty prompt: the caller should reject the prompt, not rank noise).
pub fn cosine_scores(vectors: &[f32], dim: usize, query: &[f32]) -> Result<Vec<f32>> {
    if dim == 0 || query.len() != dim || !vectors.len().is_multiple_of(dim) {
        return Err(Error::mismatch(
            crate::Mismatched::EmbeddingWidth,
            format!(
                "query has {} components, embeddings have {dim} per row ({} values); use the text \
                 tower of the same CLIP model",
                query.len(),
                vectors.len()
            ),
        ));
    }
    let q = unit_query(query)?;
    Ok(vectors
        .par_chunks_exact(dim)
        .map(|row| dot(row, &q))
        .collect())
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

/// The largest `|a[i] - b[i]|` over the pairs of `a` and `b` (their common length; NaN
/// differences are passed over), 0 when there is none: how far two copies of the same rows
/// (e.g. an f16 round trip, two encodes) drift apart.
pub fn max_abs_difference(a: &[f32], b: &[f32]) -> f32 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

/// Indices of the `k` highest scores, best first (ties by lower index). NaN scores are ignored.
pub fn top_k(scores: &[f32], k: usize) -> Vec<(usize, f32)> {
    let mut idx: Vec<(usize, f32)> = scores
        .iter()
        .copied()
        .enumerate()
        .filter(|(_, s)| !s.is_nan())
        .collect();
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
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn one_normalisation_rule_at_the_extremes() {
        // Around MIN_NORM: twice it is accepted (and comes out unit), half of it is refused.
        let mut v = vec![2e-12f32, 0.0];
        assert!(normalize_in_place(&mut v).is_ok());
        assert!((v[0] - 1.0).abs() < 1e-6, "{v:?}");
        assert!(normalize_in_place(&mut [5e-13f32, 0.0]).is_err());
        for bad in [
            vec![0f32; 4],
            vec![1e-30f32; 4],
            vec![f32::NAN, 1.0],
            vec![f32::INFINITY, 0.0],
        ] {
            let mut w = bad.clone();
            assert!(normalize_in_place(&mut w).is_err(), "{bad:?}");
            assert_eq!(format!("{w:?}"), format!("{bad:?}"), "left unchanged");
            assert!(matches!(unit_query(&bad), Err(Error::Query { .. })));
        }
        // f32::MAX components: the f64 sum does not overflow.
        let mut big = vec![f32::MAX, f32::MAX];
        normalize_in_place(&mut big).expect("f32::MAX is normalisable in f64");
        assert!(
            (big[0] - std::f32::consts::FRAC_1_SQRT_2).abs() < 1e-6,
            "{big:?}"
        );
        let mut v = vec![3f32, 4.0];
        assert_eq!(normalize_in_place(&mut v), Ok(5.0));
        assert_eq!(v, vec![0.6, 0.8]);
    }

    #[test]
    fn cosine_matches_direct_computation() {
        let dim = 13;
        let rows: Vec<Vec<f32>> = (0..20)
            .map(|i| {
                let v: Vec<f32> = (0..dim)
                    .map(|d| ((i * 31 + d * 17) % 23) as f32 - 11.0)
                    .collect();
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

/// One Gaussian matching a query.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Match {
    /// Gaussian index in the source `.ply`.
    pub id: u32,
    /// Its mean, world frame, scene units.
    pub position: [f32; 3],
    /// Cosine similarity with the text embedding.
    pub score: f32,
}

/// Where the matches are, for a planner: count, axis-aligned bounds and centroid (world frame).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct MatchSummary {
    /// Number of matches.
    pub count: usize,
    /// `[min xyz, max xyz]`, `None` without matches.
    pub aabb: Option<[[f32; 3]; 2]>,
    /// Mean position, `None` without matches.
    pub centroid: Option<[f32; 3]>,
}

/// Ranks Gaussians against a text embedding: those with cosine ≥ `threshold` (if given), best
/// first, at most `top_k` (if given). `ids[i]`/`means[i]` describe row `i` of `vectors`.
pub fn rank(
    ids: &[u32],
    means: &[[f32; 3]],
    vectors: &[f32],
    dim: usize,
    query: &[f32],
    top_k: Option<usize>,
    threshold: Option<f32>,
) -> Result<(Vec<Match>, MatchSummary)> {
    if ids.len() != means.len() || ids.len() * dim != vectors.len() {
        return Err(Error::internal(
            "rank: ids, means and vectors disagree in length",
        ));
    }
    if let Some(t) = threshold.filter(|t| !t.is_finite()) {
        return Err(Error::param("threshold", t, "a finite cosine"));
    }
    let mut scores = cosine_scores(vectors, dim, query)?;
    if let Some(t) = threshold {
        scores
            .iter_mut()
            .filter(|s| **s < t)
            .for_each(|s| *s = f32::NAN);
    }
    let ranked = top_k_or_all(&scores, top_k);
    let matches: Vec<Match> = ranked
        .into_iter()
        .map(|(i, score)| Match {
            id: ids[i],
            position: means[i],
            score,
        })
        .collect();
    let summary = summarise(&matches);
    Ok((matches, summary))
}

fn top_k_or_all(scores: &[f32], k: Option<usize>) -> Vec<(usize, f32)> {
    top_k(scores, k.unwrap_or(scores.len()))
}

/// Count, AABB and centroid of `matches` (f64 sums).
pub fn summarise(matches: &[Match]) -> MatchSummary {
    if matches.is_empty() {
        return MatchSummary {
            count: 0,
            aabb: None,
            centroid: None,
        };
    }
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    let mut sum = [0f64; 3];
    for m in matches {
        for a in 0..3 {
            lo[a] = lo[a].min(m.position[a]);
            hi[a] = hi[a].max(m.position[a]);
            sum[a] += m.position[a] as f64;
        }
    }
    let n = matches.len() as f64;
    MatchSummary {
        count: matches.len(),
        aabb: Some([lo, hi]),
        centroid: Some([
            (sum[0] / n) as f32,
            (sum[1] / n) as f32,
            (sum[2] / n) as f32,
        ]),
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod rank_tests {
    use super::*;

    #[test]
    fn threshold_and_top_k_select_the_right_rows() {
        // 2-d unit vectors at angles 0, 60, 90, 180 degrees; query along x.
        let s3 = 3f32.sqrt() / 2.0;
        let vectors = [1.0, 0.0, 0.5, s3, 0.0, 1.0, -1.0, 0.0];
        let ids = [10, 11, 12, 13];
        let means = [
            [0.0, 0.0, 0.0],
            [2.0, 0.0, 0.0],
            [0.0, 4.0, 0.0],
            [9.0, 9.0, 9.0],
        ];
        let (m, s) = rank(&ids, &means, &vectors, 2, &[3.0, 0.0], None, Some(0.28)).unwrap();
        assert_eq!(m.iter().map(|m| m.id).collect::<Vec<_>>(), vec![10, 11]);
        assert_eq!(s.count, 2);
        assert_eq!(s.aabb, Some([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]]));
        assert_eq!(s.centroid, Some([1.0, 0.0, 0.0]));
        let (m, _) = rank(&ids, &means, &vectors, 2, &[1.0, 0.0], Some(3), None).unwrap();
        assert_eq!(m.iter().map(|m| m.id).collect::<Vec<_>>(), vec![10, 11, 12]);
        let (m, s) = rank(&ids, &means, &vectors, 2, &[1.0, 0.0], None, Some(2.0)).unwrap();
        assert!(m.is_empty() && s.aabb.is_none());
        assert!(rank(&ids, &means, &vectors, 2, &[1.0, 0.0], None, Some(f32::NAN)).is_err());
    }
}
