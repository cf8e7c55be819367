//! The approximate-index abstraction with each backend this binary has: recall against the exact
//! scan, scores and ids as the exact scan's, parameter checks, and the refusal of a backend the
//! binary was built without.

use super::*;
use crate::scan::{ScanRequest, scan};
use slag_common::shards::Dtype;

/// Unit query `i`: stored row `i · 617` perturbed (near a row, equal to none).
fn query(store: &VectorStore, i: usize) -> Vec<f32> {
    let mut q = store.row_f32(i * 617 % store.len()).expect("row");
    for (j, x) in q.iter_mut().enumerate() {
        *x += 0.05 * (((j * 7 + i) % 13) as f32 / 13.0 - 0.5);
    }
    let n = q.iter().map(|x| x * x).sum::<f32>().sqrt();
    q.iter_mut().for_each(|x| *x /= n);
    q
}

/// Mean recall@k of `index` against the exact scan over 20 queries; checks every hit's score is
/// the dot product with the dequantised row and the order is the exact scan's (score desc, row
/// asc).
fn recall(index: &ApproxIndex, store: &VectorStore, k: usize) -> f64 {
    let mut found = 0usize;
    let mut total = 0usize;
    for i in 0..20 {
        let q = query(store, i);
        let qs: [&[f32]; 1] = [&q];
        let exact = scan(store, &ScanRequest::top_k(&qs, k)).expect("scan");
        let approx = index.query(&q, k).expect("query");
        assert_eq!(approx.len(), k);
        for h in &approx {
            let r = store.row_f32(h.row).expect("row");
            let dot: f32 = r.iter().zip(&q).map(|(a, b)| a * b).sum();
            assert!(
                (dot - h.score).abs() < 1e-4,
                "score {} vs dot {dot}",
                h.score
            );
        }
        assert!(
            approx
                .windows(2)
                .all(|w| crate::scan::select::rank_cmp(&w[0], &w[1]).is_le()),
            "best first"
        );
        total += exact.len();
        found += approx
            .iter()
            .filter(|h| exact.iter().any(|e| e.row == h.row))
            .count();
    }
    found as f64 / total as f64
}

fn params(ef_search: usize) -> HnswParams {
    HnswParams {
        ef_construction: 64,
        ef_search,
        seed: 3,
        ..HnswParams::default()
    }
}

#[test]
fn instant_distance_recall_is_high_on_every_dtype() {
    for dtype in [Dtype::F32, Dtype::F16, Dtype::I8] {
        let store = VectorStore::synthetic(5_000, 48, dtype, 20, 11).expect("store");
        let index =
            ApproxIndex::build(&store, HnswBackend::InstantDistance, &params(64)).expect("index");
        assert_eq!(index.backend(), HnswBackend::InstantDistance);
        assert_eq!(index.len(), 5_000);
        assert_eq!(index.ef_search(), 64);
        let r = recall(&index, &store, 20);
        assert!(r >= 0.95, "{dtype:?} recall@20 {r}");
    }
}

#[test]
fn backend_names_round_trip_and_unknown_ones_are_refused() {
    for b in HnswBackend::ALL {
        assert_eq!(HnswBackend::from_name(b.name()).expect("name"), b);
        assert_eq!(b.to_string(), b.name());
    }
    assert_eq!(
        HnswBackend::from_name("qdrant").expect("short name"),
        HnswBackend::QdrantEdge
    );
    assert!(matches!(
        HnswBackend::from_name("faiss"),
        Err(Error::Param {
            name: "hnsw_backend",
            ..
        })
    ));
    assert_eq!(HnswBackend::default(), HnswBackend::InstantDistance);
    assert!(HnswBackend::InstantDistance.available());
}

#[test]
fn bad_parameters_are_typed_errors() {
    let store = VectorStore::synthetic(200, 8, Dtype::F32, 3, 1).expect("store");
    for (p, name) in [
        (
            HnswParams {
                ef_construction: 0,
                ..params(10)
            },
            "ef_construction",
        ),
        (params(0), "ef_search"),
    ] {
        for b in HnswBackend::ALL.into_iter().filter(|b| b.available()) {
            match ApproxIndex::build(&store, b, &p) {
                Err(Error::Param { name: n, .. }) => assert_eq!(n, name),
                other => panic!("{b}: expected Param {name}, got {other:?}"),
            }
        }
    }
    // Every backend: k beyond the beam, and a query of another width.
    for b in HnswBackend::ALL.into_iter().filter(|b| b.available()) {
        let index = ApproxIndex::build(&store, b, &params(10)).expect("index");
        match index.query(&[0.1; 8], 11) {
            Err(Error::Param { name: "top_k", .. }) => {}
            other => panic!("{b}: expected Param top_k, got {other:?}"),
        }
        match index.query(&[0.1; 7], 5) {
            Err(Error::Mismatch { .. }) => {}
            other => panic!("{b}: expected Mismatch, got {other:?}"),
        }
    }
    let mut index =
        ApproxIndex::build(&store, HnswBackend::InstantDistance, &params(10)).expect("index");
    // instant-distance's beam is fixed at build time.
    assert!(index.set_ef_search(10).is_ok());
    assert!(matches!(
        index.set_ef_search(20),
        Err(Error::Param {
            name: "ef_search",
            ..
        })
    ));
}

/// Without the cargo feature the qdrant-edge backend is refused with a typed error that says how
/// to rebuild, by the name check and by the build.
#[cfg(not(feature = "qdrant-edge"))]
#[test]
fn qdrant_edge_is_refused_without_the_feature() {
    assert!(!HnswBackend::QdrantEdge.available());
    let e = HnswBackend::QdrantEdge.require().expect_err("refused");
    assert!(matches!(
        e,
        Error::Param {
            name: "hnsw_backend",
            ..
        }
    ));
    assert!(e.is_user_input());
    assert!(e.to_string().contains("cargo feature `qdrant-edge`"), "{e}");
    let store = VectorStore::synthetic(100, 8, Dtype::F32, 3, 1).expect("store");
    assert!(matches!(
        ApproxIndex::build(&store, HnswBackend::QdrantEdge, &params(10)),
        Err(Error::Param {
            name: "hnsw_backend",
            ..
        })
    ));
}

#[cfg(feature = "qdrant-edge")]
#[test]
fn qdrant_edge_recall_is_high_and_its_beam_is_adjustable() {
    let scratch = tempfile::tempdir().expect("tempdir");
    for dtype in [Dtype::F32, Dtype::F16, Dtype::I8] {
        let store = VectorStore::synthetic(5_000, 48, dtype, 20, 11).expect("store");
        let p = HnswParams {
            scratch_dir: Some(scratch.path().to_path_buf()),
            threads: 2,
            ..params(64)
        };
        let mut index = ApproxIndex::build(&store, HnswBackend::QdrantEdge, &p).expect("index");
        assert_eq!(index.backend(), HnswBackend::QdrantEdge);
        assert_eq!(index.len(), 5_000);
        // At least the f32 copy of the rows.
        assert!(
            index.memory_bytes() >= 5_000 * 48 * 4,
            "{}",
            index.memory_bytes()
        );
        let r = recall(&index, &store, 20);
        assert!(r >= 0.95, "{dtype:?} recall@20 {r}");
        assert!(matches!(
            index.query(&query(&store, 1), 65),
            Err(Error::Param { name: "top_k", .. })
        ));
        index.set_ef_search(200).expect("qdrant beam");
        assert_eq!(index.ef_search(), 200);
        assert_eq!(
            index.query(&query(&store, 1), 150).expect("query").len(),
            150
        );
        assert!(matches!(
            index.query(&[0.1; 47], 5),
            Err(Error::Mismatch { .. })
        ));
    }
    // Every scratch shard is removed with its index.
    let left: Vec<_> = std::fs::read_dir(scratch.path())
        .expect("scratch")
        .flatten()
        .map(|e| e.path())
        .collect();
    assert!(left.is_empty(), "{left:?}");
    let empty = VectorStore::new(8, Dtype::F32).expect("store");
    let e = ApproxIndex::build(&empty, HnswBackend::QdrantEdge, &params(10)).expect("empty");
    assert!(e.query(&[0.1; 8], 5).expect("query").is_empty());
}
