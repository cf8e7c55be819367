//! aarch64 NEON dot-product extension: int8 rows with SDOT, 16 bytes per step.

use std::arch::aarch64::*;

use super::super::prefetch::prefetch_l1;
use super::{I8Dot, chunk_i8_split_q};
use crate::scan::kernels::queries::{Queries, RowSpan};

/// NEON `SDOT` (dot-product extension): 16 bytes per step, signed × signed.
pub struct Sdot;

impl I8Dot for Sdot {
    type Acc = int32x4_t;
    type X = int8x16_t;
    const W: usize = 16;
    const OFFSET: i32 = 0;
    #[inline(always)]
    unsafe fn zero() -> int32x4_t {
        // SAFETY: NEON is baseline.
        unsafe { vdupq_n_s32(0) }
    }
    #[inline(always)]
    unsafe fn load_row(p: *const i8) -> int8x16_t {
        // SAFETY: NEON is baseline; `p` points at 16 readable bytes (caller).
        unsafe { vld1q_s8(p) }
    }
    #[inline(always)]
    unsafe fn load_term(p: *const i8) -> int8x16_t {
        // SAFETY: as `load_row`.
        unsafe { vld1q_s8(p) }
    }
    #[inline(always)]
    unsafe fn dot(acc: int32x4_t, x: int8x16_t, y: int8x16_t) -> int32x4_t {
        let mut acc = acc;
        // SAFETY: only inlined into `chunk_i8_sdot`, which is compiled for and only called
        // on CPUs with `dotprod` (caller's contract); register-only instruction.
        // (`vdotq_s32` is not stable Rust.)
        unsafe {
            std::arch::asm!(
                "sdot {acc:v}.4s, {a:v}.16b, {b:v}.16b",
                acc = inout(vreg) acc,
                a = in(vreg) x,
                b = in(vreg) y,
                options(pure, nomem, nostack, preserves_flags)
            );
        }
        acc
    }
    #[inline(always)]
    unsafe fn sum(acc: int32x4_t) -> i32 {
        // SAFETY: NEON is baseline.
        unsafe { vaddvq_s32(acc) }
    }
    #[inline(always)]
    fn prefetch(p: *const u8) {
        prefetch_l1(p)
    }
}

/// int8 rows with SDOT against three-term int8 splits of the queries (module doc).
#[target_feature(enable = "neon,dotprod")]
pub fn chunk_i8_sdot<const Q: usize>(
    q: &[i8],
    scales: &[f32],
    span: RowSpan<'_>,
    qs: &Queries<'_, Q>,
    out: &mut [[f32; Q]],
) {
    // SAFETY: compiled for (and only called on CPUs with) `dotprod`.
    unsafe { chunk_i8_split_q::<Sdot, Q>(q, scales, span, qs, out) }
}
