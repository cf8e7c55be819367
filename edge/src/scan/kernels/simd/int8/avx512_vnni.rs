//! x86_64 AVX-512 VNNI: int8 rows with `vpdpbusd`, 64 bytes per step.

use std::arch::x86_64::*;

use super::super::prefetch::prefetch_t0;
use super::{I8Dot, chunk_i8_split_q};
use crate::scan::kernels::queries::{Queries, RowSpan};

/// AVX-512 VNNI `vpdpbusd`: 64 bytes per step, rows shifted to unsigned (x XOR 0x80 = x + 128).
pub struct Vnni512;

impl I8Dot for Vnni512 {
    type Acc = __m512i;
    type X = __m512i;
    const W: usize = 64;
    const OFFSET: i32 = 128;
    #[inline(always)]
    unsafe fn zero() -> __m512i {
        // SAFETY: the caller runs on a CPU with AVX-512F/BW/VNNI.
        unsafe { _mm512_setzero_si512() }
    }
    #[inline(always)]
    unsafe fn load_row(p: *const i8) -> __m512i {
        // SAFETY: as `zero`; `p` points at 64 readable bytes (caller).
        unsafe { _mm512_xor_si512(_mm512_loadu_si512(p.cast()), _mm512_set1_epi8(-128)) }
    }
    #[inline(always)]
    unsafe fn load_term(p: *const i8) -> __m512i {
        // SAFETY: as `load_row`.
        unsafe { _mm512_loadu_si512(p.cast()) }
    }
    #[inline(always)]
    unsafe fn dot(acc: __m512i, x: __m512i, y: __m512i) -> __m512i {
        // SAFETY: as `zero`.
        unsafe { _mm512_dpbusd_epi32(acc, x, y) }
    }
    #[inline(always)]
    unsafe fn sum(acc: __m512i) -> i32 {
        // SAFETY: as `zero`.
        unsafe { _mm512_reduce_add_epi32(acc) }
    }
    #[inline(always)]
    fn prefetch(p: *const u8) {
        prefetch_t0(p)
    }
}

/// int8 rows with `vpdpbusd` against three-term int8 splits of the queries (module doc).
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
pub fn chunk_i8_vnni<const Q: usize>(
    q: &[i8],
    scales: &[f32],
    span: RowSpan<'_>,
    qs: &Queries<'_, Q>,
    out: &mut [[f32; Q]],
) {
    // SAFETY: compiled for (and only called on CPUs with) AVX-512F/BW/VNNI.
    unsafe { chunk_i8_split_q::<Vnni512, Q>(q, scales, span, qs, out) }
}
