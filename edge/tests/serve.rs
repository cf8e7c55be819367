//! `slag-edge serve` over loopback: answers equal an independent f64 reference over the decoded
//! shards; relevancy, bbox, batches, auth, limits and bad parameters.
#![allow(clippy::unwrap_used)]

mod support;

use std::sync::Arc;
use std::sync::atomic::Ordering;

use serde::Deserialize;
use slag_common::shards::{Dtype, decode_shard};
use slag_edge::serve::{AppState, HnswBackend, ServeOptions};
use support::{
    BasisEmbedder, GateEmbedder, TestScene, error_message, fetch_grid, grid_scene,
    grid_serve_options, header_number, match_ids, send, send_json, serve_on_loopback, shard_server,
    wait_until,
};

struct Edge {
    url: String,
    client: reqwest::Client,
    embedder: Arc<BasisEmbedder>,
    _dir: tempfile::TempDir,
}

async fn start(scene: TestScene, radius: f64, token: Option<&str>) -> (Edge, Vec<Vec<u8>>) {
    let dim = scene.manifest.dim as usize;
    let server = shard_server(scene, None).await;
    let (dir, store) = fetch_grid(&server.url, radius).await;
    let stored: Vec<Vec<u8>> = {
        let m = store.manifest("grid").unwrap().unwrap();
        m.tiles
            .iter()
            .filter_map(|t| store.shard_bytes("grid", t).unwrap())
            .collect()
    };
    let embedder = Arc::new(BasisEmbedder::new(dim));
    let state = AppState::new(store, embedder.clone(), grid_serve_options(token, true)).unwrap();
    (
        Edge {
            url: serve_on_loopback(state).await,
            client: reqwest::Client::new(),
            embedder,
            _dir: dir,
        },
        stored,
    )
}

/// Reference: every stored Gaussian's score in f64 over the dequantised shard vectors.
fn reference(
    shards: &[Vec<u8>],
    q: &[f32],
    negs: &[Vec<f32>],
    relevancy: bool,
) -> Vec<(u32, [f32; 3], f64)> {
    let mut out = Vec::new();
    for b in shards {
        let s = decode_shard(b).unwrap();
        for i in 0..s.ids.len() {
            let v = s.vector(i);
            let dot = |w: &[f32]| {
                v.iter()
                    .zip(w)
                    .map(|(a, b)| *a as f64 * *b as f64)
                    .sum::<f64>()
            };
            let pos = dot(q);
            let score = if relevancy {
                // LERF's pairwise softmax at temperature 10.
                negs.iter()
                    .map(|n| (10.0 * pos).exp() / ((10.0 * pos).exp() + (10.0 * dot(n)).exp()))
                    .fold(f64::INFINITY, f64::min)
            } else {
                pos
            };
            out.push((s.ids[i], s.means[i], score));
        }
    }
    out.sort_by(|a, b| b.2.total_cmp(&a.2).then(a.0.cmp(&b.0)));
    out
}

async fn get_json(e: &Edge, path: &str) -> (u16, serde_json::Value) {
    send_json(e.client.get(format!("{}{path}", e.url))).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn query_answers_match_an_independent_reference_for_every_dtype() {
    for dtype in [Dtype::F32, Dtype::F16, Dtype::I8] {
        let (e, shards) = start(grid_scene("grid", 3, 3, 60, 12, dtype, 1), 100.0, None).await;
        let q = e.embedder.vector("t4");
        let want = reference(&shards, &q, &[], false);
        let (status, a) = get_json(&e, "/query?text=t4").await;
        assert_eq!(status, 200, "{a}");
        assert_eq!(a["mode"], "cosine");
        assert_eq!(a["embedding_model"], "color-clip");
        let above: Vec<_> = want.iter().filter(|w| w.2 >= 0.28).collect();
        assert_eq!(
            a["summary"]["count"].as_u64().unwrap() as usize,
            above.len()
        );
        let got = match_ids(&a);
        assert_eq!(got.len(), above.len().min(100));
        // Same ranking up to near-ties (f32 kernel vs f64 reference).
        for (m, w) in a["matches"].as_array().unwrap().iter().zip(&above) {
            let s = m["score"].as_f64().unwrap();
            assert!((s - w.2).abs() < 1e-5, "{dtype:?}: {s} vs {}", w.2);
        }
        // Gaussians of tile 4 (ids 240..300) are the matches: the grid's ground truth.
        assert!(got.iter().all(|&i| (240..300).contains(&i)), "{got:?}");
        // Centroid and AABB of all matches.
        let n = above.len() as f64;
        for ax in 0..3 {
            let c = above.iter().map(|w| w.1[ax] as f64).sum::<f64>() / n;
            let got = a["summary"]["centroid"][ax].as_f64().unwrap();
            assert!((got - c).abs() < 1e-3, "centroid {ax}: {got} vs {c}");
        }

        // top_k + threshold=none: the k best of everything.
        let (_, a) = get_json(&e, "/query?text=t4&top_k=7&threshold=none").await;
        let best: Vec<u32> = want.iter().take(7).map(|w| w.0).collect();
        assert_eq!(match_ids(&a), best, "{dtype:?}");

        // bbox keeps only Gaussians inside.
        let (_, a) = get_json(
            &e,
            "/query?text=t4&bbox=10,10,0,15,15,1&threshold=none&top_k=10000",
        )
        .await;
        for m in a["matches"].as_array().unwrap() {
            let p = Vec::<f64>::deserialize(&m["position"]).unwrap();
            assert!(
                p[0] >= 10.0 && p[0] <= 15.0 && p[1] >= 10.0 && p[1] <= 15.0,
                "{p:?}"
            );
        }
        let inside = want
            .iter()
            .filter(|w| (10.0..=15.0).contains(&w.1[0]) && (10.0..=15.0).contains(&w.1[1]))
            .count();
        assert_eq!(match_ids(&a).len(), inside);

        // Relevancy against the canonical negatives (all map to the background basis here).
        let negs: Vec<Vec<f32>> = (0..4).map(|_| e.embedder.vector("object")).collect();
        let want_r = reference(&shards, &q, &negs, true);
        let (_, a) = get_json(&e, "/query?text=t4&mode=relevancy&top_k=5").await;
        assert_eq!(a["mode"], "relevancy");
        assert_eq!(a["threshold"].as_f64().unwrap(), 0.5);
        let above_r = want_r.iter().filter(|w| w.2 >= 0.5).count();
        assert_eq!(a["summary"]["count"].as_u64().unwrap() as usize, above_r);
        for (m, w) in a["matches"].as_array().unwrap().iter().zip(&want_r) {
            assert!((m["score"].as_f64().unwrap() - w.2).abs() < 1e-5);
        }

        // Nothing above the threshold: the best score is reported.
        let (_, a) = get_json(&e, "/query?text=t4&threshold=0.999").await;
        assert_eq!(a["summary"]["count"], 0);
        let best = a["best_score_below_threshold"].as_f64().unwrap();
        assert!((best - want[0].2).abs() < 1e-5);
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn batches_hnsw_stats_health_and_errors() {
    let (e, shards) = start(
        grid_scene("grid", 3, 3, 80, 12, Dtype::F16, 1),
        12.0,
        Some("tok"),
    )
    .await;
    let auth = |r: reqwest::RequestBuilder| r.bearer_auth("tok");
    // A request with the token, answered 200: its JSON body.
    let authed_json = async |r: reqwest::RequestBuilder| {
        let (status, body) = send_json(auth(r)).await;
        assert_eq!(status, 200, "{body}");
        body
    };

    // Health needs no token; everything else does.
    let (s, h) = get_json(&e, "/health").await;
    assert_eq!((s, h["status"].as_str()), (200, Some("ok")));
    let (s, err) = get_json(&e, "/query?text=t1").await;
    assert_eq!(s, 401, "{err}");
    assert!(error_message(&err).contains("Bearer"));
    let wrong = e.client.get(format!("{}/query?text=t1", e.url));
    assert_eq!(
        send(wrong.bearer_auth("wrong")).await.status().as_u16(),
        401
    );

    // Stats: what was fetched within 12 units of the origin: tiles 0, 1 and 3 (tile 4's corner
    // (10, 10) is 14.1 away).
    let st = authed_json(e.client.get(format!("{}/stats", e.url))).await;
    assert_eq!(st["shards_loaded"], 3);
    assert_eq!(st["shards_absent"], 6);
    assert_eq!(st["gaussians"], 240);
    assert!(st["memory"]["bytes_per_gaussian"].as_f64().unwrap() >= 12.0 * 2.0);
    assert_eq!(st["memory"]["hnsw_backend"], "instant-distance");
    assert!(st["memory"]["hnsw_bytes"].as_u64().unwrap() >= 240 * 12 * 4);
    assert_eq!(shards.len(), 3);

    // Batch: answers in order, equal to the single queries.
    let body = serde_json::json!({"queries": [
        {"text": "t0", "top_k": 3, "threshold": "none"},
        {"text": "t4", "mode": "relevancy", "top_k": 2},
    ]});
    let b = authed_json(e.client.post(format!("{}/query", e.url)).json(&body)).await;
    let answers = b["answers"].as_array().unwrap();
    assert_eq!(answers.len(), 2);
    let single = authed_json(
        e.client
            .get(format!("{}/query?text=t0&top_k=3&threshold=none", e.url)),
    )
    .await;
    assert_eq!(match_ids(&answers[0]), match_ids(&single));
    assert_eq!(answers[1]["mode"], "relevancy");

    // HNSW: top-k answered by the approximate index agrees with the exact one here.
    let top10 = "/query?text=t1&top_k=10&threshold=none";
    let h = authed_json(e.client.get(format!("{}{top10}&index=hnsw", e.url))).await;
    let x = authed_json(e.client.get(format!("{}{top10}", e.url))).await;
    assert_eq!(h["index"], "hnsw");
    let (hi, xi) = (match_ids(&h), match_ids(&x));
    let common = hi.iter().filter(|i| xi.contains(i)).count();
    assert!(common >= 9, "hnsw recall@10 {common}/10");

    // Bad input: 4xx with a message naming the field; the server stays up.
    for (path, status, needle) in [
        ("/query", 400, "missing query text"),
        ("/query?text=t1&top_k=abc", 400, "top_k"),
        ("/query?text=t1&top_k=1000000", 400, "top_k"),
        ("/query?text=t1&threshold=nan", 400, "threshold"),
        ("/query?text=t1&bbox=1,2", 400, "bbox"),
        ("/query?text=t1&mode=relevancy&index=hnsw", 400, "hnsw"),
        ("/query?text=t1&colour=red", 400, "colour"),
        ("/nope", 404, "no such route"),
    ] {
        let (s, v) = send_json(auth(e.client.get(format!("{}{path}", e.url)))).await;
        assert_eq!(s, status, "{path}");
        assert!(error_message(&v).contains(needle), "{path}: {v}");
    }
    let too_many: Vec<_> = (0..65).map(|_| serde_json::json!({"text": "t1"})).collect();
    let post = || auth(e.client.post(format!("{}/query", e.url)));
    let r = send(post().json(&serde_json::json!({ "queries": too_many }))).await;
    assert_eq!(r.status().as_u16(), 400);
    let second_bad = serde_json::json!({"queries": [{"text": "t1"}, {"text": "t1", "top_k": 0}]});
    let r = send(post().json(&second_bad)).await;
    assert_eq!(r.status().as_u16(), 400);
    assert!(r.text().await.unwrap().contains("queries[1]"));
    let big = "x".repeat(100 * 1024);
    let r = send(post().header("content-type", "application/json").body(big)).await;
    assert_eq!(r.status().as_u16(), 413);
    // The server closes a connection whose body it refused, so ask on a fresh connection (a pooled
    // one can race with that close: seen under qemu as hyper's IncompleteMessage).
    let r = send(reqwest::Client::new().get(format!("{}/health", e.url))).await;
    assert_eq!(r.status().as_u16(), 200);

    // The prompt is embedded once per query (negatives once at start-up).
    assert!(e.embedder.calls.load(Ordering::SeqCst) >= 1);
}

/// `index=hnsw` through each approximate-index backend: a backend this binary has answers with
/// the exact scan's ids and scores (here all ten of the exact top 10, the set is small) and
/// reports itself in `/stats`; one it lacks (`qdrant-edge` without the cargo feature) is refused
/// at start-up with a typed error before anything is served.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hnsw_backends_answer_like_the_exact_scan_or_are_refused_at_start_up() {
    for backend in HnswBackend::ALL {
        let server = shard_server(grid_scene("grid", 2, 2, 60, 12, Dtype::F16, 1), None).await;
        let (_dir, store) = fetch_grid(&server.url, 100.0).await;
        let opts = ServeOptions {
            hnsw: true,
            hnsw_backend: backend,
            ..ServeOptions::new("grid")
        };
        let state = match AppState::new(store, Arc::new(BasisEmbedder::new(12)), opts) {
            Ok(s) => s,
            Err(e) => {
                assert!(!backend.available(), "{backend}: {e}");
                assert!(
                    matches!(
                        e,
                        slag_common::Error::Param {
                            name: "hnsw_backend",
                            ..
                        }
                    ),
                    "{e}"
                );
                assert!(e.to_string().contains("cargo feature `qdrant-edge`"), "{e}");
                continue;
            }
        };
        assert!(backend.available());
        let url = serve_on_loopback(state).await;
        let client = reqwest::Client::new();
        let get = async |path: String| -> serde_json::Value {
            let (status, body) = send_json(client.get(format!("{url}{path}"))).await;
            assert_eq!(status, 200, "{path}");
            body
        };
        let st = get("/stats".into()).await;
        assert_eq!(st["memory"]["hnsw_backend"], backend.name());
        for t in ["t0", "t2", "t5"] {
            let h = get(format!(
                "/query?text={t}&index=hnsw&top_k=10&threshold=none"
            ))
            .await;
            let x = get(format!("/query?text={t}&top_k=10&threshold=none")).await;
            assert_eq!(h["index"], "hnsw");
            assert_eq!(match_ids(&h), match_ids(&x), "{backend} {t}");
            let scores = |v: &serde_json::Value| -> Vec<f64> {
                v["matches"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|m| m["score"].as_f64().unwrap())
                    .collect()
            };
            for (a, b) in scores(&h).iter().zip(scores(&x)) {
                assert!((a - b).abs() < 1e-5, "{backend} {t}: {a} vs {b}");
            }
            // The paper's threshold applies to index=hnsw answers too.
            let thr = get(format!("/query?text={t}&index=hnsw&top_k=50")).await;
            assert!(
                scores(&thr).iter().all(|&s| s >= 0.28 - 1e-6),
                "{backend} {t}"
            );
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn scans_run_one_at_a_time_in_arrival_order_and_a_full_queue_answers_503() {
    let scene = grid_scene("grid", 2, 2, 20, 8, Dtype::F32, 1);
    let server = shard_server(scene, None).await;
    let (_dir, store) = fetch_grid(&server.url, 100.0).await;
    let (gate, _open) = GateEmbedder::with_guard(8);
    let state = AppState::new(
        store,
        gate.clone(),
        ServeOptions {
            max_scans: 1,
            scan_queue: 2,
            ..ServeOptions::new("grid")
        },
    )
    .unwrap();
    let url = serve_on_loopback(state).await;
    let client = reqwest::Client::new();
    let stats =
        async || -> serde_json::Value { send_json(client.get(format!("{url}/stats"))).await.1 };
    let spawn_query = |text: &str| {
        let (c, u) = (client.clone(), format!("{url}/query?text={text}"));
        tokio::spawn(async move { send_json(c.get(u)).await })
    };

    // t1 holds the only scan permit (its prompt waits at the gate); t2 then t3 queue behind it.
    let a = spawn_query("t1");
    wait_until("t1 is scanning", async || gate.entered() == ["t1"]).await;
    let b = spawn_query("t2");
    wait_until("t2 waits", async || stats().await["scans"]["waiting"] == 1).await;
    let c = spawn_query("t3");
    wait_until("t3 waits", async || stats().await["scans"]["waiting"] == 2).await;
    let s = stats().await;
    assert_eq!(s["scans"]["running"], 1, "{s}");
    assert_eq!(s["scans"]["max_queue"], 2, "{s}");

    // The queue is full: a fourth query is turned away at once with 503 and Retry-After, as is a
    // batch; a bad query is still answered 400 (validation comes before the queue).
    let r = send(client.get(format!("{url}/query?text=t4"))).await;
    assert_eq!(r.status().as_u16(), 503);
    let retry = header_number(&r, "retry-after");
    assert!(retry >= 1, "Retry-After {retry}");
    let body: serde_json::Value = r.json().await.unwrap();
    assert_eq!(body["status"], 503);
    assert!(
        body["error"].as_str().unwrap().contains("retry after"),
        "{body}"
    );
    let batch = serde_json::json!({"queries": [{"text": "t5"}]});
    let r = send(client.post(format!("{url}/query")).json(&batch)).await;
    assert_eq!(r.status().as_u16(), 503);
    assert!(r.headers().contains_key("retry-after"));
    let r = send(client.get(format!("{url}/query?text=t6&top_k=0"))).await;
    assert_eq!(r.status().as_u16(), 400);

    // Released one at a time, the queued queries run in arrival order, each only after the one
    // before it has answered.
    for (i, (handle, text)) in [(a, "t1"), (b, "t2"), (c, "t3")].into_iter().enumerate() {
        gate.release(1);
        let (status, answer) = handle.await.unwrap();
        assert_eq!(status, 200, "{text}: {answer}");
        assert_eq!(answer["query"], text, "{answer}");
        if i < 2 {
            let next = ["t2", "t3"][i];
            wait_until("the next queued query starts", async || {
                gate.entered().len() == i + 2
            })
            .await;
            assert_eq!(gate.entered()[i + 1], next);
        }
    }
    assert_eq!(gate.entered(), ["t1", "t2", "t3"]);
    let s = stats().await;
    assert_eq!(s["scans"]["waiting"], 0, "{s}");
    assert_eq!(s["scans"]["running"], 0, "{s}");
    assert_eq!(s["scans"]["rejected_busy"], 2, "{s}");
    assert_eq!(s["queries_served"], 3, "{s}");
}

/// A text model that panics on the prompt `boom` (a bug in the model code, say) and is the
/// basis embedder otherwise.
struct PanickyEmbedder(BasisEmbedder);

impl slag_edge::query::TextEmbedder for PanickyEmbedder {
    fn embed(&self, texts: &[&str]) -> slag_common::Result<Vec<Vec<f32>>> {
        assert!(!texts.contains(&"boom"), "injected panic in the text model");
        slag_edge::query::TextEmbedder::embed(&self.0, texts)
    }
    fn name(&self) -> String {
        "panicky".into()
    }
    fn cached(&self) -> usize {
        0
    }
}

/// Who has to act decides the status: a bad query is the client's (400, the message naming the
/// field), a panicked query task slag's own fault (500, `Error::Internal`); the server stays up
/// after each.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bad_query_is_400_and_a_panicked_query_task_500() {
    let scene = grid_scene("grid", 2, 2, 20, 8, Dtype::F32, 1);
    let dim = scene.manifest.dim as usize;
    let server = shard_server(scene, None).await;
    let (_dir, store) = fetch_grid(&server.url, 100.0).await;
    let state = AppState::new(
        store,
        Arc::new(PanickyEmbedder(BasisEmbedder::new(dim))),
        ServeOptions::new("grid"),
    )
    .unwrap();
    let url = serve_on_loopback(state).await;
    let client = reqwest::Client::new();
    let get = |path: String| send_json(client.get(format!("{url}{path}")));
    let (s, v) = get("/query?text=t1&top_k=0".into()).await;
    assert_eq!(s, 400, "{v}");
    assert_eq!(v["status"], 400);
    assert!(error_message(&v).contains("top_k"), "{v}");
    let (s, v) = get("/query?text=boom".into()).await;
    assert_eq!(s, 500, "{v}");
    let msg = error_message(&v);
    assert!(
        msg.contains("internal fault") && msg.contains("query task failed"),
        "{msg}"
    );
    // A batch answers the panicked item's status in place, like any other error.
    let boom = serde_json::json!({"queries": [{"text": "boom"}]});
    let (_, b) = send_json(client.post(format!("{url}/query")).json(&boom)).await;
    assert_eq!(b["answers"][0]["status"], 500, "{b}");
    // Still serving.
    let (s, v) = get("/query?text=t1&top_k=1&threshold=none".into()).await;
    assert_eq!(s, 200, "{v}");
}
