//! The whole robot path on the embedded real scene: encode snowmiku-mini (graph masks +
//! color-clip) → partition into shards → `slag-encoder serve` → `slag-edge fetch` a radius →
//! `slag-edge serve` → `GET /query?text=…`, compared with the encoder's local `query`.

#![allow(clippy::unwrap_used)]

use std::collections::HashSet;
use std::time::Duration;

use slag_edge::fetch::Center;
use slag_encoder::query::QueryParams;
use slag_tests::{fixture, robot_fetch_params, robot_path, send_expecting, test_runtime};

fn local_query(
    emb: &std::path::Path,
    text: &str,
    top_k: usize,
    threshold: f32,
) -> serde_json::Value {
    let out = slag_encoder::query::run(&QueryParams {
        top_k,
        threshold,
        ..QueryParams::new(
            emb,
            fixture("clip/color-clip-textual.onnx"),
            fixture("clip/clip-tokenizer.json"),
            text,
        )
    })
    .unwrap();
    serde_json::to_value(out).unwrap()
}

fn scores(matches: &serde_json::Value) -> Vec<f64> {
    matches
        .as_array()
        .unwrap()
        .iter()
        .map(|m| m["score"].as_f64().unwrap())
        .collect()
}

/// Both answers hold the same Gaussians above the cut-off `cut` (ties and ~1e-6 score differences
/// at the cut-off may order them differently): each side's ids clearly above the cut are among
/// the other side's ids above it.
fn assert_same_ids(a: &serde_json::Value, b: &serde_json::Value, cut: f64) {
    let (a_clear, b_all) = (ids_above(a, cut + 2e-5), ids_above(b, cut - 2e-5));
    let (b_clear, a_all) = (ids_above(b, cut + 2e-5), ids_above(a, cut - 2e-5));
    assert!(a_clear.is_subset(&b_all) && b_clear.is_subset(&a_all));
}

/// Ids whose score is strictly above `floor`.
fn ids_above(matches: &serde_json::Value, floor: f64) -> HashSet<u64> {
    matches
        .as_array()
        .unwrap()
        .iter()
        .filter(|m| m["score"].as_f64().unwrap() > floor)
        .map(|m| m["id"].as_u64().unwrap())
        .collect()
}

fn assert_same_summary(a: &serde_json::Value, b: &serde_json::Value) {
    assert_eq!(a["count"], b["count"]);
    for key in ["centroid"] {
        for ax in 0..3 {
            let (x, y) = (a[key][ax].as_f64().unwrap(), b[key][ax].as_f64().unwrap());
            assert!((x - y).abs() < 1e-4, "{key}[{ax}] {x} vs {y}");
        }
    }
    for c in 0..2 {
        for ax in 0..3 {
            let (x, y) = (
                a["aabb"][c][ax].as_f64().unwrap(),
                b["aabb"][c][ax].as_f64().unwrap(),
            );
            assert!((x - y).abs() < 1e-5, "aabb[{c}][{ax}] {x} vs {y}");
        }
    }
}

#[test]
fn encode_partition_serve_fetch_serve_query_matches_the_local_query() {
    let rt = test_runtime();
    // f32 shards: the edge sees exactly the values of the embeddings file.
    let robot = robot_path(&rt, "f32", false, Duration::from_secs(60), None);
    let (emb, manifest, edge, edge_url) = (
        robot.embeddings.clone(),
        robot.manifest.clone(),
        robot.edge.clone(),
        robot.edge_url.clone(),
    );
    let mut params = robot_fetch_params(&robot.shard_url);
    rt.block_on(async {
        assert!(manifest.tiles.len() >= 4, "{} tiles", manifest.tiles.len());
        // The fetch covered the scene's whole ground footprint.
        let s = &robot.fetched;
        assert_eq!(s.selected, manifest.tiles.len());
        assert_eq!(s.gaussians, manifest.total_gaussians);

        let client = reqwest::Client::new();
        let get = |path: String| {
            let c = client.clone();
            async move {
                let r = c.get(path).send().await.unwrap();
                assert_eq!(r.status().as_u16(), 200);
                r.json::<serde_json::Value>().await.unwrap()
            }
        };

        // "red", ranked: the 50 reddest Gaussians, same scores as the local query.
        let a = get(format!("{edge_url}/query?text=red&top_k=50&threshold=none")).await;
        let l = local_query(&emb, "red", 50, -1.0);
        let (sa, sl) = (scores(&a["matches"]), scores(&l["matches"]));
        assert_eq!(sa.len(), 50);
        for (x, y) in sa.iter().zip(&sl) {
            assert!((x - y).abs() < 1e-5, "red score {x} vs {y}");
        }
        let cut = sa[49];
        assert_same_ids(&a["matches"], &l["matches"], cut);

        // "red" at the paper threshold: snowmiku has no red region (color-clip's ground truth
        // classes there are gray/pink/brown/white/black), so both answer nothing and agree on
        // how close the best Gaussian came.
        let a = get(format!("{edge_url}/query?text=red")).await;
        let l = local_query(&emb, "red", 20, 0.28);
        assert_eq!(a["summary"]["count"], l["summary"]["count"]);
        if a["summary"]["count"] == 0 {
            let best = a["best_score_below_threshold"].as_f64().unwrap();
            let lbest = l["nearest_below_threshold"][0]["score"].as_f64().unwrap();
            assert!((best - lbest).abs() < 1e-5);
        }

        // "pink" at the paper threshold: same matches (count, AABB, centroid) and same ranking.
        let a = get(format!("{edge_url}/query?text=pink&top_k=10000")).await;
        let l = local_query(&emb, "pink", 10000, 0.28);
        let n = a["summary"]["count"].as_u64().unwrap();
        assert!(n > 100, "pink should match a region, got {n}");
        assert_same_summary(&a["summary"], &l["summary"]);
        let (sa, sl) = (scores(&a["matches"]), scores(&l["matches"]));
        assert_eq!(sa.len(), sl.len());
        for (i, (x, y)) in sa.iter().zip(&sl).enumerate() {
            // f32 dot products summed in another order: ~1e-6 apart.
            assert!((x - y).abs() < 1e-5, "pink score #{i}: {x} vs {y} (of {n})");
        }
        let cut = *sa.last().unwrap();
        assert_same_ids(&a["matches"], &l["matches"], cut);

        // A narrower radius with --prune keeps fewer tiles; its pink matches are exactly the
        // local matches that lie in the kept tiles.
        let (center, radius) = {
            let t = &manifest.tiles[0];
            let g0 =
                t.footprint.iter().map(|p| p[0] as f64).sum::<f64>() / t.footprint.len() as f64;
            let g1 =
                t.footprint.iter().map(|p| p[1] as f64).sum::<f64>() / t.footprint.len() as f64;
            ([g0, g1], 0.0)
        };
        params.center = Center::Ground(center);
        params.radius = radius;
        params.prune = true;
        let s = slag_edge::fetch::fetch(&edge, &params).await.unwrap();
        assert!(s.selected >= 1 && s.selected < manifest.tiles.len());
        assert_eq!(s.evicted, manifest.tiles.len() - s.selected);
        send_expecting(client.post(format!("{edge_url}/reload")), 200).await;
        let kept: HashSet<u64> = {
            let (_, shards, _) = edge.load_scene("snowmiku-mini").unwrap();
            shards
                .iter()
                .flat_map(|s| s.ids.iter().map(|&i| i as u64))
                .collect()
        };
        let a = get(format!("{edge_url}/query?text=pink&top_k=10000")).await;
        let local_in: usize = l["matches"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|m| kept.contains(&m["id"].as_u64().unwrap()))
            .count();
        if n <= 10000 {
            assert_eq!(a["summary"]["count"].as_u64().unwrap() as usize, local_in);
        }
        for m in a["matches"].as_array().unwrap() {
            assert!(kept.contains(&m["id"].as_u64().unwrap()));
        }
    });
}
