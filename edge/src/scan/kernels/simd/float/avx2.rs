//! x86_64 AVX2 + FMA + F16C: 8 f32 lanes (`vcvtph2ps` for f16 rows).

use std::arch::x86_64::*;

use half::f16;
use slag_common::shards::StoredVectors;

use super::super::prefetch::prefetch_t0;
use super::{Simd, chunk_body, dots_q};
use crate::scan::kernels::queries::RowSpan;

/// AVX2 + FMA + F16C: 8 lanes.
pub struct Avx2;

impl Simd for Avx2 {
    type V = __m256;
    const W: usize = 8;
    #[inline(always)]
    unsafe fn zero() -> __m256 {
        // SAFETY: the caller runs on a CPU with AVX2 + FMA + F16C.
        unsafe { _mm256_setzero_ps() }
    }
    #[inline(always)]
    unsafe fn fma(a: __m256, b: __m256, c: __m256) -> __m256 {
        // SAFETY: as `zero`.
        unsafe { _mm256_fmadd_ps(a, b, c) }
    }
    #[inline(always)]
    unsafe fn sum(v: __m256) -> f32 {
        // SAFETY: as `zero`.
        unsafe {
            let s = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps::<1>(v));
            let s = _mm_add_ps(s, _mm_movehl_ps(s, s));
            let s = _mm_add_ss(s, _mm_shuffle_ps::<1>(s, s));
            _mm_cvtss_f32(s)
        }
    }
    #[inline(always)]
    unsafe fn load_f32(p: *const f32) -> __m256 {
        // SAFETY: as `zero`; `p` points at 8 readable f32 (caller).
        unsafe { _mm256_loadu_ps(p) }
    }
    #[inline(always)]
    unsafe fn load_f16(p: *const f16) -> __m256 {
        // SAFETY: as `zero`; `p` points at 8 readable halves = 16 bytes (caller).
        unsafe { _mm256_cvtph_ps(_mm_loadu_si128(p.cast())) }
    }
    #[inline(always)]
    unsafe fn load_i8(p: *const i8) -> __m256 {
        // SAFETY: as `zero`; `p` points at 8 readable bytes (caller).
        unsafe { _mm256_cvtepi32_ps(_mm256_cvtepi8_epi32(_mm_loadl_epi64(p.cast()))) }
    }
    #[inline(always)]
    fn prefetch(p: *const u8) {
        prefetch_t0(p)
    }
}

/// [`chunk_body`] compiled for AVX2 + FMA + F16C.
#[target_feature(enable = "avx2,fma,f16c")]
pub fn chunk_avx2<const Q: usize>(
    vectors: &StoredVectors,
    span: RowSpan<'_>,
    qs: &[&[f32]; Q],
    out: &mut [[f32; Q]],
) {
    // SAFETY: this function is compiled for (and only called on CPUs with) AVX2+FMA+F16C.
    unsafe { chunk_body::<Avx2, Q>(vectors, span, qs, out) }
}

/// One f32 dot product `a · b` (`b` at least as long as `a`) with AVX2 + FMA (the HNSW
/// graph's distance, [`crate::scan::kernels::dot_f32`]).
#[target_feature(enable = "avx2,fma,f16c")]
pub fn dot_f32_avx2(a: &[f32], b: &[f32]) -> f32 {
    // SAFETY: compiled for (and only called on CPUs with) AVX2 + FMA + F16C.
    unsafe { dots_q::<Avx2, f32, 1>(a, &[b])[0] }
}
