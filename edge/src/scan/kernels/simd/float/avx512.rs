//! x86_64 AVX-512F: 16 f32 lanes (`vcvtph2ps zmm` for f16 rows).

use std::arch::x86_64::*;

use half::f16;
use slag_common::shards::StoredVectors;

use super::super::prefetch::prefetch_t0;
use super::{Simd, chunk_body, dots_q};
use crate::scan::kernels::queries::RowSpan;

/// AVX-512F (+ F16C-equivalent `vcvtph2ps zmm`): 16 lanes.
pub struct Avx512;

impl Simd for Avx512 {
    type V = __m512;
    const W: usize = 16;
    #[inline(always)]
    unsafe fn zero() -> __m512 {
        // SAFETY: the caller runs on a CPU with AVX-512F.
        unsafe { _mm512_setzero_ps() }
    }
    #[inline(always)]
    unsafe fn fma(a: __m512, b: __m512, c: __m512) -> __m512 {
        // SAFETY: as `zero`.
        unsafe { _mm512_fmadd_ps(a, b, c) }
    }
    #[inline(always)]
    unsafe fn sum(v: __m512) -> f32 {
        // SAFETY: as `zero`.
        unsafe { _mm512_reduce_add_ps(v) }
    }
    #[inline(always)]
    unsafe fn load_f32(p: *const f32) -> __m512 {
        // SAFETY: as `zero`; `p` points at 16 readable f32 (caller).
        unsafe { _mm512_loadu_ps(p) }
    }
    #[inline(always)]
    unsafe fn load_f16(p: *const f16) -> __m512 {
        // SAFETY: as `zero`; `p` points at 16 readable halves = 32 bytes (caller).
        unsafe { _mm512_cvtph_ps(_mm256_loadu_si256(p.cast())) }
    }
    #[inline(always)]
    unsafe fn load_i8(p: *const i8) -> __m512 {
        // SAFETY: as `zero`; `p` points at 16 readable bytes (caller).
        unsafe { _mm512_cvtepi32_ps(_mm512_cvtepi8_epi32(_mm_loadu_si128(p.cast()))) }
    }
    #[inline(always)]
    fn prefetch(p: *const u8) {
        prefetch_t0(p)
    }
}

/// [`chunk_body`] compiled for AVX-512F.
#[target_feature(enable = "avx512f,avx2,fma,f16c")]
pub fn chunk_avx512<const Q: usize>(
    vectors: &StoredVectors,
    span: RowSpan<'_>,
    qs: &[&[f32]; Q],
    out: &mut [[f32; Q]],
) {
    // SAFETY: this function is compiled for (and only called on CPUs with) AVX-512F.
    unsafe { chunk_body::<Avx512, Q>(vectors, span, qs, out) }
}

/// [`dot_f32_avx2`] with AVX-512F.
#[target_feature(enable = "avx512f,avx2,fma,f16c")]
pub fn dot_f32_avx512(a: &[f32], b: &[f32]) -> f32 {
    // SAFETY: compiled for (and only called on CPUs with) AVX-512F.
    unsafe { dots_q::<Avx512, f32, 1>(a, &[b])[0] }
}
