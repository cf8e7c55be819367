//! The robot path for the mixture form: encode snowmiku-mini with
//! `--mixture-keep 16` → `partition --embeddings --mixture-keep 8` (mixture shards + codebook) →
//! `slag-encoder serve` → `slag-edge fetch` (codebook verified) → `Engine` / `slag-edge serve`,
//! whose scores must equal `MixtureEmbeddings::truncated(8).scores` (the held-out evaluation's
//! "top 8 cut from 16"); a corrupted or truncated codebook is refused with a typed error.

#![allow(clippy::unwrap_used)]

use std::collections::HashMap;
use std::time::Duration;

use slag_common::Error;
use slag_common::mixture::MixtureEmbeddings;
use slag_common::shards::MIXTURE_MANIFEST_VERSION;
use slag_edge::engine::Engine;
use slag_edge::scan::{ScanRequest, lerf_relevancy, scan};
use slag_tests::{
    Shards, fixture, robot_fetch_params, robot_path_with, send_expecting, test_runtime,
};

fn text_embedding(text: &str) -> Vec<f32> {
    let mut enc = slag_common::text::TextEncoder::new(
        &fixture("clip/color-clip-textual.onnx"),
        &fixture("clip/clip-tokenizer.json"),
        slag_common::onnx::ExecutionProvider::Cpu,
    )
    .unwrap();
    enc.encode(&[text]).unwrap().remove(0)
}

#[test]
fn mixture_shards_are_served_with_the_scores_of_the_mixture_file() {
    let rt = test_runtime();
    let robot = robot_path_with(
        &rt,
        Shards::Mixture {
            keep: 16,
            slots: Some(8),
        },
        Duration::from_secs(60),
        None,
    );
    let full = MixtureEmbeddings::read(robot.mixture.as_ref().unwrap()).unwrap();
    let mix = full.truncated(8).unwrap();
    assert!(full.keep > 8, "the encode kept {} slots", full.keep);

    // Manifest v2 with the codebook; every Gaussian fetched.
    let m = &robot.manifest;
    assert_eq!(m.manifest_version, MIXTURE_MANIFEST_VERSION);
    let info = m.mixture.as_ref().unwrap();
    assert_eq!(info.slots, 8);
    assert_eq!(info.atoms as usize, mix.codebook_len());
    assert_eq!(robot.fetched.gaussians, mix.len() as u64);
    assert_eq!(robot.fetched.codebook_bytes, info.codebook_bytes);

    // The engine's exact mixture scan: every row's score equals the mixture file's.
    let engine = Engine::load(&robot.edge, "snowmiku-mini", false).unwrap();
    assert!(engine.store.is_mixture());
    assert_eq!(engine.store.len(), mix.len());
    let reference: HashMap<&str, HashMap<u32, f32>> = ["pink", "red", "object", "things"]
        .iter()
        .map(|t| {
            let s = mix.scores(&text_embedding(t)).unwrap();
            (*t, mix.gaussian_ids.iter().copied().zip(s).collect())
        })
        .collect();
    let q = text_embedding("pink");
    let unit: Vec<f32> = {
        let n = q.iter().map(|v| v * v).sum::<f32>().sqrt();
        q.iter().map(|v| v / n).collect()
    };
    let qs = [unit.as_slice()];
    let all = scan(&engine.store, &ScanRequest::top_k(&qs, engine.store.len())).unwrap();
    assert_eq!(all.len(), mix.len());
    let ids = engine.store.ids();
    let mut worst = 0f32;
    for h in &all {
        let want = reference["pink"][&ids[h.row]];
        worst = worst.max((h.score - want).abs());
    }
    assert!(
        worst < 1e-5,
        "largest |edge - MixtureEmbeddings::scores| {worst}"
    );
    // The paper threshold on the same scan.
    let above = scan(&engine.store, &ScanRequest::threshold(&qs, 0.28)).unwrap();
    let want = reference["pink"].values().filter(|&&s| s >= 0.28).count();
    assert!(above.len().abs_diff(want) <= 2, "{} vs {want}", above.len());
    assert!(above.len() > 100, "pink matches {}", above.len());
    // A box on the means keeps exactly the rows inside it.
    let (lo, hi) = ([-0.5f32, -0.5, -0.5], [0.5f32, 0.5, 0.5]);
    let boxed = scan(
        &engine.store,
        &ScanRequest {
            bbox: Some((lo, hi)),
            ..ScanRequest::top_k(&qs, engine.store.len())
        },
    )
    .unwrap();
    let inside = engine
        .store
        .means()
        .iter()
        .filter(|p| (0..3).all(|a| p[a] >= lo[a] && p[a] <= hi[a]))
        .count();
    assert_eq!(boxed.len(), inside);
    // LERF relevancy over the mixture rows: the combiner sees the same per-query cosines.
    let neg = text_embedding("object");
    let neg_unit: Vec<f32> = {
        let n = neg.iter().map(|v| v * v).sum::<f32>().sqrt();
        neg.iter().map(|v| v / n).collect()
    };
    let qs2 = [unit.as_slice(), neg_unit.as_slice()];
    let rel = scan(
        &engine.store,
        &ScanRequest {
            combine: Some(&lerf_relevancy),
            ..ScanRequest::top_k(&qs2, 50)
        },
    )
    .unwrap();
    for h in &rel {
        let id = ids[h.row];
        let want = lerf_relevancy(&[reference["pink"][&id], reference["object"][&id]]);
        assert!((h.score - want).abs() < 1e-4, "{} vs {want}", h.score);
    }

    rt.block_on(async {
        let client = reqwest::Client::new();
        let url = &robot.edge_url;
        // GET /query: the 100 best "red" Gaussians with the reference's scores.
        let red = client.get(format!("{url}/query?text=red&top_k=100&threshold=none"));
        let a: serde_json::Value = send_expecting(red, 200).await.json().await.unwrap();
        let matches = a["matches"].as_array().unwrap();
        assert_eq!(matches.len(), 100);
        let mut best: Vec<f32> = reference["red"].values().copied().collect();
        best.sort_by(|x, y| y.total_cmp(x));
        for (m, want) in matches.iter().zip(&best) {
            let id = m["id"].as_u64().unwrap() as u32;
            let score = m["score"].as_f64().unwrap() as f32;
            assert!((score - reference["red"][&id]).abs() < 1e-5);
            assert!((score - want).abs() < 1e-5, "rank order: {score} vs {want}");
        }
        // Relevancy mode answers over mixture rows too.
        let pink = client.get(format!("{url}/query?text=pink&mode=relevancy&top_k=10"));
        send_expecting(pink, 200).await;
        // HNSW is not built over mixtures: a 400 that says why.
        let hnsw = client.get(format!("{url}/query?text=pink&index=hnsw"));
        let body = send_expecting(hnsw, 400).await.text().await.unwrap();
        assert!(
            body.contains("mixture") && body.contains("index=exact"),
            "{body}"
        );
    });

    // A corrupted or truncated codebook on disk: the scene is refused with a typed error (no
    // row can be scored without it), and the next fetch downloads it again.
    let path = robot.edge.codebook_path(&robot.manifest).unwrap().unwrap();
    let good = std::fs::read(&path).unwrap();
    let mut bad = good.clone();
    let at = bad.len() / 2;
    bad[at] ^= 0x10;
    for broken in [bad, good[..good.len() - 7].to_vec()] {
        std::fs::write(&path, &broken).unwrap();
        let err = Engine::load(&robot.edge, "snowmiku-mini", false)
            .err()
            .unwrap();
        assert!(matches!(err, Error::Format { .. }), "{err}");
        assert!(err.to_string().contains("codebook"), "{err}");
    }
    std::fs::remove_file(&path).unwrap();
    let err = Engine::load(&robot.edge, "snowmiku-mini", false)
        .err()
        .unwrap();
    assert!(err.to_string().contains("slag-edge fetch"), "{err}");
    std::fs::write(&path, &good[..100]).unwrap();
    let again = rt
        .block_on(slag_edge::fetch::fetch(
            &robot.edge,
            &robot_fetch_params(&robot.shard_url),
        ))
        .unwrap();
    assert_eq!(again.bytes_received, info.codebook_bytes);
    assert_eq!(std::fs::read(&path).unwrap(), good);
    assert_eq!(
        Engine::load(&robot.edge, "snowmiku-mini", false)
            .unwrap()
            .store
            .len(),
        mix.len()
    );

    // A corrupted download is never committed: the partial file is refused, nothing at the
    // codebook's path.
    std::fs::remove_file(&path).unwrap();
    let part = robot.dir.path().join("codebook.part");
    let mut flipped = good.clone();
    flipped[good.len() - 1] ^= 1;
    std::fs::write(&part, &flipped).unwrap();
    let err = robot
        .edge
        .commit_codebook_partial(&robot.manifest, &part)
        .unwrap_err();
    assert!(matches!(err, Error::Format { .. }), "{err}");
    assert!(!path.exists());
}
