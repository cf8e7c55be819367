//! Edge query parameters: `POST /query` items (`RawQuery::from_json` + `validate`) and the
//! `GET /query?…` path (form-urlencoded pairs as axum's `Query` decodes them → `raw_from_pairs`
//! → `validate`). Accepted parameters must be within the documented ranges.
#![no_main]

use std::collections::HashMap;

use libfuzzer_sys::fuzz_target;
use slag_edge::query::{QueryParams, RawQuery};

fn check(p: &QueryParams) {
    assert!((1..=slag_edge::query::MAX_TOP_K).contains(&p.top_k));
    assert!(!p.text.trim().is_empty());
    if let Some(t) = p.threshold {
        assert!(t.is_finite());
    }
    if let Some([lo, hi]) = p.bbox {
        assert!(lo.iter().chain(&hi).all(|x| x.is_finite()));
    }
}

fuzz_target!(|data: &[u8]| {
    if let Ok(v) = serde_json::from_slice::<serde_json::Value>(data)
        && let Ok(raw) = RawQuery::from_json(&v)
        && let Ok(p) = raw.validate(0.25)
    {
        check(&p);
    }
    if let Ok(s) = std::str::from_utf8(data)
        && let Ok(pairs) = serde_urlencoded::from_str::<HashMap<String, String>>(s)
        && let Ok(raw) = slag_edge::serve::raw_from_pairs(pairs)
        && let Ok(p) = raw.validate(0.25)
    {
        check(&p);
    }
});
