//! Explicit SIMD scan kernels (the only `unsafe` of the scan): x86_64 AVX2 + FMA + F16C and
//! AVX-512F, aarch64 NEON (FCVTL for f16) and NEON + SDOT (int8), each selected at run time by
//! [`super::simd_level`] after `is_x86_feature_detected!` /
//! `is_aarch64_feature_detected!` confirmed the instructions.
//!
//! One folder per precision of the accumulation, one file per instruction set in it:
//!
//! - [`float`]: f32 accumulators (f32, f16 and int8 rows converted in registers, fused
//!   multiply-add with the f32 queries): `avx2.rs`, `avx512.rs`, `neon.rs`;
//! - [`int8`]: exact i32 accumulators (int8 rows against three-term int8 splits of the queries):
//!   `avx512_vnni.rs` (VPDPBUSD), `neon_sdot.rs` (SDOT);
//! - `prefetch.rs`: the cache hints both use.
//!
//! Safety, once for the whole module: every `unsafe` block here either (a) calls a function
//! compiled for instructions that the caller has confirmed at run time (the `chunk_*` entry
//! points are only reached through [`chunk`], which re-checks the detection), or (b) reads `W`
//! values through a pointer at element offset `j` of a slice whose length was checked to be at
//! least `j + W` by the loop condition (queries are re-sliced to the row's length first, which
//! panics, like the portable loop, on a shorter query).
#![allow(unsafe_code)]

mod float;
mod int8;
mod prefetch;

use slag_common::shards::StoredVectors;

use super::level::SimdLevel;
use super::queries::{Queries, RowSpan};

/// Runs the chunk scan at `level` (see [`super::scan_chunk_at`]) when that level is an explicit
/// SIMD kernel of this build target and the CPU has it; returns `false` (nothing done) otherwise.
pub(super) fn chunk<const Q: usize>(
    level: SimdLevel,
    vectors: &StoredVectors,
    span: RowSpan<'_>,
    queries: &Queries<'_, Q>,
    out: &mut [[f32; Q]],
) -> bool {
    let qs = queries.vectors();
    if !level.available() {
        return false;
    }
    match level {
        #[cfg(target_arch = "x86_64")]
        SimdLevel::Avx2Fma => {
            // SAFETY: `level.available()` confirmed AVX2 + FMA + F16C on this CPU
            // (`is_x86_feature_detected!`).
            unsafe { float::avx2::chunk_avx2::<Q>(vectors, span, qs, out) };
            true
        }
        #[cfg(target_arch = "x86_64")]
        SimdLevel::Avx512 => {
            // SAFETY: `level.available()` confirmed AVX-512F + AVX2 + FMA + F16C
            // (`is_x86_feature_detected!`).
            unsafe { float::avx512::chunk_avx512::<Q>(vectors, span, qs, out) };
            true
        }
        #[cfg(target_arch = "x86_64")]
        SimdLevel::Avx512Vnni => {
            match vectors {
                // Q > 2: 3·Q term loads per 64 row bytes make VPDPBUSD load-bound; the
                // convert + FMA kernel measured faster there (`slag-edge bench` kernel table).
                StoredVectors::I8 { q, scales } if Q <= 2 => {
                    // SAFETY: `level.available()` confirmed AVX-512F/BW/VNNI
                    // (`is_x86_feature_detected!`).
                    unsafe { int8::avx512_vnni::chunk_i8_vnni::<Q>(q, scales, span, queries, out) }
                }
                // SAFETY: as above (Avx512Vnni implies Avx512).
                _ => unsafe { float::avx512::chunk_avx512::<Q>(vectors, span, qs, out) },
            }
            true
        }
        #[cfg(target_arch = "aarch64")]
        SimdLevel::Neon => {
            float::neon::chunk_neon::<Q>(vectors, span, qs, out);
            true
        }
        #[cfg(target_arch = "aarch64")]
        SimdLevel::NeonDotprod => {
            match vectors {
                StoredVectors::I8 { q, scales } => {
                    // SAFETY: `level.available()` confirmed `dotprod` on this CPU
                    // (`is_aarch64_feature_detected!`).
                    unsafe { int8::neon_sdot::chunk_i8_sdot::<Q>(q, scales, span, queries, out) }
                }
                _ => float::neon::chunk_neon::<Q>(vectors, span, qs, out),
            }
            true
        }
        _ => false,
    }
}

/// One f32 dot product `a · b` (`b` at least as long as `a`; panics when shorter) at `level`
/// when that level is an explicit SIMD kernel of this build target and the CPU has it; `None`
/// otherwise (the caller uses the portable loop).
pub(super) fn dot_f32(level: SimdLevel, a: &[f32], b: &[f32]) -> Option<f32> {
    if !level.available() {
        return None;
    }
    match level {
        #[cfg(target_arch = "x86_64")]
        SimdLevel::Avx2Fma => {
            // SAFETY: `level.available()` confirmed AVX2 + FMA + F16C (`is_x86_feature_detected!`).
            Some(unsafe { float::avx2::dot_f32_avx2(a, b) })
        }
        #[cfg(target_arch = "x86_64")]
        SimdLevel::Avx512 | SimdLevel::Avx512Vnni => {
            // SAFETY: `level.available()` confirmed AVX-512F + AVX2 + FMA + F16C.
            Some(unsafe { float::avx512::dot_f32_avx512(a, b) })
        }
        #[cfg(target_arch = "aarch64")]
        SimdLevel::Neon | SimdLevel::NeonDotprod => Some(float::neon::dot_f32_neon(a, b)),
        _ => None,
    }
}
