//! The integer dot-product kernels for int8 rows, generic over the instruction set ([`I8Dot`];
//! one file per set: `avx512_vnni.rs`, `neon_sdot.rs`).
//!
//! The row stays int8; every f32 query `y` is split once per
//! chunk into three int8 vectors with steps `s1 = max|y| / 127`, `s2 = s1 / 254`, `s3 = s2 / 254`
//! (`y ≈ s1·a + s2·b + s3·c`, error ≤ `max|y| / (2·127·254²)` ≈ 6e-8·max|y| per component), and
//! `row·y = scale · (s1·Σx·a + s2·Σx·b + s3·Σx·c)` with exact i32 sums (three `SDOT`s per 16 row
//! bytes). The sums are exact in f32 while `127²·D < 2²⁴` (D ≤ 1040).

use half::f16;

use super::float::{Simd, prefetch_row};
use crate::scan::kernels::queries::{Queries, RowSpan};

#[cfg(target_arch = "x86_64")]
pub(super) mod avx512_vnni;
#[cfg(target_arch = "aarch64")]
pub(super) mod neon_sdot;

/// Integer dot-product instructions for int8 rows against int8 query terms (SDOT on aarch64,
/// VPDPBUSD on x86_64): `W` row bytes per step, i32 lane accumulators.
trait I8Dot {
    /// i32 accumulator lanes.
    type Acc: Copy;
    /// `W` int8 (or offset u8) values.
    type X: Copy;
    /// Row bytes per step.
    const W: usize;
    /// Added to every row value by [`I8Dot::load_row`] (VPDPBUSD multiplies unsigned by signed
    /// bytes, so rows are shifted by +128 and `128 · Σ term` is subtracted afterwards).
    const OFFSET: i32;
    /// # Safety
    /// The CPU has the instructions.
    unsafe fn zero() -> Self::Acc;
    /// `W` row bytes from `p` (+ [`I8Dot::OFFSET`]).
    /// # Safety
    /// As [`I8Dot::zero`]; `p` points at `W` readable bytes.
    unsafe fn load_row(p: *const i8) -> Self::X;
    /// `W` query-term bytes from `p`.
    /// # Safety
    /// As [`I8Dot::load_row`].
    unsafe fn load_term(p: *const i8) -> Self::X;
    /// `acc` + the 4-byte-group dot products of `x` and `y` per i32 lane.
    /// # Safety
    /// As [`I8Dot::zero`].
    unsafe fn dot(acc: Self::Acc, x: Self::X, y: Self::X) -> Self::Acc;
    /// Sum of the lanes.
    /// # Safety
    /// As [`I8Dot::zero`].
    unsafe fn sum(acc: Self::Acc) -> i32;
    /// As [`Simd::prefetch`].
    fn prefetch(p: *const u8);
}

/// Prefetch-only view of an [`I8Dot`] for [`prefetch_row`].
struct PrefetchOf<K>(std::marker::PhantomData<K>);

impl<K: I8Dot> Simd for PrefetchOf<K> {
    type V = ();
    const W: usize = 1;
    unsafe fn zero() {}
    unsafe fn fma(_: (), _: (), _: ()) {}
    unsafe fn sum(_: ()) -> f32 {
        0.0
    }
    unsafe fn load_f32(_: *const f32) {}
    unsafe fn load_f16(_: *const f16) {}
    unsafe fn load_i8(_: *const i8) {}
    #[inline(always)]
    fn prefetch(p: *const u8) {
        K::prefetch(p)
    }
}

/// Exact i32 sums `Σ_j rows[r][j] · term_k,t,j` of `R` int8 rows against every query term (`R`
/// rows share each term load; `R · Q · 3` independent accumulators). `offs[k][t]` =
/// `K::OFFSET · Σ_{j<body} term_k,t,j` undoes the row offset; `body` = `d` rounded down to `K::W`,
/// the rest is summed in scalar code.
///
/// # Safety
/// The CPU has `K`'s instructions; every row and term has at least `body` values (it is checked:
/// the tails are sliced from `body`, which panics on a shorter slice before any pointer read).
#[inline(always)]
unsafe fn i8_sums<K: I8Dot, const Q: usize, const R: usize>(
    rows: [&[i8]; R],
    tq: &[[&[i8]; 3]; Q],
    offs: &[[i32; 3]; Q],
    body: usize,
) -> [[[i32; 3]; Q]; R] {
    let w = K::W;
    let mut sums = [[[0i32; 3]; Q]; R];
    // Plain loops, not closures: a closure body is not compiled with the caller's target
    // features, so intrinsics inside it would become calls. The tails first: they bound-check
    // every slice against `body`.
    for r in 0..R {
        for k in 0..Q {
            for t in 0..3 {
                let mut v = -offs[k][t];
                for (&a, &b) in rows[r][body..].iter().zip(&tq[k][t][body..]) {
                    v += a as i32 * b as i32;
                }
                sums[r][k][t] = v;
            }
        }
    }
    // SAFETY: the CPU has `K` (caller); every read covers `j .. j + w` with `j + w <= body`, and
    // every row and term has at least `body` values (checked by the slicing above).
    unsafe {
        let mut acc = [[[K::zero(); 3]; Q]; R];
        let mut j = 0;
        while j + w <= body {
            let mut x = [K::load_row(rows[0].as_ptr().add(j)); R];
            for r in 1..R {
                x[r] = K::load_row(rows[r].as_ptr().add(j));
            }
            for k in 0..Q {
                for t in 0..3 {
                    let y = K::load_term(tq[k][t].as_ptr().add(j));
                    for r in 0..R {
                        acc[r][k][t] = K::dot(acc[r][k][t], x[r], y);
                    }
                }
            }
            j += w;
        }
        for r in 0..R {
            for k in 0..Q {
                for t in 0..3 {
                    sums[r][k][t] += K::sum(acc[r][k][t]);
                }
            }
        }
    }
    sums
}

/// int8 rows against three-term int8 splits of the queries (module doc), `R` rows at a time:
/// `out[r][k] = scale_i · Σ_t step_k,t · Σ_j row_j · term_k,t,j` with exact i32 sums.
///
/// # Safety
/// The CPU has `K`'s instructions.
#[inline(always)]
unsafe fn chunk_i8_split<K: I8Dot, const Q: usize, const R: usize>(
    q: &[i8],
    scales: &[f32],
    span: RowSpan<'_>,
    qs: &Queries<'_, Q>,
    out: &mut [[f32; Q]],
) {
    let RowSpan { d, start, end, .. } = span;
    let body = d - d % K::W;
    let split = qs.split(d);
    let (terms, steps) = (&split.terms, &split.steps);
    let mut tq: [[&[i8]; 3]; Q] = [[&[]; 3]; Q];
    let mut offs = [[0i32; 3]; Q];
    for k in 0..Q {
        for t in 0..3 {
            tq[k][t] = &terms[(k * 3 + t) * d..][..d];
            offs[k][t] = K::OFFSET * tq[k][t][..body].iter().map(|&a| a as i32).sum::<i32>();
        }
    }
    let row = |i: usize| &q[i * d..(i + 1) * d];
    let finish = |i: usize, sums: &[[i32; 3]; Q], o: &mut [f32; Q]| {
        let s = scales[i];
        for k in 0..Q {
            let [a, b, c] = sums[k];
            let st = steps[k];
            o[k] = s * (st[0] * a as f32 + st[1] * b as f32 + st[2] * c as f32);
        }
    };
    let mut i = start;
    while i + R <= end {
        for r in 0..R {
            prefetch_row::<PrefetchOf<K>, i8>(q, (i + r) * d, d);
        }
        let mut any = false;
        for r in 0..R {
            any |= span.keeps(i + r);
        }
        if any {
            let mut rows: [&[i8]; R] = [&[]; R];
            for (r, x) in rows.iter_mut().enumerate() {
                *x = row(i + r);
            }
            // SAFETY: the CPU has `K` (caller).
            let sums = unsafe { i8_sums::<K, Q, R>(rows, &tq, &offs, body) };
            for r in 0..R {
                if span.keeps(i + r) {
                    finish(i + r, &sums[r], &mut out[i + r - start]);
                }
            }
        }
        i += R;
    }
    while i < end {
        if span.keeps(i) {
            // SAFETY: the CPU has `K` (caller).
            let sums = unsafe { i8_sums::<K, Q, 1>([row(i)], &tq, &offs, body) };
            finish(i, &sums[0], &mut out[i - start]);
        }
        i += 1;
    }
}

/// [`chunk_i8_split`] with the rows per step chosen for `Q` (4 rows for one or two queries,
/// 12 / 24 accumulators; one row beyond, 3·Q accumulators).
///
/// # Safety
/// As [`chunk_i8_split`].
#[inline(always)]
unsafe fn chunk_i8_split_q<K: I8Dot, const Q: usize>(
    q: &[i8],
    scales: &[f32],
    span: RowSpan<'_>,
    qs: &Queries<'_, Q>,
    out: &mut [[f32; Q]],
) {
    // SAFETY: forwarded contract.
    unsafe {
        if Q <= 2 {
            chunk_i8_split::<K, Q, 4>(q, scales, span, qs, out)
        } else {
            chunk_i8_split::<K, Q, 1>(q, scales, span, qs, out)
        }
    }
}
