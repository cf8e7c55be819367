//! `slag-edge serve` against hostile clients: stalled and idle sockets are closed within the
//! header timeout, the connection limit keeps `/health` answering, one request cannot ask for an
//! unbounded answer, every error has the JSON body (405, 408, 413, 414, 431), `Retry-After`
//! estimates the real drain time, and a blank token refuses to start.
#![allow(clippy::unwrap_used)]

mod support;

use std::sync::Arc;
use std::time::Duration;

use slag_common::http::ServerLimits;
use slag_common::shards::Dtype;
use slag_common::testing::{
    assert_answered_while_stalled, assert_blank_token_refused, assert_json_error, closed_within,
    exchange, exchange_error, flood_from_one_address, get_request as get,
};
use slag_edge::serve::{AppState, ServeOptions};
use support::{
    BasisEmbedder, GateEmbedder, error_message, exact_answer, fetch_grid, grid_scene,
    header_number, send, send_json, shard_server, wait_until,
};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// Serves a 2×2-tile grid scene with `opts` (scene "grid", dimension 8); returns `host:port`.
async fn edge(
    embedder: Arc<dyn slag_edge::query::TextEmbedder>,
    opts: ServeOptions,
) -> (String, tempfile::TempDir) {
    let server = shard_server(grid_scene("grid", 2, 2, 20, 8, Dtype::F32, 1), None).await;
    let (dir, store) = fetch_grid(&server.url, 100.0).await;
    let url = support::serve_on_loopback(AppState::new(store, embedder, opts).unwrap()).await;
    (url.trim_start_matches("http://").to_string(), dir)
}

/// [`edge`] with the basis embedder and `limits`, every other option at its default.
async fn edge_with_limits(limits: ServerLimits) -> (String, tempfile::TempDir) {
    let opts = ServeOptions {
        limits,
        ..ServeOptions::new("grid")
    };
    edge(Arc::new(BasisEmbedder::new(8)), opts).await
}

/// Limits with one address allowed every slot (the global connection limit alone).
fn limits(header_s: u64, max_connections: usize) -> ServerLimits {
    ServerLimits {
        header_timeout: Duration::from_secs(header_s),
        write_timeout: Duration::from_secs(5),
        max_connections,
        max_connections_per_ip: max_connections,
        ..ServerLimits::default()
    }
}

/// A `POST /query` head announcing a 60,000-byte body, and the body's first 12 bytes: the
/// probe's stalled body.
const STALLED_BODY: &[u8] =
    b"POST /query HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n\
    Content-Length: 60000\r\n\r\n{\"queries\": ";

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stalled_request_body_gets_408_and_its_connection_closes_at_the_body_timeout() {
    // Header timeout and request timeout far beyond the body timeout: only the body-read
    // deadline can close this connection within the bound below.
    let opts = ServeOptions {
        limits: ServerLimits {
            body_timeout: Duration::from_secs(1),
            ..limits(60, 64)
        },
        request_timeout: Duration::from_secs(120),
        ..ServeOptions::new("grid")
    };
    let (addr, _dir) = edge(Arc::new(BasisEmbedder::new(8)), opts).await;
    let mut s = tokio::net::TcpStream::connect(&addr).await.unwrap();
    s.write_all(STALLED_BODY).await.unwrap();
    let answer = tokio::time::timeout(
        Duration::from_secs(30),
        slag_common::testing::read_answer(&mut s),
    )
    .await
    .expect("the stalled body is answered within 30 s, well before the 60 s header timeout");
    let (status, head, body) = answer;
    assert_eq!(status, 408, "{head}\n{body}");
    assert_json_error(408, &head, &body);
    assert!(
        head.to_ascii_lowercase().contains("connection: close"),
        "{head}"
    );
    // The server still answers on a new connection.
    let (status, _, body) = exchange(&addr, &get("/health", "")).await;
    assert_eq!(status, 200, "{body}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_address_cannot_take_every_connection_slot() {
    // 16 slots, 4 per address, timeouts far beyond the test: nothing closes a stalled socket
    // while the test runs except the per-address share.
    let opts = ServeOptions {
        limits: ServerLimits {
            header_timeout: Duration::from_secs(60),
            body_timeout: Duration::from_secs(60),
            max_connections: 16,
            max_connections_per_ip: 4,
            ..ServerLimits::default()
        },
        request_timeout: Duration::from_secs(120),
        ..ServeOptions::new("grid")
    };
    let (addr, _dir) = edge(Arc::new(BasisEmbedder::new(8)), opts).await;
    // 24 stalled bodies from one address: more than every slot. Another address is answered
    // at once (it still has its share of the slots); the flooding address is told why (429
    // with Retry-After and the JSON body).
    let (mut stalled, head, body) =
        flood_from_one_address(&addr, 24, STALLED_BODY, "/health").await;
    assert!(
        head.to_ascii_lowercase().contains("retry-after: 1"),
        "{head}"
    );
    assert!(body.contains("at most 4"), "{body}");
    // Exactly 4 of the 24 hold a slot; the other 20 were closed at once.
    let mut open = 0;
    for s in &mut stalled {
        let mut buf = [0u8; 512];
        // Still waiting for a byte after 500 ms: the server holds it (a refused one has its 429
        // or its end of stream to read at once).
        if tokio::time::timeout(Duration::from_millis(500), s.read(&mut buf))
            .await
            .is_err()
        {
            open += 1;
        }
    }
    assert_eq!(open, 4, "stalled connections still held by the server");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stalled_and_idle_connections_are_closed_within_the_header_timeout() {
    let (addr, _dir) = edge_with_limits(limits(1, 64)).await;
    // One header line, then nothing (the probe's stalled socket).
    let mut stalled = tokio::net::TcpStream::connect(&addr).await.unwrap();
    stalled
        .write_all(b"GET /health HTTP/1.1\r\nHost: x\r\n")
        .await
        .unwrap();
    // Connected, never sends a byte.
    let mut silent = tokio::net::TcpStream::connect(&addr).await.unwrap();
    // Kept alive after one answer, then idle.
    let mut kept = tokio::net::TcpStream::connect(&addr).await.unwrap();
    kept.write_all(b"GET /health HTTP/1.1\r\nHost: x\r\n\r\n")
        .await
        .unwrap();
    let mut buf = [0u8; 4096];
    let n = kept.read(&mut buf).await.unwrap();
    assert!(String::from_utf8_lossy(&buf[..n]).starts_with("HTTP/1.1 200"));
    for s in [&mut stalled, &mut silent, &mut kept] {
        // 1 s timeout; 10 s bounds a loaded machine, not the speed.
        closed_within(s, Duration::from_secs(10)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_answers_while_stalled_sockets_hold_every_connection_slot() {
    let (addr, _dir) = edge_with_limits(limits(1, 8)).await;
    // Three times the limit stalls; slots come free as the header timeout closes them.
    assert_answered_while_stalled(&addr, 24, "/health", "\"ok\"").await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_request_cannot_ask_for_more_matches_than_the_cap() {
    let opts = ServeOptions {
        max_matches: 300,
        ..ServeOptions::new("grid")
    };
    let (addr, _dir) = edge(Arc::new(BasisEmbedder::new(8)), opts).await;
    let client = reqwest::Client::new();
    let batch = |k: usize, n: usize| {
        let q: Vec<_> = (0..n)
            .map(|_| serde_json::json!({"text": "a", "top_k": k, "threshold": "none"}))
            .collect();
        serde_json::json!({ "queries": q })
    };
    let post =
        |addr: &str, body| send_json(client.post(format!("http://{addr}/query")).json(&body));
    let (status, v) = post(&addr, batch(100, 3)).await;
    assert_eq!(status, 200);
    assert_eq!(v["answers"].as_array().unwrap().len(), 3, "{v}");
    assert_eq!(v["answers"][0]["matches"].as_array().unwrap().len(), 80);
    // 4 × 100 > 300: refused before any scan, naming the limit.
    let (status, v) = post(&addr, batch(100, 4)).await;
    assert_eq!(status, 400);
    let m = error_message(&v);
    assert!(
        m.contains("max_matches") && m.contains("300") && m.contains("400"),
        "{m}"
    );
    let r = send(client.get(format!("http://{addr}/query?text=a&top_k=301"))).await;
    assert_eq!(r.status(), 400);
    // The 3.6 KB request of the probe (64 × top_k 10000, no threshold) under the default cap.
    let (addr2, _dir2) = edge(Arc::new(BasisEmbedder::new(8)), ServeOptions::new("grid")).await;
    let (status, v) = post(&addr2, batch(10_000, 64)).await;
    assert_eq!(status, 400);
    assert!(error_message(&v).contains("20000"), "{v}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_error_the_server_sends_has_the_json_body() {
    let (gate, _open) = GateEmbedder::with_guard(8);
    let opts = ServeOptions {
        request_timeout: Duration::from_millis(500),
        ..ServeOptions::new("grid")
    };
    let (addr, _dir) = edge(gate.clone(), opts).await;
    // 405: a method the route does not answer.
    let (s, head, body) = exchange(
        &addr,
        b"DELETE /query HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n",
    )
    .await;
    assert_eq!(s, 405, "{head}");
    assert_json_error(405, &head, &body);
    assert!(head.to_ascii_lowercase().contains("allow:"), "{head}");
    // 413: a body over the limit.
    let big = format!(
        "{{\"queries\": [{{\"text\": \"{}\"}}]}}",
        "a".repeat(70_000)
    );
    let raw = format!(
        "POST /query HTTP/1.1\r\nHost: x\r\nConnection: close\r\nContent-Type: application/json\r\n\
         Content-Length: {}\r\n\r\n{big}",
        big.len()
    );
    exchange_error(&addr, raw.as_bytes(), 413).await;
    // 414: an overlong request target.
    let path = format!("/query?text={}", "a".repeat(9_000));
    exchange_error(&addr, &get(&path, ""), 414).await;
    // 431: an oversized header block.
    let hdr = format!("X-Pad: {}\r\n", "b".repeat(20_000));
    exchange_error(&addr, &get("/health", &hdr), 431).await;
    // 408: a query held past the request timeout (its prompt waits at the gate).
    exchange_error(&addr, &get("/query?text=t1", ""), 408).await;
    // 404 and 400 as before.
    exchange_error(&addr, &get("/nope", ""), 404).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn retry_after_covers_the_scan_that_is_still_running() {
    let (gate, _open) = GateEmbedder::with_guard(8);
    let opts = ServeOptions {
        max_scans: 1,
        scan_queue: 1,
        request_timeout: Duration::from_secs(60),
        ..ServeOptions::new("grid")
    };
    let (addr, _dir) = edge(gate.clone(), opts).await;
    let client = reqwest::Client::new();
    let spawn_query = |text: &str| {
        let (c, u) = (client.clone(), format!("http://{addr}/query?text={text}"));
        tokio::spawn(async move { send(c.get(u)).await.status().as_u16() })
    };
    // The first scan ever runs for 3 s (no scan has finished: no moving average yet).
    let a = spawn_query("t1");
    wait_until("t1 is scanning", async || gate.entered() == ["t1"]).await;
    tokio::time::sleep(Duration::from_secs(3)).await;
    let b = spawn_query("t2");
    let stats = async || {
        send_json(client.get(format!("http://{addr}/stats")))
            .await
            .1
    };
    wait_until("t2 waits", async || stats().await["scans"]["waiting"] == 1).await;
    let r = send(client.get(format!("http://{addr}/query?text=t3"))).await;
    assert_eq!(r.status(), 503);
    let retry = header_number(&r, "retry-after");
    // Two scans ahead (the running one and t2), each taking at least the 3 s t1 has run.
    assert!(
        retry >= 6,
        "Retry-After {retry} s while the running scan alone took 3 s"
    );
    gate.release(2);
    assert_eq!(a.await.unwrap(), 200);
    assert_eq!(b.await.unwrap(), 200);
}

/// A batch whose request timed out stops at the query it is on: the scan slot is free for the
/// next request at once, not after every query of the abandoned batch.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_timed_out_batch_stops_scanning_and_frees_the_slot() {
    let (gate, _open) = GateEmbedder::with_guard(8);
    let opts = ServeOptions {
        max_scans: 1,
        // Long enough for the follow-up query on a loaded machine; the batch's 408 waits it out.
        request_timeout: Duration::from_secs(3),
        ..ServeOptions::new("grid")
    };
    let (addr, _dir) = edge(gate.clone(), opts).await;
    let client = reqwest::Client::new();
    let q: Vec<_> = (1..=5)
        .map(|i| serde_json::json!({"text": format!("t{i}")}))
        .collect();
    let r = send(
        client
            .post(format!("http://{addr}/query"))
            .json(&serde_json::json!({ "queries": q })),
    )
    .await;
    assert_eq!(r.status(), 408);
    assert_eq!(gate.entered(), ["t1"]);
    // t1 finishes; t2..t5 must not start, and the next request gets the slot.
    gate.release(2);
    let r = send(client.get(format!("http://{addr}/query?text=t9"))).await;
    assert_eq!(r.status(), 200);
    assert_eq!(gate.entered(), ["t1", "t9"]);
}

#[test]
fn a_blank_token_in_the_environment_refuses_to_start() {
    for blank in ["", "   "] {
        let mut c = support::slag_edge_command();
        let out = c
            .args(["serve", "--scene", "grid", "--store", "/nonexistent/store"])
            .args([
                "--clip-textual",
                "/nonexistent/m.onnx",
                "--tokenizer",
                "/nonexistent/t.json",
            ])
            .env("SLAG_EDGE_TOKEN", blank)
            .env("RUST_LOG", "warn")
            .output()
            .unwrap();
        assert_blank_token_refused(&out, "SLAG_EDGE_TOKEN");
    }
}

/// An answer holds only the matches it returns: a threshold query collects every match above its
/// threshold (80 here), and a batch's answers must not keep that capacity until it is sent.
#[tokio::test]
async fn a_threshold_answer_holds_only_the_matches_it_returns() {
    use slag_edge::query::RawQuery;
    let server = shard_server(grid_scene("grid", 2, 2, 20, 8, Dtype::F32, 1), None).await;
    let (_dir, store) = fetch_grid(&server.url, 100.0).await;
    let engine = slag_edge::engine::Engine::load(&store, "grid", false).unwrap();
    let q = RawQuery {
        text: Some("t0".into()),
        top_k: Some("3".into()),
        threshold: Some("-1".into()),
        ..Default::default()
    };
    let a = exact_answer(&engine, 8, q, true);
    assert_eq!(a.summary.count, 80, "every Gaussian passes threshold -1");
    let a = slag_edge::serve::compact_answer(a);
    assert_eq!(a.matches.len(), 3);
    assert!(a.matches.capacity() < 80, "{}", a.matches.capacity());
    assert!(
        a.match_objects.capacity() < 80,
        "{}",
        a.match_objects.capacity()
    );
}
