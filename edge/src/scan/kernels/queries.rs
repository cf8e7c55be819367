//! The queries of one scan ([`Queries`], at most [`MAX_QUERIES`]), the row filter ([`Keep`]), and
//! the three-term int8 split of the queries that the integer kernels use ([`split_queries`]).

/// Largest number of queries scored in one pass.
pub const MAX_QUERIES: usize = 8;

/// The `Q` query vectors of one scan (each `[d]`), with what some kernels derive from them once
/// per scan rather than once per chunk: the three-term int8 split of the integer dot-product
/// kernels (SDOT / VPDPBUSD), computed on first use by whichever thread needs it.
pub struct Queries<'a, const Q: usize> {
    qs: [&'a [f32]; Q],
    split: std::sync::OnceLock<Split<Q>>,
}

/// Query split of the integer kernels: `terms` is `[Q · 3 · d]` (query-major, then term), `steps`
/// the three steps per query (see [`split_queries`]).
pub(super) struct Split<const Q: usize> {
    pub terms: Vec<i8>,
    pub steps: [[f32; 3]; Q],
}

impl<'a, const Q: usize> Queries<'a, Q> {
    /// Wraps `Q` query vectors (used as given; every one must have the store's width `d`, which
    /// [`scan_chunk_at`] checks).
    pub fn new(qs: [&'a [f32]; Q]) -> Self {
        Queries {
            qs,
            split: std::sync::OnceLock::new(),
        }
    }
    /// The query vectors.
    pub fn vectors(&self) -> &[&'a [f32]; Q] {
        &self.qs
    }
    /// The int8 split for rows of width `d` (computed once).
    pub(super) fn split(&self, d: usize) -> &Split<Q> {
        self.split.get_or_init(|| {
            let (terms, steps) = split_queries(&self.qs, d);
            Split { terms, steps }
        })
    }
}

/// Row filter of a chunk scan: `true` keeps row `i` (global row index).
pub type Keep<'a> = &'a (dyn Fn(usize) -> bool + Sync);

/// The rows one chunk scan scores: rows `start..end` (global row indices, `start <= end`) of
/// width `d`, those with `keep(i)` (every row when `keep` is `None`).
#[derive(Clone, Copy)]
pub struct RowSpan<'a> {
    /// Row width D (values per row).
    pub d: usize,
    /// First row.
    pub start: usize,
    /// One past the last row.
    pub end: usize,
    /// Row filter; `None` scores every row.
    pub keep: Option<Keep<'a>>,
}

impl RowSpan<'_> {
    /// `true` when row `i` is to be scored (no filter, or `keep(i)`).
    #[inline(always)]
    pub fn keeps(&self, i: usize) -> bool {
        self.keep.is_none_or(|k| k(i))
    }
}

/// Splits every query (`[d]`, finite) into three int8 vectors `a, b, c` and steps
/// `[s1, s2, s3]` with `y ≈ s1·a + s2·b + s3·c` (`simd` module doc). Returns the terms as one
/// `[Q · 3 · d]` vector (query-major, then term) and the steps per query. A zero query gives
/// zero terms and steps.
pub(super) fn split_queries<const Q: usize>(
    qs: &[&[f32]; Q],
    d: usize,
) -> (Vec<i8>, [[f32; 3]; Q]) {
    let mut terms = vec![0i8; Q * 3 * d];
    let mut steps = [[0.0f32; 3]; Q];
    for (k, y) in qs.iter().enumerate() {
        let m = y.iter().fold(0.0f64, |a, &v| a.max((v as f64).abs()));
        if m == 0.0 || !m.is_finite() {
            continue;
        }
        // The steps are rounded to f32 first (the kernel multiplies by the f32 values), so the
        // residual of each term is taken against the step that is actually applied.
        let s =
            [m / 127.0, m / (127.0 * 254.0), m / (127.0 * 254.0 * 254.0)].map(|x| x as f32 as f64);
        for (j, &v) in y.iter().take(d).enumerate() {
            let mut r = v as f64;
            for t in 0..3 {
                let a = (r / s[t]).round().clamp(-127.0, 127.0);
                terms[(k * 3 + t) * d + j] = a as i8;
                r -= a * s[t];
            }
        }
        steps[k] = [s[0] as f32, s[1] as f32, s[2] as f32];
    }
    (terms, steps)
}
