use half::f16;
use slag_common::shards::StoredVectors;

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
fn every_simd_level_gives_the_same_single_dot() {
    let mut s = 5u64;
    for d in [0usize, 1, 7, 8, 15, 16, 17, 33, 64, 100, 512, 515] {
        let a: Vec<f32> = (0..d).map(|_| lcg(&mut s)).collect();
        let b: Vec<f32> = (0..d).map(|_| lcg(&mut s)).collect();
        let want = ref_dot(a.iter().map(|&x| x as f64), &b);
        for level in SimdLevel::available_levels() {
            let got = dot_f32_at(level, &a, &b) as f64;
            assert!(
                (got - want).abs() <= 1e-5 * (1.0 + d as f64),
                "{level:?} d={d}: {got} vs {want}"
            );
        }
        assert_eq!(dot_f32(&a, &b), dot_f32_at(simd_level(), &a, &b));
    }
}

#[test]
fn every_simd_level_gives_the_same_dots() {
    use crate::scan::VectorStore;
    use slag_common::shards::Dtype;
    let d = 45;
    let mut s = 3u64;
    let qv: Vec<Vec<f32>> = (0..5)
        .map(|_| (0..d).map(|_| lcg(&mut s)).collect())
        .collect();
    let qs: [&[f32]; 5] = [&qv[0], &qv[1], &qv[2], &qv[3], &qv[4]];
    for dtype in [Dtype::F32, Dtype::F16, Dtype::I8] {
        let store = VectorStore::synthetic(300, d, dtype, 4, 2).expect("store");
        let keep = |i: usize| i % 7 != 3;
        let want = (10..300).filter(|&i| keep(i)).count();
        for level in SimdLevel::available_levels() {
            let mut out = vec![[f32::NAN; 5]; 290];
            let qq = Queries::new(qs);
            scan_chunk_at::<5>(
                level,
                store.vectors(),
                RowSpan {
                    d,
                    start: 10,
                    end: 300,
                    keep: Some(&keep),
                },
                &qq,
                &mut out,
            );
            let got: Vec<(usize, [f32; 5])> =
                (10..300).zip(out).filter(|(_, o)| !o[0].is_nan()).collect();
            assert_eq!(got.len(), want, "{level:?}");
            let mut prev = 0;
            for (i, a) in &got {
                assert!(*i >= prev && keep(*i), "{level:?}: rows out of order");
                prev = *i;
                let row = store.row_f32(*i).expect("row");
                for q in 0..5 {
                    let r: f64 = row
                        .iter()
                        .zip(&qv[q])
                        .map(|(&x, &y)| x as f64 * y as f64)
                        .sum();
                    assert!((a[q] as f64 - r).abs() < 1e-5, "{dtype:?} {level:?}");
                }
            }
        }
    }
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
        dots_f32::<3, false>(&row, &qs, &mut out);
        for q in 0..3 {
            let r = ref_dot(row.iter().map(|&x| x as f64), &qv[q]);
            assert!(
                (out[q] as f64 - r).abs() < 1e-5 * d as f64,
                "f32 d={d} q={q}"
            );
        }
        let h: Vec<f16> = row.iter().map(|&x| f16::from_f32(x)).collect();
        let mut buf = [0.0f32; BLOCK];
        {
            dots_f16::<3, false>(&h, &qs, &mut buf, &mut out, convert_f16_portable);
            for q in 0..3 {
                let r = ref_dot(h.iter().map(|x| x.to_f32() as f64), &qv[q]);
                assert!(
                    (out[q] as f64 - r).abs() < 1e-5 * d as f64,
                    "f16 d={d} q={q}"
                );
            }
        }
        let i: Vec<i8> = row.iter().map(|&x| (x * 127.0).round() as i8).collect();
        let scale = 0.01f32;
        dots_i8::<3, false>(&i, scale, &qs, &mut buf, &mut out);
        for q in 0..3 {
            let r = scale as f64 * ref_dot(i.iter().map(|&x| x as f64), &qv[q]);
            assert!(
                (out[q] as f64 - r).abs() < 1e-5 * d as f64,
                "i8 d={d} q={q}"
            );
        }
    }
}

/// Scores `rows` (`[n * d]` as f64 values of the stored type) against `qs` in f64.
/// Row `i` (width `d`) of `rows`, dequantised to f64.
fn row_f64(rows: &StoredVectors, d: usize, i: usize) -> Vec<f64> {
    match rows {
        StoredVectors::F32(v) => v[i * d..][..d].iter().map(|&x| x as f64).collect(),
        StoredVectors::F16(v) => v[i * d..][..d].iter().map(|x| x.to_f32() as f64).collect(),
        StoredVectors::I8 { q, scales } => q[i * d..][..d]
            .iter()
            .map(|&x| x as f64 * scales[i] as f64)
            .collect(),
    }
}

/// f32 rounding bound of the dot of `row` with `q`: `1e-5 · Σ|x_j·q_j| + 1e-6 · Σ|x_j| · max|q|`.
fn f32_dot_tolerance(row: &[f64], q: &[f32]) -> f64 {
    let abs: f64 = row.iter().zip(q).map(|(x, &y)| (x * y as f64).abs()).sum();
    let l1: f64 = row.iter().map(|x| x.abs()).sum();
    let m = q.iter().fold(0.0f64, |a, &y| a.max((y as f64).abs()));
    1e-5 * abs + 1e-6 * l1 * m
}

/// The dots of every row of `rows` (width `d`) with `queries`, computed at `level`: `[N][Q]`.
fn dots_at<const Q: usize>(
    level: SimdLevel,
    rows: &StoredVectors,
    d: usize,
    queries: &Queries<'_, Q>,
) -> Vec<[f32; Q]> {
    let n = rows.values() / d;
    let mut out = vec![[f32::NAN; Q]; n];
    let span = RowSpan {
        d,
        start: 0,
        end: n,
        keep: None,
    };
    scan_chunk_at::<Q>(level, rows, span, queries, &mut out);
    out
}

fn reference(rows: &StoredVectors, d: usize, qs: &[Vec<f32>]) -> Vec<Vec<f64>> {
    let n = rows.values() / d.max(1);
    (0..n)
        .map(|i| {
            let row = row_f64(rows, d, i);
            qs.iter().map(|q| ref_dot(row.iter().copied(), q)).collect()
        })
        .collect()
}

/// Every available level against the f64 reference: `|got − ref| ≤ 1e-5 · Σ|x_j·q_j| +
/// 1e-6 · Σ|x_j| · max|q|` (f32 rounding of D products; the SDOT split's 6e-8 · max|q|).
fn check_levels<const Q: usize>(
    rows: &StoredVectors,
    d: usize,
    qv: &[Vec<f32>],
) -> Result<(), proptest::test_runner::TestCaseError> {
    let n = rows.values() / d;
    let qs: [&[f32]; Q] = std::array::from_fn(|q| qv[q].as_slice());
    let want = reference(rows, d, qv);
    for level in SimdLevel::available_levels() {
        let out = dots_at(level, rows, d, &Queries::new(qs));
        let got: Vec<(usize, [f32; Q])> = out.into_iter().enumerate().collect();
        proptest::prop_assert_eq!(got.len(), n);
        for (i, dots) in got {
            let row = row_f64(rows, d, i);
            for q in 0..Q {
                let tol = f32_dot_tolerance(&row, &qv[q]) + 1e-30;
                let err = (dots[q] as f64 - want[i][q]).abs();
                proptest::prop_assert!(
                    err <= tol,
                    "{:?} {:?} d={} q={} row={}: {} vs {} (tol {})",
                    level,
                    rows.dtype(),
                    d,
                    q,
                    i,
                    dots[q],
                    want[i][q],
                    tol
                );
            }
        }
    }
    Ok(())
}

proptest::proptest! {
    #![proptest_config(proptest::prelude::ProptestConfig::with_cases(48))]

    /// Every SIMD kernel equals the scalar f64 reference for any width (tails included), any
    /// query count, every stored type.
    #[test]
    fn simd_kernels_match_the_scalar_reference(
        d in 1usize..300,
        n in 1usize..6,
        nq in 0usize..5,
        seed in proptest::prelude::any::<u64>(),
        mag in proptest::sample::select(vec![1e-3f32, 1.0, 300.0]),
    ) {
        let mut s = seed | 1;
        let vals: Vec<f32> = (0..n * d).map(|_| lcg(&mut s) * mag).collect();
        let qv: Vec<Vec<f32>> = (0..8).map(|_| (0..d).map(|_| lcg(&mut s)).collect()).collect();
        let f16s = vals.iter().map(|&x| f16::from_f32(x)).collect();
        let mut q = Vec::new();
        let scales: Vec<f32> = vals
            .chunks_exact(d)
            .map(|r| {
                let mut b = Vec::new();
                let sc = slag_common::shards::format::quantize_i8(r, &mut b);
                q.extend(b.iter().map(|&x| x as i8));
                sc
            })
            .collect();
        for rows in [StoredVectors::F32(vals.clone()), StoredVectors::F16(f16s), StoredVectors::I8 { q, scales }] {
            match [1, 2, 3, 5, 8][nq] {
                1 => check_levels::<1>(&rows, d, &qv)?,
                2 => check_levels::<2>(&rows, d, &qv)?,
                3 => check_levels::<3>(&rows, d, &qv)?,
                5 => check_levels::<5>(&rows, d, &qv)?,
                _ => check_levels::<8>(&rows, d, &qv)?,
            }
        }
    }
}

/// Dots of every available level vs [`SimdLevel::Baseline`] (the portable scalar-order
/// fallback): equal within f32 rounding when finite, the same NaN / ±inf otherwise.
fn same_as_baseline<const Q: usize>(rows: &StoredVectors, d: usize, qv: &[Vec<f32>], what: &str) {
    let n = rows.values() / d;
    let qs: [&[f32]; Q] = std::array::from_fn(|q| qv[q].as_slice());
    let queries = Queries::new(qs);
    let base = dots_at(SimdLevel::Baseline, rows, d, &queries);
    for level in SimdLevel::available_levels() {
        let got = dots_at(level, rows, d, &queries);
        for i in 0..n {
            for q in 0..Q {
                let (a, b) = (got[i][q], base[i][q]);
                let ok = if a.is_finite() && b.is_finite() {
                    let row = row_f64(rows, d, i);
                    ((a - b) as f64).abs() <= 2.0 * f32_dot_tolerance(&row, &qv[q]) + 1e-30
                } else {
                    (a.is_nan() && b.is_nan()) || a == b
                };
                assert!(
                    ok,
                    "{what} {level:?} d={d} row {i} query {q}: {a} vs baseline {b}"
                );
            }
        }
    }
}

#[test]
fn simd_levels_equal_the_scalar_fallback_on_edge_case_rows() {
    let mut s = 5u64;
    // Widths around every lane count (8, 16, 64 bytes) and the f16 block.
    for d in [
        1usize, 7, 8, 9, 15, 16, 17, 63, 64, 65, 127, 255, 256, 257, 511, 512, 513,
    ] {
        let qv: Vec<Vec<f32>> = (0..2)
            .map(|_| (0..d).map(|_| lcg(&mut s)).collect())
            .collect();
        let zero_q = vec![vec![0.0f32; d], qv[0].clone()];
        // f16: zeros, subnormals (smallest and largest), the largest finite, ±inf, normal.
        let specials = [
            f16::ZERO,
            f16::NEG_ZERO,
            f16::from_bits(0x0001),
            f16::from_bits(0x03ff),
            f16::from_bits(0x8001),
            f16::MAX,
            f16::MIN,
            f16::from_f32(0.3),
        ];
        let mut h = Vec::new();
        for r in 0..6 {
            for j in 0..d {
                h.push(match r {
                    0 => f16::ZERO,
                    1 => specials[j % specials.len()],
                    2 => f16::from_bits(0x0001 + (j as u16 % 0x3ff)), // all subnormal
                    3 if j == d / 2 => f16::INFINITY,
                    4 if j == 0 => f16::NEG_INFINITY,
                    _ => f16::from_f32(lcg(&mut s)),
                });
            }
        }
        let h = StoredVectors::F16(h);
        same_as_baseline::<1>(&h, d, &qv, "f16");
        same_as_baseline::<2>(&h, d, &qv, "f16");
        same_as_baseline::<2>(&h, d, &zero_q, "f16 zero query");
        // int8: zeros, the extremes ±127 and -128, alternating signs, random.
        let mut q8 = Vec::new();
        for r in 0..5 {
            for j in 0..d {
                q8.push(match r {
                    0 => 0i8,
                    1 => 127,
                    2 => -128,
                    3 => {
                        if j % 2 == 0 {
                            127
                        } else {
                            -127
                        }
                    }
                    _ => (lcg(&mut s) * 127.0) as i8,
                });
            }
        }
        let i8s = StoredVectors::I8 {
            q: q8,
            scales: vec![1.0, 0.5, 1e-3, 7.0, 0.01],
        };
        same_as_baseline::<1>(&i8s, d, &qv, "int8");
        same_as_baseline::<2>(&i8s, d, &qv, "int8");
        same_as_baseline::<2>(&i8s, d, &zero_q, "int8 zero query");
        // A query with a huge dynamic range (the int8 split's steps follow its largest value).
        let mut wide = qv[1].clone();
        wide[0] = 1e3;
        same_as_baseline::<1>(&i8s, d, &[wide], "int8 wide query");
        let f = StoredVectors::F32((0..4 * d).map(|_| lcg(&mut s)).collect());
        same_as_baseline::<1>(&f, d, &qv, "f32");
        same_as_baseline::<2>(&f, d, &qv, "f32");
    }
}

#[test]
fn query_split_reconstructs_within_its_bound() {
    let mut s = 11u64;
    let d = 77;
    let qv: Vec<Vec<f32>> = (0..2)
        .map(|_| (0..d).map(|_| lcg(&mut s)).collect())
        .collect();
    let zero = vec![0.0f32; d];
    let qs: [&[f32]; 3] = [&qv[0], &qv[1], &zero];
    let (terms, steps) = super::queries::split_queries(&qs, d);
    for k in 0..3 {
        let m = qs[k].iter().fold(0.0f64, |a, &y| a.max((y as f64).abs()));
        for j in 0..d {
            let r: f64 = (0..3)
                .map(|t| steps[k][t] as f64 * terms[(k * 3 + t) * d + j] as f64)
                .sum();
            assert!(
                (r - qs[k][j] as f64).abs() <= m * 7e-8 + 1e-12,
                "query {k} component {j}: {r} vs {}",
                qs[k][j]
            );
        }
    }
    assert_eq!(steps[2], [0.0; 3]);
}
