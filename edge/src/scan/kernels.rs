//! Inner loops: dot products of `Q` query vectors (1 ≤ Q ≤ [`MAX_QUERIES`]) with one stored row,
//! for `f32`, `f16` and symmetric-int8 rows.
//!
//! Every kernel is written so that LLVM vectorises it without `unsafe` or intrinsics: the row is
//! walked in fixed blocks of [`LANES`] values, each query keeps [`LANES`] independent accumulators
//! (an array that lives in SIMD registers), and the lanes are reduced once per row. The row value
//! is loaded (and, for f16/int8, converted) once per block and reused for all `Q` queries, so a
//! LERF query (positive + 4 canonical negatives) costs one pass over memory.
//!
//! - `f32`: plain multiply-add.
//! - `f16`: the row is converted in blocks of [`F16_BLOCK`] values into a stack buffer with
//!   [`half::slice::HalfFloatSliceExt::convert_to_f32_slice`] (F16C on x86_64 / FP16 on aarch64,
//!   detected at run time by `half`), then the f32 kernel runs on the buffer.
//! - `int8`: `q as f32 * query` accumulated, the per-row scale applied once at the end
//!   (`dot = scale · Σ q_j x_j`).
//!
//! Accumulation order differs from a sequential sum (16 partial sums), so results differ from a
//! scalar `f64` reference by normal `f32` rounding only (≈1e-6 relative for D = 512).

use half::f16;
use half::slice::HalfFloatSliceExt;

/// Number of independent accumulators per query (one AVX-512 register, two AVX2 / NEON×4).
pub const LANES: usize = 16;
/// Largest number of queries scored in one pass.
pub const MAX_QUERIES: usize = 8;
/// f16 values converted to f32 per block (a 1 KiB stack buffer).
pub const F16_BLOCK: usize = 256;

/// Adds `Σ_j row[j] · qs[q][off + j]` into `acc[q]` lanes (and the scalar tail into `tail[q]`).
///
/// `row` is a block of one stored row, `off` its offset within the row; every `qs[q]` is a full
/// query of the row's width.
#[inline(always)]
fn accumulate_f32<const Q: usize>(
    acc: &mut [[f32; LANES]; Q],
    tail: &mut [f32; Q],
    row: &[f32],
    qs: &[&[f32]; Q],
    off: usize,
) {
    let n = row.len();
    let body = n - n % LANES;
    let mut qb: [&[f32]; Q] = [&[]; Q];
    for q in 0..Q {
        qb[q] = &qs[q][off..off + n];
    }
    for (c, r) in row[..body].chunks_exact(LANES).enumerate() {
        let base = c * LANES;
        for q in 0..Q {
            let qc = &qb[q][base..base + LANES];
            for l in 0..LANES {
                acc[q][l] += r[l] * qc[l];
            }
        }
    }
    for j in body..n {
        for q in 0..Q {
            tail[q] += row[j] * qb[q][j];
        }
    }
}

#[inline(always)]
fn reduce<const Q: usize>(acc: &[[f32; LANES]; Q], tail: &[f32; Q], scale: f32, out: &mut [f32]) {
    for q in 0..Q {
        // Pairwise lane reduction (vectorises and is slightly more accurate than a chain).
        let mut a = acc[q];
        let mut w = LANES / 2;
        while w > 0 {
            for l in 0..w {
                a[l] += a[l + w];
            }
            w /= 2;
        }
        out[q] = (a[0] + tail[q]) * scale;
    }
}

/// Dot products of one `f32` row with `Q` queries: `out[q] = Σ_j row[j] · qs[q][j]`.
///
/// Shapes: `row.len() == qs[q].len() == D`, `out.len() >= Q`.
#[inline(always)]
pub fn dots_f32<const Q: usize>(row: &[f32], qs: &[&[f32]; Q], out: &mut [f32]) {
    let mut acc = [[0.0f32; LANES]; Q];
    let mut tail = [0.0f32; Q];
    accumulate_f32(&mut acc, &mut tail, row, qs, 0);
    reduce(&acc, &tail, 1.0, out);
}

/// Dot products of one IEEE-half row with `Q` f32 queries (row converted in blocks of
/// [`F16_BLOCK`] into `buf`, a caller-owned scratch buffer).
///
/// Shapes: `row.len() == qs[q].len() == D`, `out.len() >= Q`.
#[inline(always)]
pub fn dots_f16<const Q: usize>(
    row: &[f16],
    qs: &[&[f32]; Q],
    buf: &mut [f32; F16_BLOCK],
    out: &mut [f32],
) {
    let mut acc = [[0.0f32; LANES]; Q];
    let mut tail = [0.0f32; Q];
    let mut off = 0;
    for block in row.chunks(F16_BLOCK) {
        let b = &mut buf[..block.len()];
        block.convert_to_f32_slice(b);
        accumulate_f32(&mut acc, &mut tail, b, qs, off);
        off += block.len();
    }
    reduce(&acc, &tail, 1.0, out);
}

/// Dot products of one symmetric-int8 row (value `q_j · scale`) with `Q` f32 queries:
/// `out[q] = scale · Σ_j q_j · qs[q][j]`.
///
/// Shapes: `row.len() == qs[q].len() == D`, `out.len() >= Q`.
#[inline(always)]
pub fn dots_i8<const Q: usize>(row: &[i8], scale: f32, qs: &[&[f32]; Q], out: &mut [f32]) {
    let mut acc = [[0.0f32; LANES]; Q];
    let mut tail = [0.0f32; Q];
    let n = row.len();
    let body = n - n % LANES;
    for (c, r) in row[..body].chunks_exact(LANES).enumerate() {
        let base = c * LANES;
        let mut rf = [0.0f32; LANES];
        for l in 0..LANES {
            rf[l] = r[l] as f32;
        }
        for q in 0..Q {
            let qc = &qs[q][base..base + LANES];
            for l in 0..LANES {
                acc[q][l] += rf[l] * qc[l];
            }
        }
    }
    for j in body..n {
        for q in 0..Q {
            tail[q] += row[j] as f32 * qs[q][j];
        }
    }
    reduce(&acc, &tail, scale, out);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lcg(seed: &mut u64) -> f32 {
        *seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((*seed >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
    }

    fn ref_dot(a: impl Iterator<Item = f64>, b: &[f32]) -> f64 {
        a.zip(b).map(|(x, &y)| x * y as f64).sum()
    }

    #[test]
    fn kernels_match_f64_reference_for_odd_widths() {
        let mut s = 7u64;
        // Widths around the lane and block boundaries.
        for d in [1usize, 3, 15, 16, 17, 31, 64, 255, 256, 257, 600] {
            let row: Vec<f32> = (0..d).map(|_| lcg(&mut s)).collect();
            let qv: Vec<Vec<f32>> = (0..3)
                .map(|_| (0..d).map(|_| lcg(&mut s)).collect())
                .collect();
            let qs: [&[f32]; 3] = [&qv[0], &qv[1], &qv[2]];
            let mut out = [0.0f32; 3];
            dots_f32::<3>(&row, &qs, &mut out);
            for q in 0..3 {
                let r = ref_dot(row.iter().map(|&x| x as f64), &qv[q]);
                assert!(
                    (out[q] as f64 - r).abs() < 1e-5 * d as f64,
                    "f32 d={d} q={q}"
                );
            }
            let h: Vec<f16> = row.iter().map(|&x| f16::from_f32(x)).collect();
            let mut buf = [0.0f32; F16_BLOCK];
            dots_f16::<3>(&h, &qs, &mut buf, &mut out);
            for q in 0..3 {
                let r = ref_dot(h.iter().map(|x| x.to_f32() as f64), &qv[q]);
                assert!(
                    (out[q] as f64 - r).abs() < 1e-5 * d as f64,
                    "f16 d={d} q={q}"
                );
            }
            let i: Vec<i8> = row.iter().map(|&x| (x * 127.0).round() as i8).collect();
            let scale = 0.01f32;
            dots_i8::<3>(&i, scale, &qs, &mut out);
            for q in 0..3 {
                let r = scale as f64 * ref_dot(i.iter().map(|&x| x as f64), &qv[q]);
                assert!(
                    (out[q] as f64 - r).abs() < 1e-5 * d as f64,
                    "i8 d={d} q={q}"
                );
            }
        }
    }
}
