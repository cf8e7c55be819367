//! One committed generation at a time: while `POST /fetch` (full discs, and small discs with
//! pruning) and `POST /reload` run in loops, every answer, `/stats` and `/health` report the
//! Gaussians of a shard set some fetch committed, never a set that was half downloaded or half
//! pruned. Then the same through the library with many threads: loads racing a writer that
//! commits and evicts, and the swap of the served engine ([`ServedEngine`]), every snapshot a
//! whole committed generation and never an older one than a reader saw before.
#![allow(clippy::unwrap_used)]

mod support;

use std::collections::BTreeSet;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use slag_common::shards::Dtype;
use slag_edge::engine::{Engine, ServedEngine};
use slag_edge::serve::AppState;
use slag_edge::store::{EdgeStore, FetchRecord};
use support::{
    BasisEmbedder, TestScene, fetch_grid, grid_scene, grid_serve_options, serve_on_loopback,
    shard_server, temp_store,
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
    let post_fetch = async |radius: f64, prune: bool| {
        let body = serde_json::json!({"center": [0.0, 0.0], "radius": radius, "prune": prune});
        let r = client
            .post(format!("{url}/fetch"))
            .json(&body)
            .send()
            .await
            .unwrap();
        let status = r.status();
        assert_eq!(status, 200, "{}", r.text().await.unwrap());
    };
    for _ in 0..3 {
        // In turn, then two at once (the second waits for the first).
        for (radius, prune) in [(SMALL, true), (FULL, false), (SMALL, false)] {
            post_fetch(radius, prune).await;
        }
        tokio::join!(post_fetch(SMALL, true), post_fetch(FULL, false));
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

/// Commits a generation of `scene` holding the tiles `set` as a fetch does: the missing shard
/// files first (without the lock, like downloads), then under the generation lock the manifest
/// with the list of held tiles (with `prune` only `set`, else also every other stored tile),
/// then the evictions.
fn commit_generation(store: &EdgeStore, scene: &TestScene, set: &[u64], prune: bool) {
    let m = &scene.manifest;
    for t in m.tiles.iter().filter(|t| set.contains(&t.id)) {
        if !store.has_shard("grid", t).unwrap() {
            store.commit_shard(m, t, &scene.shards[&t.id]).unwrap();
        }
    }
    let _generation = store.lock_generation();
    let tiles: Vec<u64> = m
        .tiles
        .iter()
        .filter(|t| set.contains(&t.id) || (!prune && store.has_shard("grid", t).unwrap()))
        .map(|t| t.id)
        .collect();
    let record = FetchRecord {
        server: "http://test.invalid".into(),
        center: [0.0, 0.0],
        radius: 0.0,
        completed_unix_s: 0,
        tiles: Some(tiles),
        kept: None,
    };
    store.commit_fetch(m, &record).unwrap();
    if prune {
        for t in m.tiles.iter().filter(|t| !set.contains(&t.id)) {
            store
                .remove_shard("grid", t.id, u32::from_str_radix(&t.checksum, 16).unwrap())
                .unwrap();
        }
    }
}

/// The engine holds exactly the generation its record names: every listed tile loaded, nothing
/// else, nothing rejected, `PER_TILE` Gaussians per tile.
fn assert_whole(e: &Engine) {
    let mut listed = e.record.as_ref().unwrap().tiles.clone().unwrap();
    listed.sort_unstable();
    let mut loaded = e.load.loaded_tiles.clone();
    loaded.sort_unstable();
    assert_eq!(
        loaded, listed,
        "generation {}: {:?}",
        e.seq, e.load.rejected
    );
    assert!(e.load.rejected.is_empty(), "{:?}", e.load.rejected);
    assert_eq!(e.store.len() as u64, PER_TILE * listed.len() as u64);
}

#[test]
fn loads_and_swaps_under_a_committing_writer_see_whole_generations_in_order() {
    let scene = grid_scene("grid", 3, 3, PER_TILE as usize, 8, Dtype::F16, 1);
    let (_dir, store) = temp_store();
    let all: Vec<u64> = (0..9).collect();
    commit_generation(&store, &scene, &all, false);
    let served = Arc::new(ServedEngine::new(
        Engine::load(&store, "grid", false).unwrap(),
    ));
    let stop = Arc::new(AtomicBool::new(false));
    let mut threads = Vec::new();
    // Loaders: load, check, offer (two of them, so offers arrive out of order).
    for _ in 0..2 {
        let (store, served, stop) = (store.clone(), served.clone(), stop.clone());
        threads.push(std::thread::spawn(move || {
            let mut n = 0;
            while !stop.load(Ordering::SeqCst) {
                let e = Engine::load(&store, "grid", false).unwrap();
                assert_whole(&e);
                served.offer(e);
                n += 1;
            }
            n
        }));
    }
    // Readers: every snapshot whole, and never older than the last one this reader saw.
    for _ in 0..2 {
        let (served, stop) = (served.clone(), stop.clone());
        threads.push(std::thread::spawn(move || {
            let (mut last, mut n) = (0, 0);
            while !stop.load(Ordering::SeqCst) {
                let e = served.current();
                assert_whole(&e);
                assert!(e.seq >= last, "generation {} after {last}", e.seq);
                last = e.seq;
                n += 1;
            }
            n
        }));
    }
    let sets: [(&[u64], bool); 4] = [
        (&[0], true),
        (&all, false),
        (&[0, 1, 3, 4], true),
        (&[8], false),
    ];
    for i in 0..40 {
        let (set, prune) = sets[i % sets.len()];
        commit_generation(&store, &scene, set, prune);
    }
    stop.store(true, Ordering::SeqCst);
    let counts: Vec<usize> = threads.into_iter().map(|t| t.join().unwrap()).collect();
    assert!(counts.iter().all(|&n| n > 0), "{counts:?}");
    // The last offer of a later generation than the last commit's cannot exist: the one served
    // now is at most that, and a fresh load gives exactly it.
    let last = Engine::load(&store, "grid", false).unwrap();
    assert_whole(&last);
    assert!(served.current().seq <= last.seq);
    assert_eq!(last.store.len() as u64, 5 * PER_TILE);
}
