//! Inner loops: dot products of `Q` query vectors (1 ≤ Q ≤ [`MAX_QUERIES`]) with one stored row,
//! for `f32`, `f16` and symmetric-int8 rows.
//!
//! Every kernel is written so that LLVM vectorises it without intrinsics: one dot product walks
//! the row in fixed-size array blocks of [`LANES`] values into [`LANES`] independent accumulators
//! (4 AVX2 / 8 SSE-NEON registers), reduced once at the end. A row is fetched from DRAM once per
//! scan; for `Q > 1` the other `Q - 1` dot products re-read it from L1 (f16/int8 rows are first
//! converted per [`BLOCK`] into a stack buffer, so conversion is paid once), which is what makes a
//! LERF query (positive + 4 canonical negatives) cost one pass over memory.
//!
//! - `f32`: multiply-add (fused on aarch64 and in the AVX2 path).
//! - `f16`: converted per block into a stack buffer: with `half`'s
//!   [`convert_to_f32_slice`](half::slice::HalfFloatSliceExt::convert_to_f32_slice) (F16C on
//!   x86_64 / FP16 on aarch64, detected at run time) in the portable path, with inlined F16C
//!   `vcvtph2ps` (8 values per instruction) in the AVX2 path.
//! - `int8`: `q as f32 · query` accumulated, the per-row scale applied once at the end
//!   (`dot = scale · Σ q_j x_j`).
//!
//! Dispatch ([`scan_chunk`]): on x86_64 CPUs with AVX2 + FMA the loops are compiled a second time
//! with those features enabled and selected at run time ([`simd_level`]); elsewhere the build
//! target's baseline is used (aarch64 baseline already has NEON and FMA).
//!
//! Accumulation order differs from a sequential sum (32 partial sums), so results differ from a
//! scalar `f64` reference by normal `f32` rounding only (≈1e-6 relative for D = 512).

use half::f16;
use half::slice::HalfFloatSliceExt;
use slag_common::shards::StoredVectors;

/// Independent accumulators of one dot product (4 AVX2 registers, 8 SSE/NEON registers): enough
/// parallel chains to hide the add/FMA latency.
pub const LANES: usize = 32;
/// Largest number of queries scored in one pass.
pub const MAX_QUERIES: usize = 8;
/// Values of a row converted to f32 per block (a 1 KiB stack buffer, stays in L1).
pub const BLOCK: usize = 256;

/// `a · b + c`, fused (one rounding) when `FMA` (only instantiated where the CPU has FMA:
/// otherwise `mul_add` would be a libm call).
#[inline(always)]
fn madd<const FMA: bool>(a: f32, b: f32, c: f32) -> f32 {
    if FMA { a.mul_add(b, c) } else { c + a * b }
}

/// `Σ_j conv(x[j]) · y[j]` over `min(x.len(), y.len())` values with [`LANES`] accumulators.
///
/// Written for LLVM's loop vectoriser: fixed-size array blocks (`as_chunks`), one flat
/// accumulator array, a plain sum at the end (a pairwise reduction tree here makes LLVM fall
/// back to 2-wide vectors).
#[inline(always)]
fn dot_conv<T: Copy, const FMA: bool>(x: &[T], y: &[f32], conv: impl Fn(T) -> f32) -> f32 {
    let n = x.len().min(y.len());
    let (xb, xr) = x[..n].as_chunks::<LANES>();
    let (yb, yr) = y[..n].as_chunks::<LANES>();
    let mut a = [0.0f32; LANES];
    for (r, q) in xb.iter().zip(yb) {
        for l in 0..LANES {
            a[l] = madd::<FMA>(conv(r[l]), q[l], a[l]);
        }
    }
    let mut t = 0.0f32;
    for (&r, &q) in xr.iter().zip(yr) {
        t = madd::<FMA>(conv(r), q, t);
    }
    a.iter().sum::<f32>() + t
}

/// Accumulators per query in the multi-query loop ([`LANES_MULTI`] · Q ≤ 128 floats: 16 AVX2
/// registers at Q = 8).
pub const LANES_MULTI: usize = 16;

/// `out[q] += Σ_j x[j] · qs[q][off + j]` for all `Q` queries in one sweep over `x`: each block of
/// `x` is loaded once and multiplied into `Q` accumulator arrays (`std::array::from_fn` keeps
/// them as whole vectors for LLVM).
#[inline(always)]
fn dots_multi<const Q: usize, const FMA: bool>(
    x: &[f32],
    qs: &[&[f32]; Q],
    off: usize,
    out: &mut [f32],
) {
    const W: usize = LANES_MULTI;
    let n = x.len();
    let (xb, xr) = x.as_chunks::<W>();
    let mut qb: [&[[f32; W]]; Q] = [&[]; Q];
    let mut qt: [&[f32]; Q] = [&[]; Q];
    for q in 0..Q {
        let (b, t) = qs[q][off..off + n].as_chunks::<W>();
        qb[q] = b;
        qt[q] = t;
    }
    let mut acc = [[0.0f32; W]; Q];
    for (c, r) in xb.iter().enumerate() {
        for q in 0..Q {
            let y = &qb[q][c];
            let a = &mut acc[q];
            *a = std::array::from_fn(|l| madd::<FMA>(r[l], y[l], a[l]));
        }
    }
    for q in 0..Q {
        let mut t = 0.0f32;
        for (&v, &y) in xr.iter().zip(qt[q]) {
            t = madd::<FMA>(v, y, t);
        }
        out[q] += acc[q].iter().sum::<f32>() + t;
    }
}

/// Dot products of one `f32` row with `Q` queries: `out[q] = Σ_j row[j] · qs[q][j]`
/// (fused multiply-add when `FMA`), the row read once.
///
/// Shapes: `row.len() == qs[q].len() == D`, `out.len() >= Q`.
#[inline(always)]
pub fn dots_f32<const Q: usize, const FMA: bool>(row: &[f32], qs: &[&[f32]; Q], out: &mut [f32]) {
    if Q == 1 {
        out[0] = dot_conv::<f32, FMA>(row, qs[0], |x| x);
    } else {
        out[..Q].fill(0.0);
        dots_multi::<Q, FMA>(row, qs, 0, out);
    }
}

/// Dot products of one IEEE-half row with `Q` f32 queries: the row is converted in blocks of
/// [`BLOCK`] values into `buf` by `convert(src, dst)` (equal lengths; e.g.
/// [`convert_f16_portable`]), then the f32 loop runs on the buffer for every query.
///
/// Shapes: `row.len() == qs[q].len() == D`, `out.len() >= Q`.
#[inline(always)]
pub fn dots_f16<const Q: usize, const FMA: bool>(
    row: &[f16],
    qs: &[&[f32]; Q],
    buf: &mut [f32; BLOCK],
    out: &mut [f32],
    convert: impl Fn(&[f16], &mut [f32]),
) {
    out[..Q].fill(0.0);
    let mut off = 0;
    for block in row.chunks(BLOCK) {
        let b = &mut buf[..block.len()];
        convert(block, b);
        if Q == 1 {
            out[0] += dot_conv::<f32, FMA>(b, &qs[0][off..], |x| x);
        } else {
            dots_multi::<Q, FMA>(b, qs, off, out);
        }
        off += block.len();
    }
}

/// Converts f16 values to f32 (`src.len() == dst.len()`) with `half`'s slice conversion (F16C on
/// x86_64 / FP16 on aarch64 when present at run time, exact software conversion otherwise).
#[inline(always)]
pub fn convert_f16_portable(src: &[f16], dst: &mut [f32]) {
    src.convert_to_f32_slice(dst);
}

/// Dot products of one symmetric-int8 row (value `q_j · scale`) with `Q` f32 queries:
/// `out[q] = scale · Σ_j q_j · qs[q][j]` (scale applied once per row). For Q > 1 the row is
/// converted once per [`BLOCK`] into `buf` and reused by every query.
///
/// Shapes: `row.len() == qs[q].len() == D`, `out.len() >= Q`.
#[inline(always)]
pub fn dots_i8<const Q: usize, const FMA: bool>(
    row: &[i8],
    scale: f32,
    qs: &[&[f32]; Q],
    buf: &mut [f32; BLOCK],
    out: &mut [f32],
) {
    if Q == 1 {
        out[0] = scale * dot_conv::<i8, FMA>(row, qs[0], |x| x as f32);
        return;
    }
    out[..Q].fill(0.0);
    let mut off = 0;
    for block in row.chunks(BLOCK) {
        let b = &mut buf[..block.len()];
        for (d, &x) in b.iter_mut().zip(block) {
            *d = x as f32;
        }
        dots_multi::<Q, FMA>(b, qs, off, out);
        off += block.len();
    }
    for o in &mut out[..Q] {
        *o *= scale;
    }
}

/// The `Q` query vectors of one scan (each `[d]`), with what some kernels derive from them once
/// per scan rather than once per chunk: the three-term int8 split of the integer dot-product
/// kernels (SDOT / VPDPBUSD), computed on first use by whichever thread needs it.
pub struct Queries<'a, const Q: usize> {
    qs: [&'a [f32]; Q],
    split: std::sync::OnceLock<Split<Q>>,
}

/// Query split of the integer kernels: `terms` is `[Q · 3 · d]` (query-major, then term), `steps`
/// the three steps per query (see `simd::split_queries`).
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
            let (terms, steps) = super::simd::split_queries(&self.qs, d);
            Split { terms, steps }
        })
    }
}

/// Row filter of a chunk scan: `true` keeps row `i` (global row index).
pub type Keep<'a> = &'a (dyn Fn(usize) -> bool + Sync);

/// Scores rows `start..end` of `vectors` (`[N * d]` as stored) against `qs` into `out[r]` (row
/// `start + r`) for every row with `keep(i)` (all rows when `None`; other entries are left
/// untouched). Portable body; `FMA` selects fused multiply-add (only where the CPU has it).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn chunk_impl<const Q: usize, const FMA: bool>(
    vectors: &StoredVectors,
    d: usize,
    start: usize,
    end: usize,
    qs: &[&[f32]; Q],
    keep: Option<Keep<'_>>,
    out: &mut [[f32; Q]],
    convert: impl Fn(&[f16], &mut [f32]) + Copy,
) {
    let kept = |i: usize| keep.is_none_or(|k| k(i));
    match vectors {
        StoredVectors::F32(v) => {
            let rows = v[start * d..end * d].chunks_exact(d);
            for (r, (row, o)) in rows.zip(out.iter_mut()).enumerate() {
                if kept(start + r) {
                    dots_f32::<Q, FMA>(row, qs, o);
                }
            }
        }
        StoredVectors::F16(v) => {
            let mut buf = [0.0f32; BLOCK];
            let rows = v[start * d..end * d].chunks_exact(d);
            for (r, (row, o)) in rows.zip(out.iter_mut()).enumerate() {
                if kept(start + r) {
                    dots_f16::<Q, FMA>(row, qs, &mut buf, o, convert);
                }
            }
        }
        StoredVectors::I8 { q, scales } => {
            let mut buf = [0.0f32; BLOCK];
            let rows = q[start * d..end * d].chunks_exact(d);
            let rows = rows.zip(&scales[start..end]).zip(out.iter_mut());
            for (r, ((row, &s), o)) in rows.enumerate() {
                if kept(start + r) {
                    dots_i8::<Q, FMA>(row, s, qs, &mut buf, o);
                }
            }
        }
    }
}

/// Which instruction set the scan loops run with (see [`simd_level`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SimdLevel {
    /// The build target's baseline, auto-vectorised portable loops (SSE2 on x86_64; NEON + FMA
    /// on aarch64); f16 rows converted per [`BLOCK`] through a stack buffer.
    Baseline,
    /// x86_64 AVX2 + FMA + F16C intrinsics (8 lanes), selected at run time.
    Avx2Fma,
    /// x86_64 AVX-512F intrinsics (16 lanes; `vcvtph2ps zmm` for f16), selected at run time.
    Avx512,
    /// aarch64 NEON intrinsics (FMLA; FCVTL for f16; SXTL + SCVTF for int8).
    Neon,
    /// aarch64 NEON with the dot-product extension: as [`SimdLevel::Neon`], int8 rows with SDOT
    /// against three-term int8 splits of the queries; selected at run time.
    NeonDotprod,
    /// x86_64 AVX-512 with VNNI: as [`SimdLevel::Avx512`], int8 rows with `vpdpbusd` against
    /// three-term int8 splits of the queries; selected at run time.
    Avx512Vnni,
}

impl SimdLevel {
    /// Every level, best last per architecture.
    pub const ALL: [SimdLevel; 6] = [
        SimdLevel::Baseline,
        SimdLevel::Avx2Fma,
        SimdLevel::Avx512,
        SimdLevel::Avx512Vnni,
        SimdLevel::Neon,
        SimdLevel::NeonDotprod,
    ];

    /// `true` when this build target and CPU can run the level (detected at run time with
    /// `is_x86_feature_detected!` / `is_aarch64_feature_detected!`).
    pub fn available(self) -> bool {
        match self {
            SimdLevel::Baseline => true,
            SimdLevel::Avx2Fma => avx2_fma_available(),
            #[cfg(target_arch = "x86_64")]
            SimdLevel::Avx512 => {
                avx2_fma_available() && std::arch::is_x86_feature_detected!("avx512f")
            }
            #[cfg(target_arch = "x86_64")]
            SimdLevel::Avx512Vnni => {
                SimdLevel::Avx512.available()
                    && std::arch::is_x86_feature_detected!("avx512bw")
                    && std::arch::is_x86_feature_detected!("avx512vnni")
            }
            #[cfg(target_arch = "aarch64")]
            SimdLevel::Neon => true,
            #[cfg(target_arch = "aarch64")]
            SimdLevel::NeonDotprod => std::arch::is_aarch64_feature_detected!("dotprod"),
            #[allow(unreachable_patterns)]
            _ => false,
        }
    }

    /// The levels this CPU can run, baseline first, best last.
    pub fn available_levels() -> Vec<SimdLevel> {
        SimdLevel::ALL
            .into_iter()
            .filter(|l| l.available())
            .collect()
    }

    /// Parses `baseline`, `avx2`, `avx512`, `avx512vnni`, `neon`, `dotprod` (case-insensitive).
    pub fn from_name(s: &str) -> Option<SimdLevel> {
        match s.to_ascii_lowercase().as_str() {
            "baseline" => Some(SimdLevel::Baseline),
            "avx2" | "avx2fma" => Some(SimdLevel::Avx2Fma),
            "avx512" => Some(SimdLevel::Avx512),
            "avx512vnni" | "vnni" => Some(SimdLevel::Avx512Vnni),
            "neon" => Some(SimdLevel::Neon),
            "dotprod" | "neondotprod" => Some(SimdLevel::NeonDotprod),
            _ => None,
        }
    }
}

/// The level used by [`scan`](super::scan): the best available one (AVX-512F, else AVX2 + FMA +
/// F16C on x86_64; NEON + dotprod, else NEON on aarch64), unless the environment variable
/// `SLAG_SCAN_SIMD` names an available level (`baseline`, `avx2`, `avx512`, `neon`, `dotprod`;
/// for measurements). Detected once per process.
pub fn simd_level() -> SimdLevel {
    static LEVEL: std::sync::OnceLock<SimdLevel> = std::sync::OnceLock::new();
    *LEVEL.get_or_init(|| {
        if let Some(l) = std::env::var("SLAG_SCAN_SIMD")
            .ok()
            .and_then(|v| SimdLevel::from_name(&v))
            .filter(|l| l.available())
        {
            return l;
        }
        SimdLevel::available_levels()
            .last()
            .copied()
            .unwrap_or(SimdLevel::Baseline)
    })
}

/// Scores rows `start..end` (see the module doc) with the best available [`SimdLevel`]:
/// `out[r]` = the `Q` dot products of row `start + r`, for every row `i` with `keep(i)` (every
/// row when `keep` is `None`; the other entries are left as they were).
///
/// Shapes (checked by [`scan`](super::scan) before it gets here; a violation is a bug and
/// panics): `vectors` holds `[N * d]` values, `start <= end <= N`, `out.len() == end - start`,
/// every `qs[q]` is `[d]`.
pub fn scan_chunk<const Q: usize>(
    vectors: &StoredVectors,
    d: usize,
    start: usize,
    end: usize,
    qs: &Queries<'_, Q>,
    keep: Option<Keep<'_>>,
    out: &mut [[f32; Q]],
) {
    scan_chunk_at::<Q>(simd_level(), vectors, d, start, end, qs, keep, out)
}

/// One f32 dot product `a · b` at the [`simd_level`]: [`dot_f32_at`]. The distance of the
/// instant-distance HNSW graph (`hnsw/instant.rs`), called once per pair of rows it compares.
///
/// Shapes: `b.len() >= a.len()` (the first `a.len()` values of `b` are used).
#[inline]
pub fn dot_f32(a: &[f32], b: &[f32]) -> f32 {
    dot_f32_at(simd_level(), a, b)
}

/// [`dot_f32`] at an explicit level: the explicit SIMD kernel (AVX2 + FMA, AVX-512F, NEON) where
/// the CPU has it, else the portable loop (no FMA). Results differ between levels by f32
/// rounding only.
pub fn dot_f32_at(level: SimdLevel, a: &[f32], b: &[f32]) -> f32 {
    super::simd::dot_f32(level, a, b).unwrap_or_else(|| dot_conv::<f32, false>(a, b, |x| x))
}

/// `true` when this CPU can run [`SimdLevel::Avx2Fma`].
pub fn avx2_fma_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2")
            && std::arch::is_x86_feature_detected!("fma")
            && std::arch::is_x86_feature_detected!("f16c")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// [`scan_chunk`] at an explicit level (benchmarks and tests compare levels in one process). A
/// level the CPU lacks falls back to [`SimdLevel::Baseline`].
#[allow(clippy::too_many_arguments)]
pub fn scan_chunk_at<const Q: usize>(
    level: SimdLevel,
    vectors: &StoredVectors,
    d: usize,
    start: usize,
    end: usize,
    qs: &Queries<'_, Q>,
    keep: Option<Keep<'_>>,
    out: &mut [[f32; Q]],
) {
    assert!(
        start <= end && end * d <= vectors.values() && out.len() == end - start,
        "scan_chunk: rows {start}..{end} of dim {d}, {} values, {} outputs",
        vectors.values(),
        out.len()
    );
    assert!(
        qs.vectors().iter().all(|q| q.len() == d),
        "scan_chunk: query width != {d}"
    );
    if super::simd::chunk::<Q>(level, vectors, d, start, end, qs, keep, out) {
        return;
    }
    // aarch64 always has FMA (and NEON); elsewhere plain multiply + add. f16 rows go through
    // `half`'s run-time-detected slice conversion (F16C / FP16) here.
    const FMA: bool = cfg!(target_arch = "aarch64");
    chunk_impl::<Q, FMA>(
        vectors,
        d,
        start,
        end,
        qs.vectors(),
        keep,
        out,
        convert_f16_portable,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lcg(seed: &mut u64) -> f32 {
        *seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((*seed >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
    }

    fn ref_dot(a: impl Iterator<Item = f64>, b: &[f32]) -> f64 {
        a.zip(b).map(|(x, &y)| x * y as f64).sum()
    }

    #[test]
    fn every_simd_level_gives_the_same_single_dot() {
        let mut s = 5u64;
        for d in [0usize, 1, 7, 8, 15, 16, 17, 33, 64, 100, 512, 515] {
            let a: Vec<f32> = (0..d).map(|_| lcg(&mut s)).collect();
            let b: Vec<f32> = (0..d).map(|_| lcg(&mut s)).collect();
            let want = ref_dot(a.iter().map(|&x| x as f64), &b);
            for level in SimdLevel::available_levels() {
                let got = dot_f32_at(level, &a, &b) as f64;
                assert!(
                    (got - want).abs() <= 1e-5 * (1.0 + d as f64),
                    "{level:?} d={d}: {got} vs {want}"
                );
            }
            assert_eq!(dot_f32(&a, &b), dot_f32_at(simd_level(), &a, &b));
        }
    }

    #[test]
    fn every_simd_level_gives_the_same_dots() {
        use crate::scan::VectorStore;
        use slag_common::shards::Dtype;
        let d = 45;
        let mut s = 3u64;
        let qv: Vec<Vec<f32>> = (0..5)
            .map(|_| (0..d).map(|_| lcg(&mut s)).collect())
            .collect();
        let qs: [&[f32]; 5] = [&qv[0], &qv[1], &qv[2], &qv[3], &qv[4]];
        for dtype in [Dtype::F32, Dtype::F16, Dtype::I8] {
            let store = VectorStore::synthetic(300, d, dtype, 4, 2).expect("store");
            let keep = |i: usize| i % 7 != 3;
            let want = (10..300).filter(|&i| keep(i)).count();
            for level in SimdLevel::available_levels() {
                let mut out = vec![[f32::NAN; 5]; 290];
                let qq = Queries::new(qs);
                scan_chunk_at::<5>(
                    level,
                    store.vectors(),
                    d,
                    10,
                    300,
                    &qq,
                    Some(&keep),
                    &mut out,
                );
                let got: Vec<(usize, [f32; 5])> =
                    (10..300).zip(out).filter(|(_, o)| !o[0].is_nan()).collect();
                assert_eq!(got.len(), want, "{level:?}");
                let mut prev = 0;
                for (i, a) in &got {
                    assert!(*i >= prev && keep(*i), "{level:?}: rows out of order");
                    prev = *i;
                    let row = store.row_f32(*i).expect("row");
                    for q in 0..5 {
                        let r: f64 = row
                            .iter()
                            .zip(&qv[q])
                            .map(|(&x, &y)| x as f64 * y as f64)
                            .sum();
                        assert!((a[q] as f64 - r).abs() < 1e-5, "{dtype:?} {level:?}");
                    }
                }
            }
        }
    }

    #[test]
    fn kernels_match_f64_reference_for_odd_widths() {
        let mut s = 7u64;
        // Widths around the lane and block boundaries.
        for d in [1usize, 3, 15, 16, 17, 31, 64, 255, 256, 257, 600] {
            let row: Vec<f32> = (0..d).map(|_| lcg(&mut s)).collect();
            let qv: Vec<Vec<f32>> = (0..3)
                .map(|_| (0..d).map(|_| lcg(&mut s)).collect())
                .collect();
            let qs: [&[f32]; 3] = [&qv[0], &qv[1], &qv[2]];
            let mut out = [0.0f32; 3];
            dots_f32::<3, false>(&row, &qs, &mut out);
            for q in 0..3 {
                let r = ref_dot(row.iter().map(|&x| x as f64), &qv[q]);
                assert!(
                    (out[q] as f64 - r).abs() < 1e-5 * d as f64,
                    "f32 d={d} q={q}"
                );
            }
            let h: Vec<f16> = row.iter().map(|&x| f16::from_f32(x)).collect();
            let mut buf = [0.0f32; BLOCK];
            {
                dots_f16::<3, false>(&h, &qs, &mut buf, &mut out, convert_f16_portable);
                for q in 0..3 {
                    let r = ref_dot(h.iter().map(|x| x.to_f32() as f64), &qv[q]);
                    assert!(
                        (out[q] as f64 - r).abs() < 1e-5 * d as f64,
                        "f16 d={d} q={q}"
                    );
                }
            }
            let i: Vec<i8> = row.iter().map(|&x| (x * 127.0).round() as i8).collect();
            let scale = 0.01f32;
            dots_i8::<3, false>(&i, scale, &qs, &mut buf, &mut out);
            for q in 0..3 {
                let r = scale as f64 * ref_dot(i.iter().map(|&x| x as f64), &qv[q]);
                assert!(
                    (out[q] as f64 - r).abs() < 1e-5 * d as f64,
                    "i8 d={d} q={q}"
                );
            }
        }
    }

    /// Scores `rows` (`[n * d]` as f64 values of the stored type) against `qs` in f64.
    fn reference(rows: &StoredVectors, d: usize, qs: &[Vec<f32>]) -> Vec<Vec<f64>> {
        let n = rows.values() / d.max(1);
        (0..n)
            .map(|i| {
                let row: Vec<f64> = match rows {
                    StoredVectors::F32(v) => v[i * d..][..d].iter().map(|&x| x as f64).collect(),
                    StoredVectors::F16(v) => {
                        v[i * d..][..d].iter().map(|x| x.to_f32() as f64).collect()
                    }
                    StoredVectors::I8 { q, scales } => q[i * d..][..d]
                        .iter()
                        .map(|&x| x as f64 * scales[i] as f64)
                        .collect(),
                };
                qs.iter().map(|q| ref_dot(row.iter().copied(), q)).collect()
            })
            .collect()
    }

    /// Every available level against the f64 reference: `|got − ref| ≤ 1e-5 · Σ|x_j·q_j| +
    /// 1e-6 · Σ|x_j| · max|q|` (f32 rounding of D products; the SDOT split's 6e-8 · max|q|).
    fn check_levels<const Q: usize>(
        rows: &StoredVectors,
        d: usize,
        qv: &[Vec<f32>],
    ) -> Result<(), proptest::test_runner::TestCaseError> {
        let n = rows.values() / d;
        let qs: [&[f32]; Q] = std::array::from_fn(|q| qv[q].as_slice());
        let want = reference(rows, d, qv);
        let row_f64 = |i: usize| -> Vec<f64> {
            match rows {
                StoredVectors::F32(v) => v[i * d..][..d].iter().map(|&x| x as f64).collect(),
                StoredVectors::F16(v) => {
                    v[i * d..][..d].iter().map(|x| x.to_f32() as f64).collect()
                }
                StoredVectors::I8 { q, scales } => q[i * d..][..d]
                    .iter()
                    .map(|&x| x as f64 * scales[i] as f64)
                    .collect(),
            }
        };
        for level in SimdLevel::available_levels() {
            let mut out = vec![[f32::NAN; Q]; n];
            scan_chunk_at::<Q>(level, rows, d, 0, n, &Queries::new(qs), None, &mut out);
            let got: Vec<(usize, [f32; Q])> = out.into_iter().enumerate().collect();
            proptest::prop_assert_eq!(got.len(), n);
            for (i, dots) in got {
                let row = row_f64(i);
                for q in 0..Q {
                    let abs: f64 = row
                        .iter()
                        .zip(&qv[q])
                        .map(|(x, &y)| (x * y as f64).abs())
                        .sum();
                    let l1: f64 = row.iter().map(|x| x.abs()).sum();
                    let m = qv[q].iter().fold(0.0f64, |a, &y| a.max((y as f64).abs()));
                    let tol = 1e-5 * abs + 1e-6 * l1 * m + 1e-30;
                    let err = (dots[q] as f64 - want[i][q]).abs();
                    proptest::prop_assert!(
                        err <= tol,
                        "{:?} {:?} d={} q={} row={}: {} vs {} (tol {})",
                        level,
                        rows.dtype(),
                        d,
                        q,
                        i,
                        dots[q],
                        want[i][q],
                        tol
                    );
                }
            }
        }
        Ok(())
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(48))]

        /// Every SIMD kernel equals the scalar f64 reference for any width (tails included), any
        /// query count, every stored type.
        #[test]
        fn simd_kernels_match_the_scalar_reference(
            d in 1usize..300,
            n in 1usize..6,
            nq in 0usize..5,
            seed in proptest::prelude::any::<u64>(),
            mag in proptest::sample::select(vec![1e-3f32, 1.0, 300.0]),
        ) {
            let mut s = seed | 1;
            let vals: Vec<f32> = (0..n * d).map(|_| lcg(&mut s) * mag).collect();
            let qv: Vec<Vec<f32>> = (0..8).map(|_| (0..d).map(|_| lcg(&mut s)).collect()).collect();
            let f16s = vals.iter().map(|&x| f16::from_f32(x)).collect();
            let mut q = Vec::new();
            let scales: Vec<f32> = vals
                .chunks_exact(d)
                .map(|r| {
                    let mut b = Vec::new();
                    let sc = slag_common::shards::format::quantize_i8(r, &mut b);
                    q.extend(b.iter().map(|&x| x as i8));
                    sc
                })
                .collect();
            for rows in [StoredVectors::F32(vals.clone()), StoredVectors::F16(f16s), StoredVectors::I8 { q, scales }] {
                match [1, 2, 3, 5, 8][nq] {
                    1 => check_levels::<1>(&rows, d, &qv)?,
                    2 => check_levels::<2>(&rows, d, &qv)?,
                    3 => check_levels::<3>(&rows, d, &qv)?,
                    5 => check_levels::<5>(&rows, d, &qv)?,
                    _ => check_levels::<8>(&rows, d, &qv)?,
                }
            }
        }
    }

    /// Dots of every available level vs [`SimdLevel::Baseline`] (the portable scalar-order
    /// fallback): equal within f32 rounding when finite, the same NaN / ±inf otherwise.
    fn same_as_baseline<const Q: usize>(
        rows: &StoredVectors,
        d: usize,
        qv: &[Vec<f32>],
        what: &str,
    ) {
        let n = rows.values() / d;
        let qs: [&[f32]; Q] = std::array::from_fn(|q| qv[q].as_slice());
        let queries = Queries::new(qs);
        let mut base = vec![[0.0f32; Q]; n];
        scan_chunk_at::<Q>(
            SimdLevel::Baseline,
            rows,
            d,
            0,
            n,
            &queries,
            None,
            &mut base,
        );
        for level in SimdLevel::available_levels() {
            let mut got = vec![[0.0f32; Q]; n];
            scan_chunk_at::<Q>(level, rows, d, 0, n, &queries, None, &mut got);
            for i in 0..n {
                for q in 0..Q {
                    let (a, b) = (got[i][q], base[i][q]);
                    let ok = if a.is_finite() && b.is_finite() {
                        let row: Vec<f64> = match rows {
                            StoredVectors::F32(v) => {
                                v[i * d..][..d].iter().map(|&x| x as f64).collect()
                            }
                            StoredVectors::F16(v) => {
                                v[i * d..][..d].iter().map(|x| x.to_f32() as f64).collect()
                            }
                            StoredVectors::I8 { q: b8, scales } => b8[i * d..][..d]
                                .iter()
                                .map(|&x| x as f64 * scales[i] as f64)
                                .collect(),
                        };
                        let abs: f64 = row
                            .iter()
                            .zip(&qv[q])
                            .map(|(x, &y)| (x * y as f64).abs())
                            .sum();
                        let l1: f64 = row.iter().map(|x| x.abs()).sum();
                        let m = qv[q].iter().fold(0.0f64, |a, &y| a.max((y as f64).abs()));
                        ((a - b) as f64).abs() <= 2e-5 * abs + 2e-6 * l1 * m + 1e-30
                    } else {
                        (a.is_nan() && b.is_nan()) || a == b
                    };
                    assert!(
                        ok,
                        "{what} {level:?} d={d} row {i} query {q}: {a} vs baseline {b}"
                    );
                }
            }
        }
    }

    #[test]
    fn simd_levels_equal_the_scalar_fallback_on_edge_case_rows() {
        let mut s = 5u64;
        // Widths around every lane count (8, 16, 64 bytes) and the f16 block.
        for d in [
            1usize, 7, 8, 9, 15, 16, 17, 63, 64, 65, 127, 255, 256, 257, 511, 512, 513,
        ] {
            let qv: Vec<Vec<f32>> = (0..2)
                .map(|_| (0..d).map(|_| lcg(&mut s)).collect())
                .collect();
            let zero_q = vec![vec![0.0f32; d], qv[0].clone()];
            // f16: zeros, subnormals (smallest and largest), the largest finite, ±inf, normal.
            let specials = [
                f16::ZERO,
                f16::NEG_ZERO,
                f16::from_bits(0x0001),
                f16::from_bits(0x03ff),
                f16::from_bits(0x8001),
                f16::MAX,
                f16::MIN,
                f16::from_f32(0.3),
            ];
            let mut h = Vec::new();
            for r in 0..6 {
                for j in 0..d {
                    h.push(match r {
                        0 => f16::ZERO,
                        1 => specials[j % specials.len()],
                        2 => f16::from_bits(0x0001 + (j as u16 % 0x3ff)), // all subnormal
                        3 if j == d / 2 => f16::INFINITY,
                        4 if j == 0 => f16::NEG_INFINITY,
                        _ => f16::from_f32(lcg(&mut s)),
                    });
                }
            }
            let h = StoredVectors::F16(h);
            same_as_baseline::<1>(&h, d, &qv, "f16");
            same_as_baseline::<2>(&h, d, &qv, "f16");
            same_as_baseline::<2>(&h, d, &zero_q, "f16 zero query");
            // int8: zeros, the extremes ±127 and -128, alternating signs, random.
            let mut q8 = Vec::new();
            for r in 0..5 {
                for j in 0..d {
                    q8.push(match r {
                        0 => 0i8,
                        1 => 127,
                        2 => -128,
                        3 => {
                            if j % 2 == 0 {
                                127
                            } else {
                                -127
                            }
                        }
                        _ => (lcg(&mut s) * 127.0) as i8,
                    });
                }
            }
            let i8s = StoredVectors::I8 {
                q: q8,
                scales: vec![1.0, 0.5, 1e-3, 7.0, 0.01],
            };
            same_as_baseline::<1>(&i8s, d, &qv, "int8");
            same_as_baseline::<2>(&i8s, d, &qv, "int8");
            same_as_baseline::<2>(&i8s, d, &zero_q, "int8 zero query");
            // A query with a huge dynamic range (the int8 split's steps follow its largest value).
            let mut wide = qv[1].clone();
            wide[0] = 1e3;
            same_as_baseline::<1>(&i8s, d, &[wide], "int8 wide query");
            let f = StoredVectors::F32((0..4 * d).map(|_| lcg(&mut s)).collect());
            same_as_baseline::<1>(&f, d, &qv, "f32");
            same_as_baseline::<2>(&f, d, &qv, "f32");
        }
    }

    #[test]
    fn query_split_reconstructs_within_its_bound() {
        let mut s = 11u64;
        let d = 77;
        let qv: Vec<Vec<f32>> = (0..2)
            .map(|_| (0..d).map(|_| lcg(&mut s)).collect())
            .collect();
        let zero = vec![0.0f32; d];
        let qs: [&[f32]; 3] = [&qv[0], &qv[1], &zero];
        let (terms, steps) = crate::scan::simd::split_queries(&qs, d);
        for k in 0..3 {
            let m = qs[k].iter().fold(0.0f64, |a, &y| a.max((y as f64).abs()));
            for j in 0..d {
                let r: f64 = (0..3)
                    .map(|t| steps[k][t] as f64 * terms[(k * 3 + t) * d + j] as f64)
                    .sum();
                assert!(
                    (r - qs[k][j] as f64).abs() <= m * 7e-8 + 1e-12,
                    "query {k} component {j}: {r} vs {}",
                    qs[k][j]
                );
            }
        }
        assert_eq!(steps[2], [0.0; 3]);
    }
}
