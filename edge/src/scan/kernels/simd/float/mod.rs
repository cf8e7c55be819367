//! The f32-accumulating kernels, generic over the instruction set ([`Simd`]; one file per set:
//! `avx2.rs`, `avx512.rs`, `neon.rs`).
//!
//! Every kernel converts the stored row in registers, never through a buffer: per block of `W`
//! values one load (+ `vcvtph2ps` / `FCVTL` / sign-extend + `cvt`) feeds `Q` fused multiply-adds,
//! one per query, into f32 accumulators (`U` blocks in flight for small `Q` to hide the FMA
//! latency). The tail (`D mod W`) is a scalar loop. Results differ from the scalar reference by
//! f32 rounding only.

use half::f16;
use slag_common::shards::StoredVectors;

use crate::scan::kernels::queries::RowSpan;

#[cfg(target_arch = "x86_64")]
pub(super) mod avx2;
#[cfg(target_arch = "x86_64")]
pub(super) mod avx512;
#[cfg(target_arch = "aarch64")]
pub(super) mod neon;

/// One vector instruction set: `W` f32 lanes in a `V`.
pub(super) trait Simd {
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
pub(super) fn prefetch_row<S: Simd, T>(all: &[T], row_start: usize, row_len: usize) {
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

/// `impl Elem for $t`: widening `$to_f32` and the vector load `Simd::$load`.
macro_rules! impl_elem {
    ($($t:ty => $to_f32:expr, $load:ident;)+) => {$(
        impl Elem for $t {
            #[inline(always)]
            fn to_f32(self) -> f32 {
                $to_f32(self)
            }
            #[inline(always)]
            unsafe fn load<S: Simd>(p: *const Self) -> S::V {
                // SAFETY: forwarded contract.
                unsafe { S::$load(p) }
            }
        }
    )+};
}

impl_elem! {
    f32 => std::convert::identity, load_f32;
    f16 => f16::to_f32, load_f16;
    i8 => f32::from, load_i8;
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

/// The chunk scan (rows `start..end`, see [`crate::scan::kernels::scan_chunk_at`]) with `S` for every dtype:
/// `out[r]` = the `Q` dots of row `start + r` for every kept row (others are left untouched).
///
/// # Safety
/// The CPU has `S`'s instruction set.
#[inline(always)]
unsafe fn chunk_body<S: Simd, const Q: usize>(
    vectors: &StoredVectors,
    span: RowSpan<'_>,
    qs: &[&[f32]; Q],
    out: &mut [[f32; Q]],
) {
    let RowSpan { d, start, end, .. } = span;
    // One query over f32 / int8 rows: several rows per step (measured faster there; for f16 the
    // one-row loop measured faster, `slag-edge bench`).
    if Q == 1 && !matches!(vectors, StoredVectors::F16(_)) {
        // SAFETY: forwarded contract (the CPU has `S`).
        unsafe { chunk_q1::<S, Q>(vectors, span, qs, out) };
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
                    if span.keeps(i) {
                        *o = dots_q::<S, f32, Q>(row, qs);
                    }
                }
            }
            StoredVectors::F16(v) => {
                let rows = v[start * d..end * d].chunks_exact(d);
                for (r, (row, o)) in rows.zip(out.iter_mut()).enumerate() {
                    let i = start + r;
                    prefetch_row::<S, f16>(v, i * d, d);
                    if span.keeps(i) {
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
                    if span.keeps(i) {
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

/// [`chunk_body`] for one query: [`ROWS_Q1`] rows per step through [`dots_rows`] (the rest one
/// by one); a step whose rows are all filtered out is skipped.
///
/// # Safety
/// The CPU has `S`'s instruction set.
#[inline(always)]
unsafe fn chunk_q1<S: Simd, const Q: usize>(
    vectors: &StoredVectors,
    span: RowSpan<'_>,
    qs: &[&[f32]; Q],
    out: &mut [[f32; Q]],
) {
    let RowSpan { d, start, end, .. } = span;
    let kept = |i: usize| span.keeps(i);
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
