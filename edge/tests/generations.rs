//! One committed generation at a time: while `POST /fetch` (full discs, and small discs with
//! pruning) and `POST /reload` run in loops, every answer, `/stats` and `/health` report the
//! Gaussians of a shard set some fetch committed, never a set that was half downloaded or half
//! pruned. Also: concurrent fetches into one store through the library are serialised.
#![allow(clippy::unwrap_used)]

mod support;

use std::collections::BTreeSet;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use slag_common::shards::Dtype;
use slag_edge::serve::AppState;
use support::{
    BasisEmbedder, fetch_grid, grid_scene, grid_serve_options, serve_on_loopback, shard_server,
};

/// Gaussians per tile of the 4 × 4 grid.
const PER_TILE: u64 = 40;
/// Radius (ground units, around the origin) that selects tile (0, 0) only.
const SMALL: f64 = 4.0;
/// Radius that selects all 16 tiles.
const FULL: f64 = 100.0;

/// Observations of one kind (`what`) that are not one of the `committed` counts.
fn strays(seen: &[(String, u64)], committed: &BTreeSet<u64>) -> Vec<(String, u64)> {
    seen.iter()
        .filter(|(_, n)| !committed.contains(n))
        .cloned()
        .collect()
}

/// Loops `GET path` until `stop`, recording the number under `field` of every 200 answer.
async fn watch(
    url: String,
    path: &'static str,
    field: &'static str,
    stop: Arc<AtomicBool>,
) -> Vec<(String, u64)> {
    let client = reqwest::Client::new();
    let mut seen = Vec::new();
    while !stop.load(Ordering::SeqCst) {
        let r = client.get(format!("{url}{path}")).send().await.unwrap();
        if r.status() == 200 {
            let v: serde_json::Value = r.json().await.unwrap();
            seen.push((path.to_string(), v[field].as_u64().unwrap()));
        }
    }
    seen
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn answers_stats_and_health_come_from_committed_generations_under_fetch_and_reload() {
    let server = shard_server(
        grid_scene("grid", 4, 4, PER_TILE as usize, 8, Dtype::F16, 1),
        None,
    )
    .await;
    let (_dir, store) = fetch_grid(&server.url, FULL).await;
    // Slow shard bodies: each download takes a while, so reloads land in the middle of fetches.
    let len = server.state.scene.read().unwrap().shards[&0].len();
    *server.state.slow.lock().unwrap() = Some((len / 4, Duration::from_millis(15)));
    let embedder = Arc::new(BasisEmbedder::new(8));
    let state = AppState::new(store, embedder, grid_serve_options(None, false)).unwrap();
    let url = serve_on_loopback(state).await;
    let committed: BTreeSet<u64> = [PER_TILE, 16 * PER_TILE].into();

    let stop = Arc::new(AtomicBool::new(false));
    let watchers = [
        ("/query?text=t1&threshold=none&top_k=1", "searched"),
        ("/query?text=t2&threshold=none&top_k=1", "searched"),
        ("/stats", "gaussians"),
        ("/health", "gaussians"),
    ]
    .map(|(path, field)| tokio::spawn(watch(url.clone(), path, field, stop.clone())));
    let reloads = {
        let (url, stop) = (url.clone(), stop.clone());
        tokio::spawn(async move {
            let client = reqwest::Client::new();
            let mut n = 0;
            while !stop.load(Ordering::SeqCst) {
                let r = client.post(format!("{url}/reload")).send().await.unwrap();
                assert_eq!(r.status(), 200, "{}", r.text().await.unwrap());
                n += 1;
            }
            n
        })
    };
    let client = reqwest::Client::new();
    for cycle in 0..3 {
        for (radius, prune) in [(SMALL, true), (FULL, false), (SMALL, false)] {
            let body = serde_json::json!({"center": [0.0, 0.0], "radius": radius, "prune": prune});
            let r = client
                .post(format!("{url}/fetch"))
                .json(&body)
                .send()
                .await
                .unwrap();
            assert_eq!(
                r.status(),
                200,
                "cycle {cycle}: {}",
                r.text().await.unwrap()
            );
        }
    }
    stop.store(true, Ordering::SeqCst);
    let reloads = reloads.await.unwrap();
    let mut seen = Vec::new();
    for w in watchers {
        seen.extend(w.await.unwrap());
    }
    assert!(
        reloads > 0 && seen.len() > 20,
        "{reloads} reloads, {} answers",
        seen.len()
    );
    let strays = strays(&seen, &committed);
    assert!(
        strays.is_empty(),
        "{} of {} answers came from shard sets no fetch committed ({committed:?}): {:?}",
        strays.len(),
        seen.len(),
        &strays[..strays.len().min(20)]
    );
}
