//! aarch64 NEON: 8 f32 lanes in two registers (FMLA; FCVTL for f16 rows; SXTL + SCVTF for int8).

use std::arch::aarch64::*;

use half::f16;
use slag_common::shards::StoredVectors;

use super::super::prefetch::prefetch_l1;
use super::{Simd, chunk_body, dots_q};
use crate::scan::kernels::queries::RowSpan;

/// NEON: two `float32x4_t` (8 lanes) per vector, so that one `ld1` of 8 halves feeds an
/// `FCVTL` + `FCVTL2` pair and one `ld1` of 8 int8 a `SXTL` chain.
pub struct Neon;

impl Simd for Neon {
    type V = (float32x4_t, float32x4_t);
    const W: usize = 8;
    #[inline(always)]
    unsafe fn zero() -> Self::V {
        // SAFETY: NEON is part of the aarch64 baseline.
        unsafe { (vdupq_n_f32(0.0), vdupq_n_f32(0.0)) }
    }
    #[inline(always)]
    unsafe fn fma(a: Self::V, b: Self::V, c: Self::V) -> Self::V {
        // SAFETY: as `zero` (FMLA).
        unsafe { (vfmaq_f32(c.0, a.0, b.0), vfmaq_f32(c.1, a.1, b.1)) }
    }
    #[inline(always)]
    unsafe fn sum(v: Self::V) -> f32 {
        // SAFETY: as `zero`.
        unsafe { vaddvq_f32(vaddq_f32(v.0, v.1)) }
    }
    #[inline(always)]
    unsafe fn load_f32(p: *const f32) -> Self::V {
        // SAFETY: as `zero`; `p` points at 8 readable f32 (caller).
        unsafe { (vld1q_f32(p), vld1q_f32(p.add(4))) }
    }
    #[inline(always)]
    unsafe fn load_f16(p: *const f16) -> Self::V {
        // SAFETY: as `zero`; `p` points at 8 readable halves = 16 bytes (caller). FCVTL /
        // FCVTL2 (half → single, exact, subnormals included) are base AdvSIMD instructions
        // (no FP16 extension needed); written as `asm!` because the `float16x4_t`
        // intrinsics are not stable Rust.
        unsafe {
            let h = vld1q_u16(p.cast());
            let lo: float32x4_t;
            let hi: float32x4_t;
            std::arch::asm!(
                "fcvtl {lo:v}.4s, {h:v}.4h",
                "fcvtl2 {hi:v}.4s, {h:v}.8h",
                h = in(vreg) h,
                lo = out(vreg) lo,
                hi = out(vreg) hi,
                options(pure, nomem, nostack, preserves_flags)
            );
            (lo, hi)
        }
    }
    #[inline(always)]
    unsafe fn load_i8(p: *const i8) -> Self::V {
        // SAFETY: as `zero`; `p` points at 8 readable bytes (caller).
        unsafe {
            let w = vmovl_s8(vld1_s8(p));
            (
                vcvtq_f32_s32(vmovl_s16(vget_low_s16(w))),
                vcvtq_f32_s32(vmovl_high_s16(w)),
            )
        }
    }
    #[inline(always)]
    fn prefetch(p: *const u8) {
        prefetch_l1(p)
    }
}

/// [`chunk_body`] with NEON (FMLA; FCVTL for f16; SXTL + SCVTF for int8).
pub fn chunk_neon<const Q: usize>(
    vectors: &StoredVectors,
    span: RowSpan<'_>,
    qs: &[&[f32]; Q],
    out: &mut [[f32; Q]],
) {
    // SAFETY: NEON is part of the aarch64 baseline.
    unsafe { chunk_body::<Neon, Q>(vectors, span, qs, out) }
}

/// One f32 dot product `a · b` (`b` at least as long as `a`) with NEON FMLA (the HNSW
/// graph's distance, [`crate::scan::kernels::dot_f32`]).
pub fn dot_f32_neon(a: &[f32], b: &[f32]) -> f32 {
    // SAFETY: NEON is part of the aarch64 baseline.
    unsafe { dots_q::<Neon, f32, 1>(a, &[b])[0] }
}
