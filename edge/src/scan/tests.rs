//! Scan tests against an independent f64 reference on the dequantised rows.

use super::*;
use proptest::prelude::*;
use slag_common::shards::{Dtype, ShardInput, StoredVectors, decode_shard_stored, encode_shard};

const DTYPES: [Dtype; 3] = [Dtype::F32, Dtype::F16, Dtype::I8];

fn lcg(s: &mut u64) -> f32 {
    *s = s
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    ((*s >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
}

fn unit(v: &mut [f32]) {
    let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
    if n > 0.0 {
        v.iter_mut().for_each(|x| *x /= n);
    }
}

/// Random unit rows pushed through the real shard path (encode → decode_shard_stored →
/// push_shard), split over several shards.
fn store_via_shards(n: usize, d: usize, dtype: Dtype, seed: u64) -> VectorStore {
    store_via_shards_reserved(n, d, dtype, seed, None)
}

/// [`store_via_shards`], after `VectorStore::reserve(rows)` when `reserve` is given; checks that
/// the reserved buffer is filled in place (no reallocation) when it is large enough.
fn store_via_shards_reserved(
    n: usize,
    d: usize,
    dtype: Dtype,
    seed: u64,
    reserve: Option<usize>,
) -> VectorStore {
    let mut s = seed;
    let mut vectors: Vec<f32> = (0..n * d).map(|_| lcg(&mut s)).collect();
    for row in vectors.chunks_exact_mut(d) {
        unit(row);
    }
    let means: Vec<[f32; 3]> = (0..n)
        .map(|_| [lcg(&mut s) * 10.0, lcg(&mut s) * 10.0, lcg(&mut s)])
        .collect();
    let ids: Vec<u32> = (0..n as u32).map(|i| 3 * i + 1).collect();
    let mut store = VectorStore::new(d, dtype).expect("store");
    let buffer = |st: &VectorStore| match st.vectors() {
        StoredVectors::F32(v) => (v.as_ptr() as usize, v.capacity() * 4),
        StoredVectors::F16(v) => (v.as_ptr() as usize, v.capacity() * 2),
        StoredVectors::I8 { q, .. } => (q.as_ptr() as usize, q.capacity()),
    };
    if let Some(rows) = reserve {
        store.reserve(rows).expect("reserve");
    }
    let reserved = buffer(&store);
    let per = n.div_ceil(3).max(1);
    let mut start = 0;
    let mut tile = 0;
    while start < n {
        let end = (start + per).min(n);
        let bytes = encode_shard(&ShardInput {
            scene_id: "test",
            model: "test-model",
            tile_id: tile,
            dim: d,
            dtype,
            ids: &ids[start..end],
            means: &means[start..end],
            vectors: &vectors[start * d..end * d],
            ..Default::default()
        })
        .expect("encode");
        store
            .push_shard(decode_shard_stored(&bytes).expect("decode"))
            .expect("push");
        start = end;
        tile += 1;
    }
    assert_eq!(store.len(), n);
    if reserve.is_some_and(|rows| rows >= n) {
        assert_eq!(
            buffer(&store),
            reserved,
            "rows landed in the reserved buffer, in place"
        );
    }
    store
}

fn queries(q: usize, d: usize, seed: u64) -> Vec<Vec<f32>> {
    let mut s = seed ^ 0xABCD;
    (0..q)
        .map(|_| {
            let mut v: Vec<f32> = (0..d).map(|_| lcg(&mut s)).collect();
            unit(&mut v);
            v
        })
        .collect()
}

/// A combiner for Q > 1 tests: positive minus the best negative, halved.
fn contrast(d: &[f32]) -> f32 {
    let neg = d[1..].iter().copied().fold(f32::NEG_INFINITY, f32::max);
    d[0] - 0.5 * neg
}

/// f64 scores of every row (dequantised values), combined with `combine` on f32-rounded dots.
fn reference_scores(
    store: &VectorStore,
    qs: &[Vec<f32>],
    combine: Option<fn(&[f32]) -> f32>,
) -> Vec<f64> {
    (0..store.len())
        .map(|i| {
            let row = store.row_f32(i).expect("row");
            let dots: Vec<f64> = qs
                .iter()
                .map(|q| row.iter().zip(q).map(|(&a, &b)| a as f64 * b as f64).sum())
                .collect();
            match combine {
                None => dots[0],
                Some(f) => {
                    let d32: Vec<f32> = dots.iter().map(|&x| x as f32).collect();
                    f(&d32) as f64
                }
            }
        })
        .collect()
}

struct Mode {
    top_k: Option<usize>,
    threshold: Option<f32>,
    bbox: Option<([f32; 3], [f32; 3])>,
}

/// Checks `got` against the reference: every score within `tol`, order by (score desc, row asc),
/// and the selected set equal to the reference's up to rows whose reference score is within
/// `2·tol` of the selection boundary (near-ties that rounding may legitimately swap).
fn check(store: &VectorStore, got: &[Hit], reference: &[f64], mode: &Mode, tol: f64) {
    let means = store.means();
    let eligible: Vec<usize> = (0..store.len())
        .filter(|&i| match mode.bbox {
            None => true,
            Some((lo, hi)) => (0..3).all(|a| means[i][a] >= lo[a] && means[i][a] <= hi[a]),
        })
        .filter(|&i| {
            mode.threshold
                .is_none_or(|t| reference[i] >= t as f64 - tol)
        })
        .collect();
    for w in got.windows(2) {
        assert!(
            rank_cmp_ok(&w[0], &w[1]),
            "not sorted: {:?} before {:?}",
            w[0],
            w[1]
        );
    }
    for h in got {
        assert!(
            (h.score as f64 - reference[h.row]).abs() <= tol,
            "row {} score {} reference {}",
            h.row,
            h.score,
            reference[h.row]
        );
        assert!(eligible.contains(&h.row), "row {} not eligible", h.row);
        if let Some(t) = mode.threshold {
            assert!(h.score >= t);
        }
    }
    let mut sorted = eligible.clone();
    sorted.sort_by(|&a, &b| reference[b].total_cmp(&reference[a]).then(a.cmp(&b)));
    // Rows surely selected: above threshold + tol and (for top-k) clearly inside the top k.
    let sure_thr = |i: usize| {
        mode.threshold
            .is_none_or(|t| reference[i] >= t as f64 + tol)
    };
    let want: Vec<usize> = match mode.top_k {
        Some(k) => {
            let boundary = sorted.get(k).map(|&i| reference[i]);
            sorted
                .iter()
                .take(k)
                .copied()
                .filter(|&i| sure_thr(i) && boundary.is_none_or(|b| reference[i] > b + 2.0 * tol))
                .collect()
        }
        None => sorted.iter().copied().filter(|&i| sure_thr(i)).collect(),
    };
    for i in &want {
        assert!(got.iter().any(|h| h.row == *i), "row {i} missing");
    }
    if let Some(k) = mode.top_k {
        let avail = sorted.iter().filter(|&&i| sure_thr(i)).count();
        assert!(got.len() <= k);
        assert!(
            got.len() >= k.min(avail),
            "{} hits, {} available",
            got.len(),
            avail
        );
    }
}

fn rank_cmp_ok(a: &Hit, b: &Hit) -> bool {
    a.score > b.score || (a.score == b.score && a.row < b.row)
}

#[test]
fn every_dtype_and_query_count_matches_the_f64_reference() {
    // 4500 rows: more than two rayon tasks (CHUNK_ROWS = 2048), so merging is exercised.
    let n = 4500;
    for (d, seed) in [(19usize, 1u64), (40, 2)] {
        for dtype in DTYPES {
            let store = store_via_shards(n, d, dtype, seed);
            // Values are exact for f32 rows; f16/int8 are compared on their dequantised values.
            let tol = if dtype == Dtype::F32 { 1e-5 } else { 1e-4 };
            for q in [1usize, 5] {
                let qv = queries(q, d, seed + q as u64);
                let qs: Vec<&[f32]> = qv.iter().map(|v| v.as_slice()).collect();
                let combine: Option<fn(&[f32]) -> f32> = (q > 1).then_some(contrast as _);
                let reference = reference_scores(&store, &qv, combine);
                let modes = [
                    Mode {
                        top_k: Some(37),
                        threshold: None,
                        bbox: None,
                    },
                    Mode {
                        top_k: None,
                        threshold: Some(0.2),
                        bbox: None,
                    },
                    Mode {
                        top_k: Some(5),
                        threshold: Some(0.1),
                        bbox: None,
                    },
                    Mode {
                        top_k: Some(20),
                        threshold: None,
                        bbox: Some(([-5.0, -2.0, -1.0], [3.0, 8.0, 0.5])),
                    },
                    Mode {
                        top_k: None,
                        threshold: Some(0.0),
                        bbox: Some(([0.0, 0.0, -1.0], [10.0, 10.0, 1.0])),
                    },
                ];
                for mode in &modes {
                    let combine_dyn = combine.map(|f| f as fn(&[f32]) -> f32);
                    let req = ScanRequest {
                        queries: &qs,
                        top_k: mode.top_k,
                        threshold: mode.threshold,
                        bbox: mode.bbox,
                        combine: combine_dyn.as_ref().map(|f| f as Combiner<'_>),
                    };
                    let got = scan(&store, &req).expect("scan");
                    if mode.top_k == Some(37) || mode.top_k == Some(20) {
                        assert_eq!(got.len(), mode.top_k.unwrap_or(0), "{dtype:?} q={q}");
                    }
                    check(&store, &got, &reference, mode, tol);
                }
            }
        }
    }
}

#[test]
fn exact_ties_break_by_row_across_tasks() {
    // The same vector stored at many rows spread over several tasks: identical scores, so the
    // top-k must be the lowest rows among them.
    let d = 24;
    let n = 6000;
    for dtype in DTYPES {
        let mut s = 5u64;
        let mut base: Vec<f32> = (0..d).map(|_| lcg(&mut s)).collect();
        unit(&mut base);
        let mut vectors = Vec::with_capacity(n * d);
        for i in 0..n {
            if i % 700 == 3 {
                vectors.extend_from_slice(&base);
            } else {
                let mut v: Vec<f32> = (0..d).map(|_| lcg(&mut s)).collect();
                unit(&mut v);
                // Keep other rows clearly below the base row's score.
                let dot: f32 = v.iter().zip(&base).map(|(a, b)| a * b).sum();
                v.iter_mut()
                    .zip(&base)
                    .for_each(|(x, b)| *x -= (dot + 0.5).max(0.0) * b);
                vectors.extend_from_slice(&v);
            }
        }
        let ids: Vec<u32> = (0..n as u32).collect();
        let means = vec![[0.0f32; 3]; n];
        let mut store = VectorStore::new(d, dtype).expect("store");
        store.push_f32_rows(&ids, &means, &vectors).expect("push");
        let qs: [&[f32]; 1] = [&base];
        let got = scan(&store, &ScanRequest::top_k(&qs, 4)).expect("scan");
        let rows: Vec<usize> = got.iter().map(|h| h.row).collect();
        assert_eq!(rows, vec![3, 703, 1403, 2103], "{dtype:?}");
        assert!(got.windows(2).all(|w| w[0].score == w[1].score));
    }
}

#[test]
fn results_do_not_depend_on_thread_count() {
    let store = store_via_shards(7000, 33, Dtype::F16, 9);
    let qv = queries(5, 33, 4);
    let qs: Vec<&[f32]> = qv.iter().map(|v| v.as_slice()).collect();
    let req = ScanRequest {
        queries: &qs,
        top_k: Some(100),
        threshold: None,
        bbox: None,
        combine: Some(&lerf_relevancy),
    };
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("pool")
            .install(|| scan(&store, &req).expect("scan"))
    };
    let one = run(1);
    assert_eq!(one.len(), 100);
    assert_eq!(one, run(2));
    assert_eq!(one, run(5));
}

#[test]
fn edge_cases_are_errors_or_documented_results() {
    let d = 8;
    let store = store_via_shards(50, d, Dtype::F32, 3);
    let qv = queries(1, d, 1);
    let qs: [&[f32]; 1] = [&qv[0]];
    let reference = reference_scores(&store, &qv, None);
    // k > N: every row, sorted.
    let all = scan(&store, &ScanRequest::top_k(&qs, 1000)).expect("scan");
    assert_eq!(all.len(), 50);
    let mut order: Vec<usize> = (0..50).collect();
    order.sort_by(|&a, &b| reference[b].total_cmp(&reference[a]));
    assert_eq!(all.iter().map(|h| h.row).collect::<Vec<_>>(), order);
    // k = 0: nothing.
    assert!(
        scan(&store, &ScanRequest::top_k(&qs, 0))
            .expect("scan")
            .is_empty()
    );
    // Empty store.
    let empty = VectorStore::new(d, Dtype::I8).expect("store");
    assert!(
        scan(&empty, &ScanRequest::top_k(&qs, 5))
            .expect("scan")
            .is_empty()
    );
    // Threshold above every score, +inf, -inf.
    assert!(
        scan(&store, &ScanRequest::threshold(&qs, 1.01))
            .expect("scan")
            .is_empty()
    );
    assert!(
        scan(&store, &ScanRequest::threshold(&qs, f32::INFINITY))
            .expect("scan")
            .is_empty()
    );
    assert_eq!(
        scan(&store, &ScanRequest::threshold(&qs, f32::NEG_INFINITY))
            .expect("scan")
            .len(),
        50
    );
    // NaN threshold: typed error.
    assert!(matches!(
        scan(&store, &ScanRequest::threshold(&qs, f32::NAN)),
        Err(Error::Param {
            name: "threshold",
            ..
        })
    ));
    // Zero query: every score is 0, so the top-k are the lowest rows.
    let zero = vec![0.0f32; d];
    let zq: [&[f32]; 1] = [&zero];
    let z = scan(&store, &ScanRequest::top_k(&zq, 3)).expect("scan");
    assert_eq!(z.iter().map(|h| h.row).collect::<Vec<_>>(), vec![0, 1, 2]);
    assert!(z.iter().all(|h| h.score == 0.0));
    // Wrong width, non-finite query, bad query counts, missing combiner, no selection, bad box.
    let short = vec![0.1f32; d - 1];
    let sq: [&[f32]; 1] = [&short];
    let Err(Error::Mismatch { message: msg, .. }) = scan(&store, &ScanRequest::top_k(&sq, 3))
    else {
        panic!("dim mismatch must be an error");
    };
    assert!(
        msg.contains("7 components") && msg.contains("dim 8"),
        "{msg}"
    );
    let mut nan = qv[0].clone();
    nan[2] = f32::NAN;
    let nq: [&[f32]; 1] = [&nan];
    assert!(scan(&store, &ScanRequest::top_k(&nq, 3)).is_err());
    let none: [&[f32]; 0] = [];
    assert!(scan(&store, &ScanRequest::top_k(&none, 3)).is_err());
    let nine: Vec<&[f32]> = vec![&qv[0]; 9];
    let mut req = ScanRequest::top_k(&nine, 3);
    req.combine = Some(&lerf_relevancy);
    assert!(scan(&store, &req).is_err());
    let two: Vec<&[f32]> = vec![&qv[0]; 2];
    assert!(scan(&store, &ScanRequest::top_k(&two, 3)).is_err());
    let mut req = ScanRequest::top_k(&qs, 3);
    req.top_k = None;
    assert!(scan(&store, &req).is_err());
    let mut req = ScanRequest::top_k(&qs, 3);
    req.bbox = Some(([1.0, 0.0, 0.0], [0.0, 1.0, 1.0]));
    assert!(scan(&store, &req).is_err());
    req.bbox = Some(([f32::NAN, 0.0, 0.0], [1.0, 1.0, 1.0]));
    assert!(scan(&store, &req).is_err());
}

#[test]
fn push_shard_rejects_mismatches_and_leaves_the_store_unchanged() {
    let mut store = store_via_shards(10, 8, Dtype::F16, 1);
    let other_dim = store_via_shards(4, 9, Dtype::F16, 1);
    let other_type = store_via_shards(4, 8, Dtype::I8, 1);
    let mk = |s: &VectorStore, dtype| {
        let n = s.len();
        let d = s.dim();
        let v: Vec<f32> = (0..n).flat_map(|i| s.row_f32(i).expect("row")).collect();
        decode_shard_stored(
            &encode_shard(&ShardInput {
                scene_id: "t",
                model: "m",
                tile_id: 42,
                dim: d,
                dtype,
                ids: s.ids(),
                means: s.means(),
                vectors: &v,
                ..Default::default()
            })
            .expect("encode"),
        )
        .expect("decode")
    };
    let Err(Error::Mismatch { message: msg, .. }) = store.push_shard(mk(&other_dim, Dtype::F16))
    else {
        panic!("dim mismatch must be an error");
    };
    assert!(msg.contains("dim 9") && msg.contains("dim 8"), "{msg}");
    let Err(Error::Mismatch { message: msg, .. }) = store.push_shard(mk(&other_type, Dtype::I8))
    else {
        panic!("dtype mismatch must be an error");
    };
    assert!(msg.contains("int8") && msg.contains("f16"), "{msg}");
    let mut broken = mk(&other_type, Dtype::F16);
    broken.means.pop();
    assert!(store.push_shard(broken).is_err());
    assert_eq!(store.len(), 10);
    assert_eq!(store.vector_bytes(), 10 * 8 * 2);
    store.push_shard(mk(&other_type, Dtype::F16)).expect("push");
    assert_eq!(store.len(), 14);
    assert_eq!(&store.ids()[10..], other_type.ids());
    assert!(VectorStore::new(0, Dtype::F32).is_err());
    assert!(store.row_f32(14).is_none());
}

#[test]
fn memory_accounting_per_dtype() {
    for (dtype, per) in [
        (Dtype::F32, 2048 + 16),
        (Dtype::F16, 1024 + 16),
        (Dtype::I8, 516 + 16),
    ] {
        let s = VectorStore::synthetic(1000, 512, dtype, 4, 1).expect("store");
        assert_eq!(s.bytes_per_gaussian(), per);
        assert_eq!(s.memory_bytes(), 1000 * per);
        assert_eq!(s.vector_bytes(), 1000 * (per - 16));
        let held = match s.vectors() {
            StoredVectors::F32(v) => v.len() * 4,
            StoredVectors::F16(v) => v.len() * 2,
            StoredVectors::I8 { q, scales } => q.len() + 4 * scales.len(),
        };
        assert_eq!(held, s.vector_bytes());
    }
}

#[test]
fn synthetic_store_is_deterministic_unit_and_clustered() {
    let a = VectorStore::synthetic(3000, 64, Dtype::F32, 5, 7).expect("store");
    let b = rayon::ThreadPoolBuilder::new()
        .num_threads(3)
        .build()
        .expect("pool")
        .install(|| VectorStore::synthetic(3000, 64, Dtype::F32, 5, 7).expect("store"));
    assert_eq!(a.vectors(), b.vectors());
    assert_eq!(a.means(), b.means());
    let h = VectorStore::synthetic(3000, 64, Dtype::F16, 5, 7).expect("store");
    let q = VectorStore::synthetic(3000, 64, Dtype::I8, 5, 7).expect("store");
    let mut close_pairs = 0;
    for i in 0..3000 {
        let r = a.row_f32(i).expect("row");
        let n: f32 = r.iter().map(|x| x * x).sum();
        assert!((n - 1.0).abs() < 1e-4);
        let rh = h.row_f32(i).expect("row");
        let rq = q.row_f32(i).expect("row");
        for j in 0..64 {
            assert!((r[j] - rh[j]).abs() < 1e-3);
            assert!((r[j] - rq[j]).abs() < 0.01);
        }
        // Clustered: consecutive rows share a cluster 1 time in 5, with cosine ≈ 0.6.
        let r2 = a.row_f32((i + 1) % 3000).expect("row");
        if r.iter().zip(&r2).map(|(x, y)| x * y).sum::<f32>() > 0.4 {
            close_pairs += 1;
        }
    }
    assert!((300..1000).contains(&close_pairs), "{close_pairs}");
}

#[test]
fn naive_baseline_agrees_with_scan() {
    for dtype in DTYPES {
        let store = store_via_shards(3000, 16, dtype, 8);
        let qv = queries(1, 16, 2);
        let qs: [&[f32]; 1] = [&qv[0]];
        let fast = scan(&store, &ScanRequest::top_k(&qs, 50)).expect("scan");
        let slow = naive_scan_f32(&store, &qv[0], 50).expect("naive");
        assert_eq!(fast.len(), 50);
        assert_eq!(slow.len(), 50);
        for (a, b) in fast.iter().zip(&slow) {
            assert!((a.score - b.score).abs() < 1e-5);
        }
        let reference = reference_scores(&store, &qv, None);
        let mode = Mode {
            top_k: Some(50),
            threshold: None,
            bbox: None,
        };
        check(&store, &slow, &reference, &mode, 1e-5);
    }
}

#[test]
fn lerf_relevancy_is_the_min_pairwise_softmax() {
    let dots = [0.3f32, 0.25, 0.31, 0.1, 0.2];
    let p = dots[0] as f64;
    let want = dots[1..]
        .iter()
        .map(|&n| {
            let (a, b) = ((10.0 * p).exp(), (10.0 * n as f64).exp());
            a / (a + b)
        })
        .fold(f64::INFINITY, f64::min);
    assert!((lerf_relevancy(&dots) as f64 - want).abs() < 1e-6);
    assert_eq!(lerf_relevancy(&[0.3]), 1.0);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]
    #[test]
    fn random_small_stores_match_the_reference(
        n in 0usize..80,
        d in 1usize..40,
        dt in 0usize..3,
        q in 1usize..=3,
        k in 0usize..100,
        thr in proptest::option::of(-1.0f32..1.0),
        seed in 0u64..1000,
    ) {
        let dtype = DTYPES[dt];
        let store = if n == 0 {
            VectorStore::new(d, dtype).expect("store")
        } else {
            store_via_shards(n, d, dtype, seed)
        };
        let qv = queries(q, d, seed);
        let qs: Vec<&[f32]> = qv.iter().map(|v| v.as_slice()).collect();
        let combine: Option<fn(&[f32]) -> f32> = (q > 1).then_some(contrast as _);
        let reference = reference_scores(&store, &qv, combine);
        let combine_dyn = combine.map(|f| f as fn(&[f32]) -> f32);
        let mode = Mode { top_k: Some(k), threshold: thr, bbox: None };
        let req = ScanRequest {
            queries: &qs,
            top_k: Some(k),
            threshold: thr,
            bbox: None,
            combine: combine_dyn.as_ref().map(|f| f as Combiner<'_>),
        };
        let got = scan(&store, &req).expect("scan");
        let tol = if dtype == Dtype::F32 { 1e-5 } else { 1e-4 };
        check(&store, &got, &reference, &mode, tol);
    }
}

#[test]
fn reserved_stores_fill_in_place_and_equal_unreserved_ones() {
    for dtype in [Dtype::F32, Dtype::F16, Dtype::I8] {
        let plain = store_via_shards(1000, 96, dtype, 17);
        let reserved = store_via_shards_reserved(1000, 96, dtype, 17, Some(1000));
        assert_eq!(plain.ids(), reserved.ids());
        assert_eq!(plain.means(), reserved.means());
        assert_eq!(plain.vectors(), reserved.vectors(), "{dtype:?}");
        // Exactly the rows asked for: no doubling of the served memory.
        let cap = match reserved.vectors() {
            StoredVectors::F32(v) => v.capacity(),
            StoredVectors::F16(v) => v.capacity(),
            StoredVectors::I8 { q, .. } => q.capacity(),
        };
        assert_eq!(cap, 1000 * 96, "{dtype:?}");
    }
    // Room the allocator cannot give is a typed error that says what to do, not an abort.
    let mut store = store_via_shards(10, 8, Dtype::F16, 1);
    let Err(e @ Error::Limit { .. }) = store.reserve(usize::MAX / 2) else {
        panic!("an impossible reservation must be refused");
    };
    // The library names the limit and the parameter; `slag-edge` adds the flag (its hint).
    let msg = e.to_string();
    assert!(msg.contains("radius") && !msg.contains("--"), "{msg}");
    assert_eq!(store.len(), 10);
}

/// Segment ids travel from version-3 shards into the store, row for row; rows of a shard without
/// segments read `NO_SEGMENT`, and a store of shards without segments has none.
#[test]
fn store_keeps_segment_ids_per_row() {
    let d = 2;
    let shard = |tile: u64, ids: &[u32], segments: Option<&[u32]>| {
        let means: Vec<[f32; 3]> = ids.iter().map(|&i| [i as f32, 0.0, 0.0]).collect();
        let vectors: Vec<f32> = ids.iter().flat_map(|_| [1.0, 0.0]).collect();
        let bytes = encode_shard(&ShardInput {
            scene_id: "test",
            model: "test-model",
            tile_id: tile,
            dim: d,
            dtype: Dtype::F16,
            ids,
            means: &means,
            vectors: &vectors,
            segments,
            ..Default::default()
        })
        .expect("encode");
        decode_shard_stored(&bytes).expect("decode")
    };
    let mut plain = VectorStore::new(d, Dtype::F16).expect("store");
    plain.push_shard(shard(0, &[1, 2], None)).expect("push");
    assert_eq!(plain.segments(), None);

    let mut store = VectorStore::new(d, Dtype::F16).expect("store");
    store.push_shard(shard(0, &[1, 2], None)).expect("push");
    store
        .push_shard(shard(1, &[5, 6, 7], Some(&[4, 4, 9])))
        .expect("push");
    store.push_shard(shard(2, &[8], None)).expect("push");
    store.push_shard(shard(3, &[9], Some(&[4]))).expect("push");
    let no = store::NO_SEGMENT;
    assert_eq!(store.segments(), Some(&[no, no, 4, 4, 9, no, 4][..]));
    assert_eq!(store.segments().map(<[u32]>::len), Some(store.len()));
    // A shard whose segments disagree with its rows is refused and leaves the store unchanged.
    let mut bad = shard(4, &[10, 11], Some(&[1, 2]));
    bad.segments = Some(vec![1]);
    assert!(store.push_shard(bad).is_err());
    assert_eq!(store.len(), 7);
    assert_eq!(store.segments().map(<[u32]>::len), Some(7));
}

#[test]
fn scores_equal_the_scan_row_by_row() {
    // 4500 rows (three rayon chunks), every dtype and a mixture store; one query and five with a
    // combiner.
    let mut stores: Vec<(String, VectorStore)> = DTYPES
        .iter()
        .map(|&dt| (format!("{dt:?}"), store_via_shards(4500, 24, dt, 11)))
        .collect();
    stores.push(("mixture".into(), mixture_store(4500, 24, 64, 4, 3, None)));
    for (name, store) in &stores {
        for q in [1usize, 5] {
            let qv = queries(q, 24, 40 + q as u64);
            let qs: Vec<&[f32]> = qv.iter().map(|v| v.as_slice()).collect();
            let f = contrast as fn(&[f32]) -> f32;
            let combine: Option<Combiner<'_>> = (q > 1).then_some(&f as Combiner<'_>);
            let all = scores(store, &qs, combine).expect("scores");
            assert_eq!(all.len(), store.len());
            let req = ScanRequest {
                queries: &qs,
                top_k: None,
                threshold: Some(f32::NEG_INFINITY),
                bbox: None,
                combine,
            };
            let hits = scan(store, &req).expect("scan");
            assert_eq!(hits.len(), store.len(), "{name} q={q}");
            for h in hits {
                assert_eq!(
                    all[h.row].to_bits(),
                    h.score.to_bits(),
                    "{name} q={q} row {}",
                    h.row
                );
            }
        }
        // Five queries without a combiner: refused as by the scan.
        let qv = queries(5, 24, 1);
        let qs: Vec<&[f32]> = qv.iter().map(|v| v.as_slice()).collect();
        assert!(scores(store, &qs, None).is_err());
    }
}

/// A mixture store of `n` rows over a random codebook of `atoms` rows of width `d`, `slots`
/// slots per row (the last slot of every third row empty), through the shard codec.
fn mixture_store(
    n: usize,
    d: usize,
    atoms: usize,
    slots: usize,
    seed: u64,
    segments: Option<&[u32]>,
) -> VectorStore {
    use slag_common::shards::{MixtureShardInput, decode_mixture_shard, encode_mixture_shard};
    let mut s = seed;
    let book: Vec<f32> = queries(atoms, d, seed).into_iter().flatten().collect();
    let book: Vec<f32> = book
        .iter()
        .map(|&x| half::f16::from_f32(x).to_f32())
        .collect();
    let mut atoms_of = Vec::with_capacity(n * slots);
    let mut weights = Vec::with_capacity(n * slots);
    for i in 0..n {
        for k in 0..slots {
            if k == slots - 1 && i % 3 == 0 {
                atoms_of.push(slag_common::shards::mixture::UNUSED);
                weights.push(0.0);
            } else {
                atoms_of.push(((lcg(&mut s) * atoms as f32) as u32).min(atoms as u32 - 1));
                weights.push(0.05 + lcg(&mut s));
            }
        }
    }
    let ids: Vec<u32> = (0..n as u32).collect();
    let means: Vec<[f32; 3]> = (0..n).map(|i| [i as f32, 0.0, 0.0]).collect();
    let bytes = encode_mixture_shard(&MixtureShardInput {
        scene_id: "test",
        model: "test-model",
        tile_id: 0,
        dim: d,
        slots,
        codebook_crc: 0,
        ids: &ids,
        means: &means,
        atoms: &atoms_of,
        weights: &weights,
        segments,
        ..Default::default()
    })
    .expect("encode");
    let mut store = VectorStore::new_mixture(d, slots, book, 0).expect("store");
    store
        .push_mixture_shard(decode_mixture_shard(&bytes).expect("decode"))
        .expect("push");
    store
}

#[test]
fn mixture_shards_with_segments_give_each_row_its_segment() {
    let segments: Vec<u32> = (0..50u32).map(|i| i / 10).collect();
    let store = mixture_store(50, 8, 16, 3, 5, Some(&segments));
    assert_eq!(store.segments(), Some(&segments[..]));
    let plain = mixture_store(50, 8, 16, 3, 5, None);
    assert_eq!(plain.segments(), None);
}
