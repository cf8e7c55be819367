//! Inner loops: dot products of `Q` query vectors (1 ≤ Q ≤ [`MAX_QUERIES`]) with one stored row,
//! for `f32`, `f16` and symmetric-int8 rows.
//!
//! - [`portable`](mod@portable): loops written for LLVM's auto-vectoriser, every build target;
//! - `simd/`: explicit intrinsics, one folder per precision of the accumulation and one file per
//!   instruction set (x86_64 AVX2, AVX-512F, AVX-512 VNNI; aarch64 NEON, NEON SDOT), the scan's
//!   only `unsafe`;
//! - [`SimdLevel`] / [`simd_level`]: which of them runs, detected once per process;
//! - [`Queries`]: the queries of one scan and what is derived from them once per scan.
//!
//! Dispatch ([`scan_chunk`], [`scan_chunk_at`]): the explicit kernel of the level when the CPU
//! has it, else the portable loops (aarch64's baseline already has NEON and FMA).
//!
//! Accumulation order differs from a sequential sum (32 partial sums), so results differ from a
//! scalar `f64` reference by normal `f32` rounding only (≈1e-6 relative for D = 512).

mod level;
pub mod portable;
mod queries;
mod simd;

use slag_common::shards::StoredVectors;

pub use level::{SimdLevel, avx2_fma_available, simd_level};
pub use portable::{BLOCK, LANES, LANES_MULTI, convert_f16_portable, dots_f16, dots_f32, dots_i8};
pub use queries::{Keep, MAX_QUERIES, Queries, RowSpan};

/// Scores rows `start..end` (see the module doc) with the best available [`SimdLevel`]:
/// `out[r]` = the `Q` dot products of row `start + r`, for every row `i` with `keep(i)` (every
/// row when `keep` is `None`; the other entries are left as they were).
///
/// Shapes (checked by [`scan`](super::scan) before it gets here; a violation is a bug and
/// panics): `vectors` holds `[N * d]` values, `start <= end <= N`, `out.len() == end - start`,
/// every `qs[q]` is `[d]`.
pub fn scan_chunk<const Q: usize>(
    vectors: &StoredVectors,
    span: RowSpan<'_>,
    qs: &Queries<'_, Q>,
    out: &mut [[f32; Q]],
) {
    scan_chunk_at::<Q>(simd_level(), vectors, span, qs, out)
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
    simd::dot_f32(level, a, b).unwrap_or_else(|| portable::dot_conv::<f32, false>(a, b, |x| x))
}

/// [`scan_chunk`] at an explicit level (benchmarks and tests compare levels in one process). A
/// level the CPU lacks falls back to [`SimdLevel::Baseline`].
pub fn scan_chunk_at<const Q: usize>(
    level: SimdLevel,
    vectors: &StoredVectors,
    span: RowSpan<'_>,
    qs: &Queries<'_, Q>,
    out: &mut [[f32; Q]],
) {
    let RowSpan { d, start, end, .. } = span;
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
    if simd::chunk::<Q>(level, vectors, span, qs, out) {
        return;
    }
    // aarch64 always has FMA (and NEON); elsewhere plain multiply + add. f16 rows go through
    // `half`'s run-time-detected slice conversion (F16C / FP16) here.
    const FMA: bool = cfg!(target_arch = "aarch64");
    portable::chunk_impl::<Q, FMA>(vectors, span, qs.vectors(), out, convert_f16_portable)
}

#[cfg(test)]
mod tests;
