//! The portable kernels: the build target's baseline, no intrinsics ([`super::SimdLevel::Baseline`]).
//!
//! Every kernel is written so that LLVM vectorises it without intrinsics: one dot product walks
//! the row in fixed-size array blocks of [`LANES`] values into [`LANES`] independent accumulators
//! (4 AVX2 / 8 SSE-NEON registers), reduced once at the end. A row is fetched from DRAM once per
//! scan; for `Q > 1` the other `Q - 1` dot products re-read it from L1 (f16/int8 rows are first
//! converted per [`BLOCK`] into a stack buffer, so conversion is paid once), which is what makes a
//! LERF query (positive + 4 canonical negatives) cost one pass over memory.
//!
//! - `f32`: multiply-add (fused on aarch64 and in the AVX2 path).
//! - `f16`: converted per block into a stack buffer: with `half`'s
//!   [`convert_to_f32_slice`](half::slice::HalfFloatSliceExt::convert_to_f32_slice) (F16C on
//!   x86_64 / FP16 on aarch64, detected at run time) in the portable path, with inlined F16C
//!   `vcvtph2ps` (8 values per instruction) in the AVX2 path.
//! - `int8`: `q as f32 · query` accumulated, the per-row scale applied once at the end
//!   (`dot = scale · Σ q_j x_j`).

use half::f16;
use half::slice::HalfFloatSliceExt;
use slag_common::shards::StoredVectors;

use super::queries::RowSpan;

/// Independent accumulators of one dot product (4 AVX2 registers, 8 SSE/NEON registers): enough
/// parallel chains to hide the add/FMA latency.
pub const LANES: usize = 32;

/// Values of a row converted to f32 per block (a 1 KiB stack buffer, stays in L1).
pub const BLOCK: usize = 256;

/// `a · b + c`, fused (one rounding) when `FMA` (only instantiated where the CPU has FMA:
/// otherwise `mul_add` would be a libm call).
#[inline(always)]
fn madd<const FMA: bool>(a: f32, b: f32, c: f32) -> f32 {
    if FMA { a.mul_add(b, c) } else { c + a * b }
}

/// `Σ_j conv(x[j]) · y[j]` over `min(x.len(), y.len())` values with [`LANES`] accumulators.
///
/// Written for LLVM's loop vectoriser: fixed-size array blocks (`as_chunks`), one flat
/// accumulator array, a plain sum at the end (a pairwise reduction tree here makes LLVM fall
/// back to 2-wide vectors).
#[inline(always)]
pub(super) fn dot_conv<T: Copy, const FMA: bool>(
    x: &[T],
    y: &[f32],
    conv: impl Fn(T) -> f32,
) -> f32 {
    let n = x.len().min(y.len());
    let (xb, xr) = x[..n].as_chunks::<LANES>();
    let (yb, yr) = y[..n].as_chunks::<LANES>();
    let mut a = [0.0f32; LANES];
    for (r, q) in xb.iter().zip(yb) {
        for l in 0..LANES {
            a[l] = madd::<FMA>(conv(r[l]), q[l], a[l]);
        }
    }
    let mut t = 0.0f32;
    for (&r, &q) in xr.iter().zip(yr) {
        t = madd::<FMA>(conv(r), q, t);
    }
    a.iter().sum::<f32>() + t
}

/// Accumulators per query in the multi-query loop ([`LANES_MULTI`] · Q ≤ 128 floats: 16 AVX2
/// registers at Q = 8).
pub const LANES_MULTI: usize = 16;

/// `out[q] += Σ_j x[j] · qs[q][off + j]` for all `Q` queries in one sweep over `x`: each block of
/// `x` is loaded once and multiplied into `Q` accumulator arrays (`std::array::from_fn` keeps
/// them as whole vectors for LLVM).
#[inline(always)]
fn dots_multi<const Q: usize, const FMA: bool>(
    x: &[f32],
    qs: &[&[f32]; Q],
    off: usize,
    out: &mut [f32],
) {
    const W: usize = LANES_MULTI;
    let n = x.len();
    let (xb, xr) = x.as_chunks::<W>();
    let mut qb: [&[[f32; W]]; Q] = [&[]; Q];
    let mut qt: [&[f32]; Q] = [&[]; Q];
    for q in 0..Q {
        let (b, t) = qs[q][off..off + n].as_chunks::<W>();
        qb[q] = b;
        qt[q] = t;
    }
    let mut acc = [[0.0f32; W]; Q];
    for (c, r) in xb.iter().enumerate() {
        for q in 0..Q {
            let y = &qb[q][c];
            let a = &mut acc[q];
            *a = std::array::from_fn(|l| madd::<FMA>(r[l], y[l], a[l]));
        }
    }
    for q in 0..Q {
        let mut t = 0.0f32;
        for (&v, &y) in xr.iter().zip(qt[q]) {
            t = madd::<FMA>(v, y, t);
        }
        out[q] += acc[q].iter().sum::<f32>() + t;
    }
}

/// Dot products of one `f32` row with `Q` queries: `out[q] = Σ_j row[j] · qs[q][j]`
/// (fused multiply-add when `FMA`), the row read once.
///
/// Shapes: `row.len() == qs[q].len() == D`, `out.len() >= Q`.
#[inline(always)]
pub fn dots_f32<const Q: usize, const FMA: bool>(row: &[f32], qs: &[&[f32]; Q], out: &mut [f32]) {
    if Q == 1 {
        out[0] = dot_conv::<f32, FMA>(row, qs[0], |x| x);
    } else {
        out[..Q].fill(0.0);
        dots_multi::<Q, FMA>(row, qs, 0, out);
    }
}

/// Dot products of one IEEE-half row with `Q` f32 queries: the row is converted in blocks of
/// [`BLOCK`] values into `buf` by `convert(src, dst)` (equal lengths; e.g.
/// [`convert_f16_portable`]), then the f32 loop runs on the buffer for every query.
///
/// Shapes: `row.len() == qs[q].len() == D`, `out.len() >= Q`.
#[inline(always)]
pub fn dots_f16<const Q: usize, const FMA: bool>(
    row: &[f16],
    qs: &[&[f32]; Q],
    buf: &mut [f32; BLOCK],
    out: &mut [f32],
    convert: impl Fn(&[f16], &mut [f32]),
) {
    out[..Q].fill(0.0);
    let mut off = 0;
    for block in row.chunks(BLOCK) {
        let b = &mut buf[..block.len()];
        convert(block, b);
        if Q == 1 {
            out[0] += dot_conv::<f32, FMA>(b, &qs[0][off..], |x| x);
        } else {
            dots_multi::<Q, FMA>(b, qs, off, out);
        }
        off += block.len();
    }
}

/// Converts f16 values to f32 (`src.len() == dst.len()`) with `half`'s slice conversion (F16C on
/// x86_64 / FP16 on aarch64 when present at run time, exact software conversion otherwise).
#[inline(always)]
pub fn convert_f16_portable(src: &[f16], dst: &mut [f32]) {
    src.convert_to_f32_slice(dst);
}

/// Dot products of one symmetric-int8 row (value `q_j · scale`) with `Q` f32 queries:
/// `out[q] = scale · Σ_j q_j · qs[q][j]` (scale applied once per row). For Q > 1 the row is
/// converted once per [`BLOCK`] into `buf` and reused by every query.
///
/// Shapes: `row.len() == qs[q].len() == D`, `out.len() >= Q`.
#[inline(always)]
pub fn dots_i8<const Q: usize, const FMA: bool>(
    row: &[i8],
    scale: f32,
    qs: &[&[f32]; Q],
    buf: &mut [f32; BLOCK],
    out: &mut [f32],
) {
    if Q == 1 {
        out[0] = scale * dot_conv::<i8, FMA>(row, qs[0], |x| x as f32);
        return;
    }
    out[..Q].fill(0.0);
    let mut off = 0;
    for block in row.chunks(BLOCK) {
        let b = &mut buf[..block.len()];
        for (d, &x) in b.iter_mut().zip(block) {
            *d = x as f32;
        }
        dots_multi::<Q, FMA>(b, qs, off, out);
        off += block.len();
    }
    for o in &mut out[..Q] {
        *o *= scale;
    }
}

/// Scores rows `start..end` of `vectors` (`[N * d]` as stored) against `qs` into `out[r]` (row
/// `start + r`) for every row with `keep(i)` (all rows when `None`; other entries are left
/// untouched). Portable body; `FMA` selects fused multiply-add (only where the CPU has it).
#[inline(always)]
pub(super) fn chunk_impl<const Q: usize, const FMA: bool>(
    vectors: &StoredVectors,
    span: RowSpan<'_>,
    qs: &[&[f32]; Q],
    out: &mut [[f32; Q]],
    convert: impl Fn(&[f16], &mut [f32]) + Copy,
) {
    let RowSpan { d, start, end, .. } = span;
    match vectors {
        StoredVectors::F32(v) => {
            let rows = v[start * d..end * d].chunks_exact(d);
            for (r, (row, o)) in rows.zip(out.iter_mut()).enumerate() {
                if span.keeps(start + r) {
                    dots_f32::<Q, FMA>(row, qs, o);
                }
            }
        }
        StoredVectors::F16(v) => {
            let mut buf = [0.0f32; BLOCK];
            let rows = v[start * d..end * d].chunks_exact(d);
            for (r, (row, o)) in rows.zip(out.iter_mut()).enumerate() {
                if span.keeps(start + r) {
                    dots_f16::<Q, FMA>(row, qs, &mut buf, o, convert);
                }
            }
        }
        StoredVectors::I8 { q, scales } => {
            let mut buf = [0.0f32; BLOCK];
            let rows = q[start * d..end * d].chunks_exact(d);
            let rows = rows.zip(&scales[start..end]).zip(out.iter_mut());
            for (r, ((row, &s), o)) in rows.enumerate() {
                if span.keeps(start + r) {
                    dots_i8::<Q, FMA>(row, s, qs, &mut buf, o);
                }
            }
        }
    }
}
