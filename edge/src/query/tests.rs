//! Tests of query parsing (the paper's and LERF's defaults, typed errors naming the field, JSON
//! numbers and arrays) and of the relevancy score against LERF's formula.

#![allow(clippy::unwrap_used)]

use super::*;
use crate::scan;
use slag_common::similarity::PAPER_THRESHOLD;

fn raw(pairs: &[(&str, &str)]) -> RawQuery {
    let v: serde_json::Map<String, serde_json::Value> = pairs
        .iter()
        .map(|(k, v)| (k.to_string(), serde_json::Value::String(v.to_string())))
        .collect();
    RawQuery::from_json(&serde_json::Value::Object(v)).unwrap()
}

#[test]
fn defaults_follow_the_paper_and_lerf() {
    let q = raw(&[("text", "chair")]).validate(PAPER_THRESHOLD).unwrap();
    assert_eq!(q.threshold, Some(PAPER_THRESHOLD));
    assert_eq!(q.top_k, DEFAULT_TOP_K);
    assert_eq!(q.mode, ScoreMode::Cosine);
    let q = raw(&[("text", "chair"), ("mode", "relevancy")])
        .validate(PAPER_THRESHOLD)
        .unwrap();
    assert_eq!(q.threshold, Some(RELEVANCY_THRESHOLD));
    let q = raw(&[("text", "chair"), ("threshold", "none")])
        .validate(PAPER_THRESHOLD)
        .unwrap();
    assert_eq!(q.threshold, None);
}

#[test]
fn bad_parameters_are_typed_errors_naming_the_field() {
    for (pairs, needle) in [
        (vec![], "missing query text"),
        (vec![("text", "   ")], "missing query text"),
        (vec![("text", "a"), ("top_k", "0")], "top_k"),
        (vec![("text", "a"), ("top_k", "10001")], "top_k"),
        (vec![("text", "a"), ("top_k", "-3")], "top_k"),
        (vec![("text", "a"), ("threshold", "NaN")], "threshold"),
        (vec![("text", "a"), ("threshold", "2")], "threshold"),
        (
            vec![("text", "a"), ("mode", "relevancy"), ("threshold", "-0.1")],
            "threshold",
        ),
        (vec![("text", "a"), ("mode", "fuzzy")], "mode"),
        (vec![("text", "a"), ("bbox", "1,2,3")], "bbox"),
        (vec![("text", "a"), ("bbox", "1,1,1,0,0,0")], "bbox"),
        (vec![("text", "a"), ("bbox", "0,0,0,inf,1,1")], "bbox"),
        (vec![("text", "a"), ("index", "ivf")], "index"),
    ] {
        let e = raw(&pairs)
            .validate(PAPER_THRESHOLD)
            .unwrap_err()
            .to_string();
        assert!(e.contains(needle), "{pairs:?}: {e}");
    }
    let long = "x".repeat(MAX_TEXT_BYTES + 1);
    assert!(raw(&[("text", &long)]).validate(PAPER_THRESHOLD).is_err());
    let e = RawQuery::from_json(&serde_json::json!({"text": "a", "topk": 3})).unwrap_err();
    assert!(e.to_string().contains("topk"));
    assert!(RawQuery::from_json(&serde_json::json!(["a"])).is_err());
}

#[test]
fn json_numbers_and_arrays_are_accepted() {
    let q = RawQuery::from_json(&serde_json::json!({
        "text": "red", "top_k": 5, "threshold": 0.1, "bbox": [0, 0, 0, 1, 2, 3]
    }))
    .unwrap()
    .validate(PAPER_THRESHOLD)
    .unwrap();
    assert_eq!(q.top_k, 5);
    assert_eq!(q.threshold, Some(0.1));
    assert_eq!(q.bbox, Some([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]]));
}

#[test]
fn relevancy_matches_lerf_formula() {
    // Independent form: min over negatives of the pairwise softmax at temperature 10.
    let dots = [0.3f32, 0.1, 0.25, -0.2, 0.2];
    let e = |x: f32| (10.0 * x).exp();
    let want = dots[1..]
        .iter()
        .map(|&n| e(dots[0]) / (e(dots[0]) + e(n)))
        .fold(f32::INFINITY, f32::min);
    assert!((scan::lerf_relevancy(&dots) - want).abs() < 1e-6);
    // Prompt equal to the closest negative: exactly 0.5.
    assert!((scan::lerf_relevancy(&[0.4, 0.4, 0.0]) - 0.5).abs() < 1e-7);
    // Extremes stay finite and within (0, 1).
    let r = scan::lerf_relevancy(&[-1.0, 1.0]);
    assert!(r > 0.0 && r < 0.5);
}
