//! Exact and approximate text-query scans over the robot's stored embeddings.
//!
//! - [`VectorStore`]: all stored rows (f32, f16 or int8, as fetched, or codebook mixtures,
//!   [`mixture`]) with ids and means;
//! - [`scan`]: the exact multi-threaded scan: `Q` query vectors (1 ≤ Q ≤ [`MAX_QUERIES`]) dotted
//!   with every row in one pass over memory, scores combined per row (plain cosine for Q = 1, e.g.
//!   [`lerf_relevancy`] for a positive prompt plus canonical negatives), then a top-k and/or
//!   threshold selection (the paper's cosine ≥ 0.28 rule, SLAG Sec. IV) and an optional box on
//!   the means;
//! - [`naive_scan_f32`]: what a straightforward implementation does (scalar dot, all scores, full
//!   sort), the benchmark baseline;
//! - [`hnsw::ApproxIndex`]: the approximate (HNSW) index behind `index=hnsw`, backend
//!   `instant-distance` (always built) or `qdrant-edge` (cargo feature `qdrant-edge`), picked at
//!   run time ([`hnsw::HnswBackend`]);
//! - [`kernels`]: the inner loops (portable and per instruction set) and their dispatch;
//! - [`synthetic`]: deterministic synthetic stores for tests and the benchmark (`slag-edge bench`).
//!
//! Memory: a scan allocates only per-thread selection state (O(k) for top-k) and its output; it
//! never copies or dequantises the store.

pub mod hnsw;
pub mod kernels;
pub mod mixture;
pub mod select;
mod store;
pub mod synthetic;

use rayon::prelude::*;
use slag_common::Error;
use slag_common::shards::StoredVectors;

pub use kernels::{MAX_QUERIES, avx2_fma_available};
pub use select::{Hit, TopK};
pub use store::{NO_SEGMENT, VectorStore};

pub use kernels::{SimdLevel, simd_level};

/// Rows handed to one rayon task (a few hundred KiB to 4 MiB of rows at D = 512).
pub const CHUNK_ROWS: usize = 2048;

/// Combines the `Q` dot products of one row (`[Q]`, in the order of
/// [`ScanRequest::queries`]) into the row's score.
pub type Combiner<'a> = &'a (dyn Fn(&[f32]) -> f32 + Sync);

/// One scan: which queries, how to combine them, which rows to keep.
#[derive(Clone, Copy)]
pub struct ScanRequest<'a> {
    /// `Q` query vectors, each `[D]`, 1 ≤ Q ≤ [`MAX_QUERIES`]. Used as given (not normalised):
    /// pass unit vectors to get cosines. A zero query gives score 0 for every row.
    pub queries: &'a [&'a [f32]],
    /// Keep at most this many best rows (`Some(0)` keeps none).
    pub top_k: Option<usize>,
    /// Keep rows whose combined score is `>= threshold` (e.g. the paper's 0.28). `+inf` keeps
    /// nothing, `-inf` keeps every row; NaN is rejected.
    pub threshold: Option<f32>,
    /// Keep only rows whose mean lies in the closed box `(min, max)` (world frame, scene units).
    pub bbox: Option<([f32; 3], [f32; 3])>,
    /// Score of a row from its `Q` dot products. `None`: the dot product itself (Q = 1 only).
    pub combine: Option<Combiner<'a>>,
}

impl<'a> ScanRequest<'a> {
    /// The `k` rows with the highest cosine to one query.
    pub fn top_k(query: &'a [&'a [f32]], k: usize) -> Self {
        ScanRequest {
            queries: query,
            top_k: Some(k),
            threshold: None,
            bbox: None,
            combine: None,
        }
    }
    /// All rows with cosine `>= threshold` to one query.
    pub fn threshold(query: &'a [&'a [f32]], threshold: f32) -> Self {
        ScanRequest {
            queries: query,
            top_k: None,
            threshold: Some(threshold),
            bbox: None,
            combine: None,
        }
    }
}

impl std::fmt::Debug for ScanRequest<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ScanRequest")
            .field("queries", &self.queries.len())
            .field("top_k", &self.top_k)
            .field("threshold", &self.threshold)
            .field("bbox", &self.bbox)
            .field("combine", &self.combine.is_some())
            .finish()
    }
}

/// Temperature of LERF's pairwise softmax (LERF reference implementation: `softmax(10 · …)`).
pub const LERF_TEMPERATURE: f32 = 10.0;

/// LERF relevancy (Kerr et al. 2023, Eq. 1) from the dots `[positive, negative_1, …]`:
/// `min_i exp(τ·p) / (exp(τ·p) + exp(τ·n_i)) = 1 / (1 + exp(τ·(max_i n_i − p)))`, τ =
/// [`LERF_TEMPERATURE`]. In (0, 1); 0.5 means "as close to the prompt as to a canonical phrase".
/// With no negatives it returns 1. Use as [`ScanRequest::combine`].
pub fn lerf_relevancy(dots: &[f32]) -> f32 {
    let Some((&p, negs)) = dots.split_first() else {
        return 0.0;
    };
    let Some(worst) = negs.iter().copied().reduce(f32::max) else {
        return 1.0;
    };
    1.0 / (1.0 + (LERF_TEMPERATURE * (worst - p)).exp())
}

/// Selection state of one rayon task.
enum Acc {
    Top(TopK),
    All(Vec<Hit>),
}

impl Acc {
    fn new(top_k: Option<usize>) -> Acc {
        match top_k {
            Some(k) => Acc::Top(TopK::new(k)),
            None => Acc::All(Vec::new()),
        }
    }
    fn merge(self, other: Acc) -> Acc {
        match (self, other) {
            (Acc::Top(a), Acc::Top(b)) => Acc::Top(a.merge(b)),
            (Acc::All(mut a), Acc::All(mut b)) => {
                if a.len() < b.len() {
                    std::mem::swap(&mut a, &mut b);
                }
                a.append(&mut b);
                Acc::All(a)
            }
            // Both sides are created from the same request.
            (a, _) => a,
        }
    }
    fn into_sorted(self) -> Vec<Hit> {
        match self {
            Acc::Top(t) => t.into_sorted(),
            Acc::All(mut v) => {
                v.sort_unstable_by(select::rank_cmp);
                v
            }
        }
    }
}

fn check_queries(dim: usize, queries: &[&[f32]]) -> Result<(), Error> {
    if queries.is_empty() || queries.len() > MAX_QUERIES {
        return Err(Error::param(
            "queries",
            format!("{} query vectors", queries.len()),
            format!("1 to {MAX_QUERIES} query vectors per scan"),
        ));
    }
    for (i, q) in queries.iter().enumerate() {
        if q.len() != dim {
            return Err(Error::mismatch(
                slag_common::Mismatched::EmbeddingWidth,
                format!(
                    "query {i} has {} components but the store's rows have dim {dim}; encode \
                     the text with the model that produced the shards",
                    q.len()
                ),
            ));
        }
        if q.iter().any(|x| !x.is_finite()) {
            return Err(Error::query(
                "text",
                format!("query {i} contains NaN or infinite values; re-encode the text"),
            ));
        }
    }
    Ok(())
}

/// `$f::<Q>($store, [the Q queries], $extra)` with `Q = $queries.len()` (1..=[`MAX_QUERIES`],
/// checked by the caller): the scan kernels are compiled once per query count.
macro_rules! per_query_count {
    ($f:ident, $store:expr, $queries:expr, $extra:expr) => {{
        let q: &[&[f32]] = $queries;
        match q.len() {
            1 => $f::<1>($store, [q[0]], $extra),
            2 => $f::<2>($store, [q[0], q[1]], $extra),
            3 => $f::<3>($store, [q[0], q[1], q[2]], $extra),
            4 => $f::<4>($store, [q[0], q[1], q[2], q[3]], $extra),
            5 => $f::<5>($store, [q[0], q[1], q[2], q[3], q[4]], $extra),
            6 => $f::<6>($store, [q[0], q[1], q[2], q[3], q[4], q[5]], $extra),
            7 => $f::<7>($store, [q[0], q[1], q[2], q[3], q[4], q[5], q[6]], $extra),
            _ => $f::<8>(
                $store,
                [q[0], q[1], q[2], q[3], q[4], q[5], q[6], q[7]],
                $extra,
            ),
        }
    }};
}

/// Exact scan of every row (see the module doc): returns the selected rows, best first
/// (higher score, then lower row), deterministic for any thread count.
///
/// Score of row `i`: `combine(&[q_0·x_i, …, q_{Q-1}·x_i])`, or `q_0·x_i` without a combiner,
/// where `x_i` is the stored row dequantised (f16 → f32; int8 `q·scale`). Rows with a NaN score
/// are never returned. Work: one pass over `store.vector_bytes()` on all rayon threads; memory:
/// O(k) per task for top-k, plus the output.
///
/// Errors, each saying what to change: a query of the wrong width ([`Error::Mismatch`]) or with
/// non-finite values ([`Error::Query`]); [`Error::Param`] for no queries or more than
/// [`MAX_QUERIES`], Q > 1 without a combiner, neither `top_k` nor `threshold` set (that would
/// return the whole store), a NaN threshold, a box with a NaN bound or `min > max`.
pub fn scan(store: &VectorStore, req: &ScanRequest<'_>) -> Result<Vec<Hit>, Error> {
    check_queries(store.dim(), req.queries)?;
    if req.queries.len() > 1 && req.combine.is_none() {
        return Err(Error::param(
            "combine",
            "none",
            format!(
                "a score combiner (e.g. lerf_relevancy) for {} queries, or one query",
                req.queries.len()
            ),
        ));
    }
    if req.top_k.is_none() && req.threshold.is_none() {
        return Err(Error::param(
            "top_k",
            "none",
            "top_k, a threshold, or both (otherwise a scan returns every row)",
        ));
    }
    if req.threshold.is_some_and(f32::is_nan) {
        return Err(Error::param("threshold", f32::NAN, "a cosine such as 0.28"));
    }
    if let Some((lo, hi)) = req.bbox
        && (0..3).any(|a| lo[a].is_nan() || hi[a].is_nan() || lo[a] > hi[a])
    {
        return Err(Error::param(
            "bbox",
            format!("min {lo:?} max {hi:?}"),
            "min <= max on every axis, no NaN",
        ));
    }
    Ok(per_query_count!(scan_q, store, req.queries, req))
}

/// Scores row `i` from its `Q` dot products (`combine`d, or the first without a combiner) and
/// offers it to `acc` when it reaches `threshold` (a NaN score never does; without a threshold a
/// top-k selection takes it, a full list never does).
#[inline]
fn offer_row<const Q: usize>(
    acc: &mut Acc,
    i: usize,
    dots: &[f32; Q],
    combine: Option<Combiner<'_>>,
    threshold: Option<f32>,
) {
    let s = match combine {
        None => dots[0],
        Some(f) => f(dots),
    };
    if let Some(t) = threshold {
        // NaN scores are dropped too.
        if s.is_nan() || s < t {
            return;
        }
    }
    match acc {
        Acc::Top(t) => t.push(i, s),
        Acc::All(v) => {
            if !s.is_nan() {
                v.push(Hit { row: i, score: s })
            }
        }
    }
}

fn scan_q<const Q: usize>(store: &VectorStore, qs: [&[f32]; Q], req: &ScanRequest<'_>) -> Vec<Hit> {
    let n = store.len();
    let d = store.dim();
    let means = store.means();
    let bbox = req.bbox;
    let thr = req.threshold;
    let combine = req.combine;
    let top_k = req.top_k;
    if top_k == Some(0) || n == 0 {
        return Vec::new();
    }
    let inside = |i: usize| match bbox {
        None => true,
        Some((lo, hi)) => {
            let m = means[i];
            (0..3).all(|a| m[a] >= lo[a] && m[a] <= hi[a])
        }
    };
    let offer = |acc: &mut Acc, i: usize, dots: &[f32; Q]| offer_row(acc, i, dots, combine, thr);
    let cr = CHUNK_ROWS;
    let chunks = n.div_ceil(cr);
    let queries = kernels::Queries::new(qs);
    let keep: Option<kernels::Keep<'_>> = match bbox {
        Some(_) => Some(&inside),
        None => None,
    };
    // Mixture rows: the queries against the codebook once, then S multiply-adds per row.
    let mix = store.mixture().map(|m| (m, m.project(&queries)));
    (0..chunks)
        .into_par_iter()
        .fold(
            // Per task: its selection and one chunk's dot products (`[CHUNK_ROWS][Q]`).
            || (Acc::new(top_k), Vec::new()),
            |(mut acc, mut dots), c| {
                let start = c * cr;
                let end = (start + cr).min(n);
                dots.clear();
                dots.resize(end - start, [f32::NAN; Q]);
                match &mix {
                    Some((m, proj)) => m.scan_chunk::<Q>(proj, start, end, keep, &mut dots),
                    None => kernels::scan_chunk::<Q>(
                        store.vectors(),
                        kernels::RowSpan {
                            d,
                            start,
                            end,
                            keep,
                        },
                        &queries,
                        &mut dots,
                    ),
                }
                for (r, row_dots) in dots.iter().enumerate() {
                    let i = start + r;
                    if bbox.is_none() || inside(i) {
                        offer(&mut acc, i, row_dots);
                    }
                }
                (acc, dots)
            },
        )
        .map(|(acc, _)| acc)
        .reduce(|| Acc::new(top_k), Acc::merge)
        .into_sorted()
}

/// The score of every row (`[N]`, row order; NaN for a row without one, e.g. a mixture row of
/// zero norm): the same scores as [`scan`] with the same queries and combiner, without any
/// selection. For queries that need every score before selecting, such as the segment smoothing
/// of `smooth=segment` ([`slag_common::segments::rank_smoothed`]). Work: one pass over the store
/// on all rayon threads; memory: the `[N]` output plus one chunk's dot products per task.
///
/// Errors: as [`scan`] for the queries and the combiner (a query of the wrong width
/// [`Error::Mismatch`], non-finite values [`Error::Query`], no queries, more than
/// [`MAX_QUERIES`] or Q > 1 without a combiner [`Error::Param`]).
pub fn scores(
    store: &VectorStore,
    queries: &[&[f32]],
    combine: Option<Combiner<'_>>,
) -> Result<Vec<f32>, Error> {
    check_queries(store.dim(), queries)?;
    if queries.len() > 1 && combine.is_none() {
        return Err(Error::param(
            "combine",
            "none",
            format!(
                "a score combiner (e.g. lerf_relevancy) for {} queries, or one query",
                queries.len()
            ),
        ));
    }
    Ok(per_query_count!(scores_q, store, queries, combine))
}

fn scores_q<const Q: usize>(
    store: &VectorStore,
    qs: [&[f32]; Q],
    combine: Option<Combiner<'_>>,
) -> Vec<f32> {
    let d = store.dim();
    let queries = kernels::Queries::new(qs);
    let mix = store.mixture().map(|m| (m, m.project(&queries)));
    let mut out = vec![f32::NAN; store.len()];
    out.par_chunks_mut(CHUNK_ROWS).enumerate().for_each_init(
        Vec::new,
        |dots: &mut Vec<[f32; Q]>, (c, chunk)| {
            let start = c * CHUNK_ROWS;
            let end = start + chunk.len();
            dots.clear();
            dots.resize(end - start, [f32::NAN; Q]);
            match &mix {
                Some((m, proj)) => m.scan_chunk::<Q>(proj, start, end, None, dots),
                None => kernels::scan_chunk::<Q>(
                    store.vectors(),
                    kernels::RowSpan {
                        d,
                        start,
                        end,
                        keep: None,
                    },
                    &queries,
                    dots,
                ),
            }
            for (s, row) in chunk.iter_mut().zip(dots.iter()) {
                *s = match combine {
                    None => row[0],
                    Some(f) => f(row),
                };
            }
        },
    );
    out
}

/// The baseline a user would write first: single thread, each row dequantised to a fresh `f32`
/// vector ([`VectorStore::row_f32`]; borrowed as is for f32 stores), a scalar
/// `iter().zip().map().sum()` dot, every score collected into an `[N]` vector, a full sort, then
/// the first `top_k`. Same result order as [`scan`] (score desc, row asc).
///
/// Errors: [`Error::Mismatch`] for a query of the wrong width, [`Error::Query`] for non-finite values.
pub fn naive_scan_f32(store: &VectorStore, query: &[f32], top_k: usize) -> Result<Vec<Hit>, Error> {
    check_queries(store.dim(), &[query])?;
    let d = store.dim();
    let mut all: Vec<Hit> = Vec::with_capacity(store.len());
    for i in 0..store.len() {
        let score = match store.vectors() {
            StoredVectors::F32(v) => v[i * d..(i + 1) * d]
                .iter()
                .zip(query)
                .map(|(a, b)| a * b)
                .sum::<f32>(),
            _ => {
                let row = store.row_f32(i).unwrap_or_default();
                row.iter().zip(query).map(|(a, b)| a * b).sum::<f32>()
            }
        };
        if !score.is_nan() {
            all.push(Hit { row: i, score });
        }
    }
    all.sort_by(select::rank_cmp);
    all.truncate(top_k);
    Ok(all)
}

#[cfg(test)]
mod tests;
