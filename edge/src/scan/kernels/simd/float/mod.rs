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

use super::kernels::{Keep, Queries, SimdLevel};

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
    /// Hints the cache line holding `p` into L1 (a hint: never faults, any address).
    fn prefetch(p: *const u8);
}

/// Bytes ahead of the current row that [`prefetch_row`] asks for: far enough that a row's DRAM
/// latency is hidden behind the rows in between, across the 4 KiB page boundaries where the
/// hardware prefetchers stop (`slag-edge bench`, int8 top-k ÷ floor: none 2.1, 2 KiB 1.45,
/// 4 KiB 1.16–1.21, 8 KiB 1.3).
pub(super) const PREFETCH_BYTES: usize = 4096;

/// Prefetches the cache lines of the row `PREFETCH_BYTES` ahead of `row` (`bytes` long), when
/// that row still lies inside `all` (no pointer is formed outside the slice).
#[inline(always)]
fn prefetch_row<S: Simd, T>(all: &[T], row_start: usize, row_len: usize) {
    let bytes = std::mem::size_of_val(all);
    let sz = std::mem::size_of::<T>().max(1);
    let at = row_start * sz + PREFETCH_BYTES;
    let len = row_len * sz;
    if at + len <= bytes {
        let base = all.as_ptr().cast::<u8>();
        let mut o = 0;
        while o < len {
            // `at + o < bytes`: inside the slice, so `wrapping_add` stays in bounds.
            S::prefetch(base.wrapping_add(at + o));
            o += 64;
        }
    }
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
#[allow(clippy::needless_range_loop)] // `u` and `q` index several arrays at once
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

/// One query against `R` rows at once: `out[r] = Σ_j rows[r][j] · q[j]`, each query block loaded
/// once for the `R` rows (`R` independent row streams in flight, `2R` accumulators).
///
/// # Safety
/// The CPU has `S`'s instruction set. (Lengths are checked here: every row is re-sliced to
/// `q.len()`, panicking when shorter.)
#[inline(always)]
#[allow(clippy::needless_range_loop)] // `r` and `u` index several arrays at once
unsafe fn dots_rows<S: Simd, T: Elem, const R: usize>(rows: [&[T]; R], q: &[f32]) -> [f32; R] {
    let n = q.len();
    let mut rs: [&[T]; R] = [&[]; R];
    for r in 0..R {
        rs[r] = &rows[r][..n];
    }
    let w = S::W;
    // SAFETY (whole body): the CPU has `S` (caller); every pointer read covers `j + u·w ..
    // j + u·w + w`, inside `0..n` by the loop conditions, and `q` and every `rs[r]` have `n`
    // values.
    unsafe {
        let mut acc = [[S::zero(); 2]; R];
        let mut j = 0;
        while j + 2 * w <= n {
            for u in 0..2 {
                let y = S::load_f32(q.as_ptr().add(j + u * w));
                for r in 0..R {
                    let x = T::load::<S>(rs[r].as_ptr().add(j + u * w));
                    acc[r][u] = S::fma(x, y, acc[r][u]);
                }
            }
            j += 2 * w;
        }
        while j + w <= n {
            let y = S::load_f32(q.as_ptr().add(j));
            for r in 0..R {
                let x = T::load::<S>(rs[r].as_ptr().add(j));
                acc[r][0] = S::fma(x, y, acc[r][0]);
            }
            j += w;
        }
        let mut out = [0.0f32; R];
        for r in 0..R {
            let mut t = 0.0f32;
            for k in j..n {
                t += rs[r][k].to_f32() * q[k];
            }
            out[r] = S::sum(acc[r][0]) + S::sum(acc[r][1]) + t;
        }
        out
    }
}

/// Rows per step of the one-query kernels ([`dots_rows`]).
const ROWS_Q1: usize = 4;

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

/// The chunk scan (rows `start..end`, see `kernels::scan_chunk_at`) with `S` for every dtype:
/// `out[r]` = the `Q` dots of row `start + r` for every kept row (others are left untouched).
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
    keep: Option<Keep<'_>>,
    out: &mut [[f32; Q]],
) {
    let kept = |i: usize| keep.is_none_or(|k| k(i));
    // One query over f32 / int8 rows: several rows per step (measured faster there; for f16 the
    // one-row loop measured faster, `slag-edge bench`).
    if Q == 1 && !matches!(vectors, StoredVectors::F16(_)) {
        // SAFETY: forwarded contract (the CPU has `S`).
        unsafe { chunk_q1::<S, Q>(vectors, d, start, end, qs, keep, out) };
        return;
    }
    // SAFETY: forwarded contract (the CPU has `S`).
    unsafe {
        match vectors {
            StoredVectors::F32(v) => {
                let rows = v[start * d..end * d].chunks_exact(d);
                for (r, (row, o)) in rows.zip(out.iter_mut()).enumerate() {
                    let i = start + r;
                    prefetch_row::<S, f32>(v, i * d, d);
                    if kept(i) {
                        *o = dots_q::<S, f32, Q>(row, qs);
                    }
                }
            }
            StoredVectors::F16(v) => {
                let rows = v[start * d..end * d].chunks_exact(d);
                for (r, (row, o)) in rows.zip(out.iter_mut()).enumerate() {
                    let i = start + r;
                    prefetch_row::<S, f16>(v, i * d, d);
                    if kept(i) {
                        *o = dots_q::<S, f16, Q>(row, qs);
                    }
                }
            }
            StoredVectors::I8 { q, scales } => {
                let rows = q[start * d..end * d].chunks_exact(d);
                let rows = rows.zip(&scales[start..end]).zip(out.iter_mut());
                for (r, ((row, &s), o)) in rows.enumerate() {
                    let i = start + r;
                    prefetch_row::<S, i8>(q, i * d, d);
                    if kept(i) {
                        let mut x = dots_q::<S, i8, Q>(row, qs);
                        for v in &mut x {
                            *v *= s;
                        }
                        *o = x;
                    }
                }
            }
        }
    }
}

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
#[allow(clippy::too_many_arguments)]
unsafe fn chunk_i8_split<K: I8Dot, const Q: usize, const R: usize>(
    q: &[i8],
    scales: &[f32],
    d: usize,
    start: usize,
    end: usize,
    qs: &Queries<'_, Q>,
    keep: Option<Keep<'_>>,
    out: &mut [[f32; Q]],
) {
    let kept = |i: usize| keep.is_none_or(|k| k(i));
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
            any |= kept(i + r);
        }
        if any {
            let mut rows: [&[i8]; R] = [&[]; R];
            for (r, x) in rows.iter_mut().enumerate() {
                *x = row(i + r);
            }
            // SAFETY: the CPU has `K` (caller).
            let sums = unsafe { i8_sums::<K, Q, R>(rows, &tq, &offs, body) };
            for r in 0..R {
                if kept(i + r) {
                    finish(i + r, &sums[r], &mut out[i + r - start]);
                }
            }
        }
        i += R;
    }
    while i < end {
        if kept(i) {
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
#[allow(clippy::too_many_arguments)]
unsafe fn chunk_i8_split_q<K: I8Dot, const Q: usize>(
    q: &[i8],
    scales: &[f32],
    d: usize,
    start: usize,
    end: usize,
    qs: &Queries<'_, Q>,
    keep: Option<Keep<'_>>,
    out: &mut [[f32; Q]],
) {
    // SAFETY: forwarded contract.
    unsafe {
        if Q <= 2 {
            chunk_i8_split::<K, Q, 4>(q, scales, d, start, end, qs, keep, out)
        } else {
            chunk_i8_split::<K, Q, 1>(q, scales, d, start, end, qs, keep, out)
        }
    }
}

/// [`chunk_body`] for one query: [`ROWS_Q1`] rows per step through [`dots_rows`] (the rest one
/// by one); a step whose rows are all filtered out is skipped.
///
/// # Safety
/// The CPU has `S`'s instruction set.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
unsafe fn chunk_q1<S: Simd, const Q: usize>(
    vectors: &StoredVectors,
    d: usize,
    start: usize,
    end: usize,
    qs: &[&[f32]; Q],
    keep: Option<Keep<'_>>,
    out: &mut [[f32; Q]],
) {
    let kept = |i: usize| keep.is_none_or(|k| k(i));
    let q = qs[0];
    /// Scores rows `start..end` of `v` (row `i` scaled by `scale(i)`) into `out`.
    #[inline(always)]
    unsafe fn run<S: Simd, T: Elem, const Q: usize>(
        v: &[T],
        d: usize,
        (start, end): (usize, usize),
        q: &[f32],
        kept: &dyn Fn(usize) -> bool,
        scale: &dyn Fn(usize) -> f32,
        out: &mut [[f32; Q]],
    ) {
        let mut i = start;
        while i + ROWS_Q1 <= end {
            let mut any = false;
            let mut rows: [&[T]; ROWS_Q1] = [&[]; ROWS_Q1];
            for r in 0..ROWS_Q1 {
                prefetch_row::<S, T>(v, (i + r) * d, d);
                any |= kept(i + r);
                rows[r] = &v[(i + r) * d..(i + r + 1) * d];
            }
            if any {
                // SAFETY: the CPU has `S` (caller).
                let dots = unsafe { dots_rows::<S, T, ROWS_Q1>(rows, q) };
                for r in 0..ROWS_Q1 {
                    if kept(i + r) {
                        out[i + r - start][0] = dots[r] * scale(i + r);
                    }
                }
            }
            i += ROWS_Q1;
        }
        while i < end {
            if kept(i) {
                // SAFETY: the CPU has `S` (caller).
                let dots = unsafe { dots_rows::<S, T, 1>([&v[i * d..(i + 1) * d]], q) };
                out[i - start][0] = dots[0] * scale(i);
            }
            i += 1;
        }
    }
    // SAFETY: forwarded contract (the CPU has `S`).
    unsafe {
        match vectors {
            StoredVectors::F32(v) => run::<S, f32, Q>(v, d, (start, end), q, &kept, &|_| 1.0, out),
            // (Not reached from `chunk_body`, which keeps f16 on the one-row loop.)
            StoredVectors::F16(v) => run::<S, f16, Q>(v, d, (start, end), q, &kept, &|_| 1.0, out),
            StoredVectors::I8 { q: b, scales } => {
                run::<S, i8, Q>(b, d, (start, end), q, &kept, &|i| scales[i], out)
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::{
        I8Dot, Keep, Queries, Simd, StoredVectors, chunk_body, chunk_i8_split_q, dots_q, f16,
    };
    use std::arch::x86_64::*;

    /// `prefetcht0` (SSE, part of the x86_64 baseline).
    #[inline(always)]
    fn prefetch_t0(p: *const u8) {
        // SAFETY: SSE is in the x86_64 baseline; a prefetch is a hint that never faults and
        // reads nothing visible to the program, whatever the address.
        unsafe { _mm_prefetch::<_MM_HINT_T0>(p.cast()) }
    }

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

    /// [`chunk_body`] compiled for AVX2 + FMA + F16C.
    #[target_feature(enable = "avx2,fma,f16c")]
    pub fn chunk_avx2<const Q: usize>(
        vectors: &StoredVectors,
        d: usize,
        start: usize,
        end: usize,
        qs: &[&[f32]; Q],
        keep: Option<Keep<'_>>,
        out: &mut [[f32; Q]],
    ) {
        // SAFETY: this function is compiled for (and only called on CPUs with) AVX2+FMA+F16C.
        unsafe { chunk_body::<Avx2, Q>(vectors, d, start, end, qs, keep, out) }
    }

    /// [`chunk_body`] compiled for AVX-512F.
    #[target_feature(enable = "avx512f,avx2,fma,f16c")]
    pub fn chunk_avx512<const Q: usize>(
        vectors: &StoredVectors,
        d: usize,
        start: usize,
        end: usize,
        qs: &[&[f32]; Q],
        keep: Option<Keep<'_>>,
        out: &mut [[f32; Q]],
    ) {
        // SAFETY: this function is compiled for (and only called on CPUs with) AVX-512F.
        unsafe { chunk_body::<Avx512, Q>(vectors, d, start, end, qs, keep, out) }
    }

    /// One f32 dot product `a · b` (`b` at least as long as `a`) with AVX2 + FMA (the HNSW
    /// graph's distance, [`super::dot_f32`]).
    #[target_feature(enable = "avx2,fma,f16c")]
    pub fn dot_f32_avx2(a: &[f32], b: &[f32]) -> f32 {
        // SAFETY: compiled for (and only called on CPUs with) AVX2 + FMA + F16C.
        unsafe { dots_q::<Avx2, f32, 1>(a, &[b])[0] }
    }

    /// [`dot_f32_avx2`] with AVX-512F.
    #[target_feature(enable = "avx512f,avx2,fma,f16c")]
    pub fn dot_f32_avx512(a: &[f32], b: &[f32]) -> f32 {
        // SAFETY: compiled for (and only called on CPUs with) AVX-512F.
        unsafe { dots_q::<Avx512, f32, 1>(a, &[b])[0] }
    }

    /// int8 rows with `vpdpbusd` against three-term int8 splits of the queries (module doc).
    #[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
    #[allow(clippy::too_many_arguments)]
    pub fn chunk_i8_vnni<const Q: usize>(
        q: &[i8],
        scales: &[f32],
        d: usize,
        start: usize,
        end: usize,
        qs: &Queries<'_, Q>,
        keep: Option<Keep<'_>>,
        out: &mut [[f32; Q]],
    ) {
        // SAFETY: compiled for (and only called on CPUs with) AVX-512F/BW/VNNI.
        unsafe { chunk_i8_split_q::<Vnni512, Q>(q, scales, d, start, end, qs, keep, out) }
    }
}

#[cfg(target_arch = "aarch64")]
mod arm {
    use super::{
        I8Dot, Keep, Queries, Simd, StoredVectors, chunk_body, chunk_i8_split_q, dots_q, f16,
    };
    use std::arch::aarch64::*;

    /// `prfm pldl1keep` (a hint: never faults).
    #[inline(always)]
    fn prefetch_l1(p: *const u8) {
        // SAFETY: PRFM is a base AArch64 instruction; a prefetch never faults and has no effect
        // visible to the program, whatever the address.
        unsafe {
            std::arch::asm!(
                "prfm pldl1keep, [{p}]",
                p = in(reg) p,
                options(nostack, preserves_flags, readonly)
            );
        }
    }

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

    /// [`chunk_body`] with NEON (FMLA; FCVTL for f16; SXTL + SCVTF for int8).
    pub fn chunk_neon<const Q: usize>(
        vectors: &StoredVectors,
        d: usize,
        start: usize,
        end: usize,
        qs: &[&[f32]; Q],
        keep: Option<Keep<'_>>,
        out: &mut [[f32; Q]],
    ) {
        // SAFETY: NEON is part of the aarch64 baseline.
        unsafe { chunk_body::<Neon, Q>(vectors, d, start, end, qs, keep, out) }
    }

    /// One f32 dot product `a · b` (`b` at least as long as `a`) with NEON FMLA (the HNSW
    /// graph's distance, [`super::dot_f32`]).
    pub fn dot_f32_neon(a: &[f32], b: &[f32]) -> f32 {
        // SAFETY: NEON is part of the aarch64 baseline.
        unsafe { dots_q::<Neon, f32, 1>(a, &[b])[0] }
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
        qs: &Queries<'_, Q>,
        keep: Option<Keep<'_>>,
        out: &mut [[f32; Q]],
    ) {
        // SAFETY: compiled for (and only called on CPUs with) `dotprod`.
        unsafe { chunk_i8_split_q::<Sdot, Q>(q, scales, d, start, end, qs, keep, out) }
    }
}

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

/// Splits every query (`[d]`, finite) into three int8 vectors `a, b, c` and steps
/// `[s1, s2, s3]` with `y ≈ s1·a + s2·b + s3·c` (module doc). Returns the terms as one
/// `[Q · 3 · d]` vector (query-major, then term) and the steps per query. A zero query gives
/// zero terms and steps.
pub(super) fn split_queries<const Q: usize>(
    qs: &[&[f32]; Q],
    d: usize,
) -> (Vec<i8>, [[f32; 3]; Q]) {
    let mut terms = vec![0i8; Q * 3 * d];
    let mut steps = [[0.0f32; 3]; Q];
    for (k, y) in qs.iter().enumerate() {
        let m = y.iter().fold(0.0f64, |a, &v| a.max((v as f64).abs()));
        if m == 0.0 || !m.is_finite() {
            continue;
        }
        // The steps are rounded to f32 first (the kernel multiplies by the f32 values), so the
        // residual of each term is taken against the step that is actually applied.
        let s =
            [m / 127.0, m / (127.0 * 254.0), m / (127.0 * 254.0 * 254.0)].map(|x| x as f32 as f64);
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
    queries: &Queries<'_, Q>,
    keep: Option<Keep<'_>>,
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
            unsafe { x86::chunk_avx2::<Q>(vectors, d, start, end, qs, keep, out) };
            true
        }
        #[cfg(target_arch = "x86_64")]
        SimdLevel::Avx512 => {
            // SAFETY: `level.available()` confirmed AVX-512F + AVX2 + FMA + F16C
            // (`is_x86_feature_detected!`).
            unsafe { x86::chunk_avx512::<Q>(vectors, d, start, end, qs, keep, out) };
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
                    unsafe { x86::chunk_i8_vnni::<Q>(q, scales, d, start, end, queries, keep, out) }
                }
                // SAFETY: as above (Avx512Vnni implies Avx512).
                _ => unsafe { x86::chunk_avx512::<Q>(vectors, d, start, end, qs, keep, out) },
            }
            true
        }
        #[cfg(target_arch = "aarch64")]
        SimdLevel::Neon => {
            arm::chunk_neon::<Q>(vectors, d, start, end, qs, keep, out);
            true
        }
        #[cfg(target_arch = "aarch64")]
        SimdLevel::NeonDotprod => {
            match vectors {
                StoredVectors::I8 { q, scales } => {
                    // SAFETY: `level.available()` confirmed `dotprod` on this CPU
                    // (`is_aarch64_feature_detected!`).
                    unsafe { arm::chunk_i8_sdot::<Q>(q, scales, d, start, end, queries, keep, out) }
                }
                _ => arm::chunk_neon::<Q>(vectors, d, start, end, qs, keep, out),
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
            Some(unsafe { x86::dot_f32_avx2(a, b) })
        }
        #[cfg(target_arch = "x86_64")]
        SimdLevel::Avx512 | SimdLevel::Avx512Vnni => {
            // SAFETY: `level.available()` confirmed AVX-512F + AVX2 + FMA + F16C.
            Some(unsafe { x86::dot_f32_avx512(a, b) })
        }
        #[cfg(target_arch = "aarch64")]
        SimdLevel::Neon | SimdLevel::NeonDotprod => Some(arm::dot_f32_neon(a, b)),
        _ => None,
    }
}
