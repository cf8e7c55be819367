//! Explicit SIMD scan kernels (the only `unsafe` of the scan): x86_64 AVX2 + FMA + F16C and
//! AVX-512F, aarch64 NEON (FCVTL for f16) and NEON + SDOT (int8), each selected at run time by
//! [`super::kernels::simd_level`] after `is_x86_feature_detected!` /
//! `is_aarch64_feature_detected!` confirmed the instructions.
//!
//! Every kernel converts the stored row in registers, never through a buffer: per block of `W`
//! values one load (+ `vcvtph2ps` / `FCVTL` / sign-extend + `cvt`) feeds `Q` fused multiply-adds,
//! one per query, into f32 accumulators (`U` blocks in flight for small `Q` to hide the FMA
//! latency). The tail (`D mod W`) is a scalar loop. Results differ from the scalar reference by
//! f32 rounding only.
//!
//! int8 with SDOT (aarch64 `dotprod`): the row stays int8; every f32 query `y` is split once per
//! chunk into three int8 vectors with steps `s1 = max|y| / 127`, `s2 = s1 / 254`, `s3 = s2 / 254`
//! (`y ≈ s1·a + s2·b + s3·c`, error ≤ `max|y| / (2·127·254²)` ≈ 6e-8·max|y| per component), and
//! `row·y = scale · (s1·Σx·a + s2·Σx·b + s3·Σx·c)` with exact i32 sums (three `SDOT`s per 16 row
//! bytes). The sums are exact in f32 while `127²·D < 2²⁴` (D ≤ 1040).
//!
//! Safety, once for the whole module: every `unsafe` block here either (a) calls a function
//! compiled for instructions that the caller has confirmed at run time (the `chunk_*` entry
//! points are only reached through [`chunk`], which re-checks the detection), or (b) reads `W`
//! values through a pointer at element offset `j` of a slice whose length was checked to be at
//! least `j + W` by the loop condition (queries are re-sliced to the row's length first, which
//! panics, like the portable loop, on a shorter query).
#![allow(unsafe_code)]

use half::f16;
use slag_common::shards::StoredVectors;

use super::kernels::{Keep, SimdLevel};

/// One vector instruction set: `W` f32 lanes in a `V`.
trait Simd {
    /// `W` f32 lanes.
    type V: Copy;
    /// Lanes per vector.
    const W: usize;
    /// # Safety
    /// The CPU has the instruction set.
    unsafe fn zero() -> Self::V;
    /// `a · b + c`, fused.
    /// # Safety
    /// As [`Simd::zero`].
    unsafe fn fma(a: Self::V, b: Self::V, c: Self::V) -> Self::V;
    /// Sum of the lanes.
    /// # Safety
    /// As [`Simd::zero`].
    unsafe fn sum(v: Self::V) -> f32;
    /// `W` f32 from `p`.
    /// # Safety
    /// As [`Simd::zero`]; `p` points at `W` readable values.
    unsafe fn load_f32(p: *const f32) -> Self::V;
    /// `W` halves from `p`, converted.
    /// # Safety
    /// As [`Simd::load_f32`].
    unsafe fn load_f16(p: *const f16) -> Self::V;
    /// `W` int8 from `p`, converted (not scaled).
    /// # Safety
    /// As [`Simd::load_f32`].
    unsafe fn load_i8(p: *const i8) -> Self::V;
}

/// A stored element type.
trait Elem: Copy {
    fn to_f32(self) -> f32;
    /// # Safety
    /// As [`Simd::load_f32`].
    unsafe fn load<S: Simd>(p: *const Self) -> S::V;
}

impl Elem for f32 {
    #[inline(always)]
    fn to_f32(self) -> f32 {
        self
    }
    #[inline(always)]
    unsafe fn load<S: Simd>(p: *const Self) -> S::V {
        // SAFETY: forwarded contract.
        unsafe { S::load_f32(p) }
    }
}
impl Elem for f16 {
    #[inline(always)]
    fn to_f32(self) -> f32 {
        f16::to_f32(self)
    }
    #[inline(always)]
    unsafe fn load<S: Simd>(p: *const Self) -> S::V {
        // SAFETY: forwarded contract.
        unsafe { S::load_f16(p) }
    }
}
impl Elem for i8 {
    #[inline(always)]
    fn to_f32(self) -> f32 {
        self as f32
    }
    #[inline(always)]
    unsafe fn load<S: Simd>(p: *const Self) -> S::V {
        // SAFETY: forwarded contract.
        unsafe { S::load_i8(p) }
    }
}

/// `out[q] = Σ_j row[j] · qs[q][j]` for every query, `U` blocks of `W` in flight.
///
/// # Safety
/// The CPU has `S`'s instruction set. (Lengths are checked here: every query is re-sliced to
/// `row.len()`, panicking when shorter.)
#[inline(always)]
unsafe fn dots<S: Simd, T: Elem, const Q: usize, const U: usize>(
    row: &[T],
    qs: &[&[f32]; Q],
) -> [f32; Q] {
    let n = row.len();
    let qs: [&[f32]; Q] = std::array::from_fn(|q| &qs[q][..n]);
    let w = S::W;
    // SAFETY (whole body): the CPU has `S` (caller); every pointer read covers `j + u·w ..
    // j + u·w + w`, inside `0..n` by the loop conditions, and `row`, `qs[q]` have `n` values.
    unsafe {
        let mut acc = [[S::zero(); U]; Q];
        let mut j = 0;
        while j + w * U <= n {
            for u in 0..U {
                let x = T::load::<S>(row.as_ptr().add(j + u * w));
                for q in 0..Q {
                    let y = S::load_f32(qs[q].as_ptr().add(j + u * w));
                    acc[q][u] = S::fma(x, y, acc[q][u]);
                }
            }
            j += w * U;
        }
        while j + w <= n {
            let x = T::load::<S>(row.as_ptr().add(j));
            for q in 0..Q {
                let y = S::load_f32(qs[q].as_ptr().add(j));
                acc[q][0] = S::fma(x, y, acc[q][0]);
            }
            j += w;
        }
        let mut out = [0.0f32; Q];
        for q in 0..Q {
            let mut t = 0.0f32;
            for k in j..n {
                t += row[k].to_f32() * qs[q][k];
            }
            let mut s = 0.0f32;
            for a in &acc[q] {
                s += S::sum(*a);
            }
            out[q] = s + t;
        }
        out
    }
}

/// [`dots`] with the unroll chosen for `Q` (4 blocks for one query, 2 for two, 1 beyond: enough
/// independent FMA chains either way).
///
/// # Safety
/// As [`dots`].
#[inline(always)]
unsafe fn dots_q<S: Simd, T: Elem, const Q: usize>(row: &[T], qs: &[&[f32]; Q]) -> [f32; Q] {
    // SAFETY: forwarded contract.
    unsafe {
        if Q == 1 {
            dots::<S, T, Q, 4>(row, qs)
        } else if Q == 2 {
            dots::<S, T, Q, 2>(row, qs)
        } else {
            dots::<S, T, Q, 1>(row, qs)
        }
    }
}

/// The chunk scan (rows `start..end`, see `kernels::scan_chunk`) with `S` for every dtype.
///
/// # Safety
/// The CPU has `S`'s instruction set.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
unsafe fn chunk_body<S: Simd, const Q: usize>(
    vectors: &StoredVectors,
    d: usize,
    start: usize,
    end: usize,
    qs: &[&[f32]; Q],
    keep: Keep<'_>,
    sink: &mut dyn FnMut(usize, &[f32; Q]),
) {
    // SAFETY: forwarded contract (the CPU has `S`).
    unsafe {
        match vectors {
            StoredVectors::F32(v) => {
                for (r, row) in v[start * d..end * d].chunks_exact(d).enumerate() {
                    let i = start + r;
                    if keep(i) {
                        sink(i, &dots_q::<S, f32, Q>(row, qs));
                    }
                }
            }
            StoredVectors::F16(v) => {
                for (r, row) in v[start * d..end * d].chunks_exact(d).enumerate() {
                    let i = start + r;
                    if keep(i) {
                        sink(i, &dots_q::<S, f16, Q>(row, qs));
                    }
                }
            }
            StoredVectors::I8 { q, scales } => {
                let rows = q[start * d..end * d].chunks_exact(d);
                for (r, (row, &s)) in rows.zip(&scales[start..end]).enumerate() {
                    let i = start + r;
                    if keep(i) {
                        let mut o = dots_q::<S, i8, Q>(row, qs);
                        for x in &mut o {
                            *x *= s;
                        }
                        sink(i, &o);
                    }
                }
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::{Keep, Simd, StoredVectors, chunk_body, f16};
    use std::arch::x86_64::*;

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
    }

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
    }

    /// [`chunk_body`] compiled for AVX2 + FMA + F16C.
    #[target_feature(enable = "avx2,fma,f16c")]
    pub fn chunk_avx2<const Q: usize>(
        vectors: &StoredVectors,
        d: usize,
        start: usize,
        end: usize,
        qs: &[&[f32]; Q],
        keep: Keep<'_>,
        sink: &mut dyn FnMut(usize, &[f32; Q]),
    ) {
        // SAFETY: this function is compiled for (and only called on CPUs with) AVX2+FMA+F16C.
        unsafe { chunk_body::<Avx2, Q>(vectors, d, start, end, qs, keep, sink) }
    }

    /// [`chunk_body`] compiled for AVX-512F.
    #[target_feature(enable = "avx512f,avx2,fma,f16c")]
    pub fn chunk_avx512<const Q: usize>(
        vectors: &StoredVectors,
        d: usize,
        start: usize,
        end: usize,
        qs: &[&[f32]; Q],
        keep: Keep<'_>,
        sink: &mut dyn FnMut(usize, &[f32; Q]),
    ) {
        // SAFETY: this function is compiled for (and only called on CPUs with) AVX-512F.
        unsafe { chunk_body::<Avx512, Q>(vectors, d, start, end, qs, keep, sink) }
    }
}

#[cfg(target_arch = "aarch64")]
mod arm {
    use super::{Keep, Simd, StoredVectors, chunk_body, f16};
    use std::arch::aarch64::*;

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
            // FCVTL2 (half → single, exact) are base AdvSIMD instructions (no FP16 extension
            // needed); written as `asm!` because the `float16x4_t` intrinsics need a newer Rust
            // than the workspace's minimum.
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
    }

    /// [`chunk_body`] with NEON (FMLA; FCVTL for f16; SXTL + SCVTF for int8).
    pub fn chunk_neon<const Q: usize>(
        vectors: &StoredVectors,
        d: usize,
        start: usize,
        end: usize,
        qs: &[&[f32]; Q],
        keep: Keep<'_>,
        sink: &mut dyn FnMut(usize, &[f32; Q]),
    ) {
        // SAFETY: NEON is part of the aarch64 baseline.
        unsafe { chunk_body::<Neon, Q>(vectors, d, start, end, qs, keep, sink) }
    }

    /// `acc += Σ` of 4-byte groups of `a ⊙ b` per lane (SDOT). Needs `dotprod`.
    #[inline(always)]
    fn sdot(acc: int32x4_t, a: int8x16_t, b: int8x16_t) -> int32x4_t {
        let mut acc = acc;
        // SAFETY: only inlined into `chunk_i8_sdot`, which is compiled for and only called on
        // CPUs with `dotprod`; register-only instruction. (`vdotq_s32` is not stable yet.)
        unsafe {
            std::arch::asm!(
                "sdot {acc:v}.4s, {a:v}.16b, {b:v}.16b",
                acc = inout(vreg) acc,
                a = in(vreg) a,
                b = in(vreg) b,
                options(pure, nomem, nostack, preserves_flags)
            );
        }
        acc
    }

    /// int8 rows with SDOT against three-term int8 splits of the queries (module doc).
    #[target_feature(enable = "neon,dotprod")]
    #[allow(clippy::too_many_arguments)]
    pub fn chunk_i8_sdot<const Q: usize>(
        q: &[i8],
        scales: &[f32],
        d: usize,
        start: usize,
        end: usize,
        qs: &[&[f32]; Q],
        keep: Keep<'_>,
        sink: &mut dyn FnMut(usize, &[f32; Q]),
    ) {
        let (terms, steps) = super::split_queries(qs, d);
        let tq: [[&[i8]; 3]; Q] =
            std::array::from_fn(|k| std::array::from_fn(|t| &terms[(k * 3 + t) * d..][..d]));
        let rows = q[start * d..end * d].chunks_exact(d);
        for (r, (row, &s)) in rows.zip(&scales[start..end]).enumerate() {
            let i = start + r;
            if !keep(i) {
                continue;
            }
            // SAFETY: pointer reads of 16 bytes at `j`, `j + 16 <= d` by the loop condition;
            // `row` and every `tq[k][t]` have `d` values (sliced above); NEON is baseline.
            let sums: [[i32; 3]; Q] = unsafe {
                let mut acc = [[vdupq_n_s32(0); 3]; Q];
                let mut j = 0;
                while j + 16 <= d {
                    let x = vld1q_s8(row.as_ptr().add(j));
                    for k in 0..Q {
                        for t in 0..3 {
                            let y = vld1q_s8(tq[k][t].as_ptr().add(j));
                            acc[k][t] = sdot(acc[k][t], x, y);
                        }
                    }
                    j += 16;
                }
                std::array::from_fn(|k| {
                    std::array::from_fn(|t| {
                        let tail: i32 = row[j..]
                            .iter()
                            .zip(&tq[k][t][j..])
                            .map(|(&a, &b)| a as i32 * b as i32)
                            .sum();
                        vaddvq_s32(acc[k][t]) + tail
                    })
                })
            };
            let out: [f32; Q] = std::array::from_fn(|k| {
                let [a, b, c] = sums[k];
                let st = steps[k];
                s * (st[0] * a as f32 + st[1] * b as f32 + st[2] * c as f32)
            });
            sink(i, &out);
        }
    }
}

/// Splits every query (`[d]`, finite) into three int8 vectors `a, b, c` and steps
/// `[s1, s2, s3]` with `y ≈ s1·a + s2·b + s3·c` (module doc). Returns the terms as one
/// `[Q · 3 · d]` vector (query-major, then term) and the steps per query. A zero query gives
/// zero terms and steps.
#[cfg_attr(not(target_arch = "aarch64"), allow(dead_code))]
pub(super) fn split_queries<const Q: usize>(qs: &[&[f32]; Q], d: usize) -> (Vec<i8>, [[f32; 3]; Q]) {
    let mut terms = vec![0i8; Q * 3 * d];
    let mut steps = [[0.0f32; 3]; Q];
    for (k, y) in qs.iter().enumerate() {
        let m = y.iter().fold(0.0f64, |a, &v| a.max((v as f64).abs()));
        if m == 0.0 || !m.is_finite() {
            continue;
        }
        // The steps are rounded to f32 first (the kernel multiplies by the f32 values), so the
        // residual of each term is taken against the step that is actually applied.
        let s = [m / 127.0, m / (127.0 * 254.0), m / (127.0 * 254.0 * 254.0)]
            .map(|x| x as f32 as f64);
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

/// Runs the chunk scan at `level` (see `kernels::scan_chunk_at`) when that level is an explicit
/// SIMD kernel of this build target and the CPU has it; returns `false` (nothing done) otherwise.
#[allow(clippy::too_many_arguments)]
pub(super) fn chunk<const Q: usize>(
    level: SimdLevel,
    vectors: &StoredVectors,
    d: usize,
    start: usize,
    end: usize,
    qs: &[&[f32]; Q],
    keep: Keep<'_>,
    sink: &mut dyn FnMut(usize, &[f32; Q]),
) -> bool {
    if !level.available() {
        return false;
    }
    match level {
        #[cfg(target_arch = "x86_64")]
        SimdLevel::Avx2Fma => {
            // SAFETY: `level.available()` confirmed AVX2 + FMA + F16C on this CPU.
            unsafe { x86::chunk_avx2::<Q>(vectors, d, start, end, qs, keep, sink) };
            true
        }
        #[cfg(target_arch = "x86_64")]
        SimdLevel::Avx512 => {
            // SAFETY: `level.available()` confirmed AVX-512F + AVX2 + FMA + F16C.
            unsafe { x86::chunk_avx512::<Q>(vectors, d, start, end, qs, keep, sink) };
            true
        }
        #[cfg(target_arch = "aarch64")]
        SimdLevel::Neon => {
            arm::chunk_neon::<Q>(vectors, d, start, end, qs, keep, sink);
            true
        }
        #[cfg(target_arch = "aarch64")]
        SimdLevel::NeonDotprod => {
            match vectors {
                StoredVectors::I8 { q, scales } => {
                    // SAFETY: `level.available()` confirmed `dotprod` on this CPU.
                    unsafe { arm::chunk_i8_sdot::<Q>(q, scales, d, start, end, qs, keep, sink) }
                }
                _ => arm::chunk_neon::<Q>(vectors, d, start, end, qs, keep, sink),
            }
            true
        }
        _ => false,
    }
}
