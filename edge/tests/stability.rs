//! Numerical stability of the query side: zero and non-finite prompt
//! embeddings, zero-norm stored rows, in the exact scan (f32 / f16 / int8), the HNSW index, the
//! LERF relevancy combiner and `run_query`. Expected: a typed [`Error::Query`] (HTTP 400) for a
//! prompt embedding without a direction, and finite scores (0 for a zero row) everywhere else;
//! never a NaN score or a panic.
//!
//! Run: `cargo test --workspace --test stability`.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use proptest::prelude::*;
use slag_common::Error;
use slag_common::Result;
use slag_common::shards::Dtype;
use slag_edge::query::{IndexKind, QueryParams, ScoreMode, TextEmbedder, run_query};
use slag_edge::scan::hnsw::HnswIndex;
use slag_edge::scan::{ScanRequest, VectorStore, lerf_relevancy, scan};

const DIM: usize = 16;

/// A text model that returns a fixed vector for every prompt.
struct Fixed(Vec<f32>);
impl TextEmbedder for Fixed {
    fn embed(&self, texts: &[&str]) -> Result<Vec<Vec<f32>>> {
        Ok(texts.iter().map(|_| self.0.clone()).collect())
    }
    fn name(&self) -> String {
        "fixed".into()
    }
    fn cached(&self) -> usize {
        0
    }
}

fn unit(v: Vec<f32>) -> Vec<f32> {
    let n = v.iter().map(|x| (*x as f64).powi(2)).sum::<f64>().sqrt();
    v.into_iter().map(|x| (x as f64 / n) as f32).collect()
}

/// `n` rows: row 0 and row 3 all-zero (a zero-norm stored vector), the others unit vectors.
fn rows(n: usize) -> Vec<f32> {
    let mut v = Vec::with_capacity(n * DIM);
    for i in 0..n {
        if i == 0 || i == 3 {
            v.extend(std::iter::repeat_n(0.0, DIM));
        } else {
            v.extend(unit(
                (0..DIM)
                    .map(|d| ((i * 7 + d * 5) % 13) as f32 - 6.0)
                    .collect(),
            ));
        }
    }
    v
}

fn store(dtype: Dtype, n: usize) -> VectorStore {
    let mut s = VectorStore::new(DIM, dtype).expect("store");
    let ids: Vec<u32> = (0..n as u32).collect();
    let means: Vec<[f32; 3]> = (0..n).map(|i| [i as f32, 0.0, 0.0]).collect();
    s.push_f32_rows(&ids, &means, &rows(n)).expect("rows");
    s
}

fn params(mode: ScoreMode, threshold: Option<f32>) -> QueryParams {
    QueryParams {
        text: "a chair".into(),
        top_k: 5,
        threshold,
        mode,
        bbox: None,
        index: IndexKind::Exact,
        frame: Default::default(),
        objects: Default::default(),
        smooth: Default::default(),
    }
}

#[test]
fn zero_or_non_finite_prompt_embeddings_are_a_typed_400_error() {
    let s = store(Dtype::F32, 40);
    let negatives: Vec<Vec<f32>> = (0..4)
        .map(|k| unit((0..DIM).map(|d| ((d + k) % 3) as f32).collect()))
        .collect();
    let bad: [(&str, Vec<f32>); 4] = [
        ("zero", vec![0.0; DIM]),
        ("subnormal", vec![1e-45; DIM]),
        ("NaN", {
            let mut v = vec![0.25; DIM];
            v[3] = f32::NAN;
            v
        }),
        ("infinite", {
            let mut v = vec![0.25; DIM];
            v[0] = f32::INFINITY;
            v
        }),
    ];
    for (what, phi) in bad {
        for mode in [ScoreMode::Cosine, ScoreMode::Relevancy] {
            for threshold in [None, Some(0.28)] {
                let r = run_query(
                    &s,
                    "m",
                    &Fixed(phi.clone()),
                    &negatives,
                    None,
                    &params(mode, threshold),
                );
                match r {
                    Err(Error::Query {
                        field: "text",
                        message: m,
                    }) => {
                        assert!(m.contains("prompt") && m.contains("norm"), "{what}: {m}")
                    }
                    other => panic!("{what} {mode:?}: expected Error::Query, got {other:?}"),
                }
            }
        }
    }
    // Control: a small but non-zero prompt embedding (norm 1e-6) is a direction: it is
    // normalised, and scores are the unit prompt's cosines.
    let u = unit((0..DIM).map(|d| d as f32 - 7.5).collect());
    let small: Vec<f32> = u.iter().map(|x| x * 1e-6).collect();
    let p = params(ScoreMode::Cosine, None);
    let a = run_query(&s, "m", &Fixed(small), &negatives, None, &p).expect("small prompt");
    let b = run_query(&s, "m", &Fixed(u), &negatives, None, &p).expect("unit prompt");
    assert_eq!(a.matches.len(), 5);
    for (x, y) in a.matches.iter().zip(&b.matches) {
        assert_eq!(x.id, y.id);
        assert!(
            (x.score - y.score).abs() < 1e-6,
            "{} vs {}",
            x.score,
            y.score
        );
        assert!(x.score.is_finite() && x.score.abs() <= 1.0 + 1e-5);
    }
}

#[test]
fn zero_rows_score_zero_in_every_dtype_and_the_index() {
    let n = 300;
    let q = unit((0..DIM).map(|d| (d % 5) as f32 - 2.0).collect());
    let zero_q = vec![0.0f32; DIM];
    for dtype in [Dtype::F32, Dtype::F16, Dtype::I8] {
        let s = store(dtype, n);
        // Every row's score, via threshold -inf.
        for (label, query) in [("unit", &q), ("zero", &zero_q)] {
            let qs: [&[f32]; 1] = [query];
            let hits = scan(&s, &ScanRequest::threshold(&qs, f32::NEG_INFINITY)).expect("scan");
            assert_eq!(hits.len(), n, "{dtype:?} {label}");
            for h in &hits {
                assert!(h.score.is_finite(), "{dtype:?} {label}: row {} NaN", h.row);
                if h.row == 0 || h.row == 3 || label == "zero" {
                    assert_eq!(h.score, 0.0, "{dtype:?} {label}: row {}", h.row);
                }
            }
        }
        // LERF relevancy with a zero row: 1 / (1 + exp(0)) = 0.5, finite.
        let negs = unit((0..DIM).map(|d| (d % 2) as f32).collect());
        let qs: [&[f32]; 2] = [&q, &negs];
        let req = ScanRequest {
            queries: &qs,
            top_k: None,
            threshold: Some(f32::NEG_INFINITY),
            bbox: None,
            combine: Some(&lerf_relevancy),
        };
        let hits = scan(&s, &req).expect("relevancy");
        assert!(
            hits.iter()
                .all(|h| h.score.is_finite() && (0.0..=1.0).contains(&h.score))
        );
        let zero_row = hits.iter().find(|h| h.row == 0).expect("row 0");
        assert_eq!(zero_row.score, 0.5, "{dtype:?}");
        // HNSW over a store holding zero rows: builds, answers finite scores.
        let index = HnswIndex::build(&s, 32, 32, 7).expect("hnsw build");
        let hits = index.query(&q, 10).expect("hnsw query");
        assert_eq!(hits.len(), 10, "{dtype:?}");
        assert!(
            hits.iter().all(|h| h.score.is_finite()),
            "{dtype:?}: {hits:?}"
        );
        let hits = index.query(&zero_q, 10).expect("hnsw zero query");
        assert!(hits.iter().all(|h| h.score == 0.0), "{dtype:?}: {hits:?}");
    }
}

#[test]
fn non_finite_queries_and_rows_are_typed_errors() {
    let s = store(Dtype::F16, 20);
    let mut q = vec![0.1f32; DIM];
    q[5] = f32::NAN;
    let qs: [&[f32]; 1] = [&q];
    assert!(matches!(
        scan(&s, &ScanRequest::top_k(&qs, 3)),
        Err(Error::Query { .. })
    ));
    let mut s2 = VectorStore::new(DIM, Dtype::I8).expect("store");
    let mut v = rows(2);
    v[1] = f32::INFINITY;
    assert!(matches!(
        s2.push_f32_rows(&[0, 1], &[[0.0; 3]; 2], &v),
        Err(Error::Invalid(_))
    ));
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// Any finite query (including huge, tiny, zero components) against unit and zero rows in
    /// every dtype: every score finite.
    #[test]
    fn prop_any_finite_query_gives_finite_scores(
        q in proptest::collection::vec(
            prop_oneof![Just(0.0f32), -1e-30f32..1e-30, -1.0f32..1.0, -1e3f32..1e3],
            DIM,
        ),
        dt in prop_oneof![Just(Dtype::F32), Just(Dtype::F16), Just(Dtype::I8)],
    ) {
        let s = store(dt, 50);
        let qs: [&[f32]; 1] = [&q];
        let hits = scan(&s, &ScanRequest::threshold(&qs, f32::NEG_INFINITY)).unwrap();
        prop_assert_eq!(hits.len(), 50);
        prop_assert!(hits.iter().all(|h| h.score.is_finite()));
    }
}
