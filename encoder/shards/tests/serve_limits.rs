//! The shard server against hostile clients: stalled and idle sockets closed within the header
//! timeout, a client that stops reading dropped after the write timeout, the connection limit,
//! JSON error bodies for 405 / 414 / 431 / 416, the bearer scheme in any case, and a blank
//! `SLAG_SHARD_TOKEN` refused at start-up.
#![allow(clippy::unwrap_used)]

mod support;

use std::time::Duration;

use slag_common::http::ServerLimits;
use slag_common::testing::{
    assert_json_error, closed_within, exchange, get_request as get, stalled_heads,
};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// Limits with one address allowed every slot (the global connection limit alone).
fn limits(header_s: u64, write_s: u64, max_connections: usize) -> ServerLimits {
    ServerLimits {
        write_timeout: Duration::from_secs(write_s),
        ..support::limits(header_s, max_connections, max_connections)
    }
}

/// A served store of one small scene `lab`; returns `host:port`.
async fn start(token: Option<&str>, limits: ServerLimits) -> (String, tempfile::TempDir) {
    support::serve_lab(token, limits, None).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stalled_sockets_close_and_the_connection_limit_keeps_the_server_answering() {
    let (addr, _dir) = start(None, limits(1, 5, 8)).await;
    let mut idle = tokio::net::TcpStream::connect(&addr).await.unwrap();
    let mut stalled = stalled_heads(&addr, 24, "/v1/scenes").await;
    let (status, _, body) = exchange(&addr, &get("/v1/scenes", "")).await;
    assert_eq!(status, 200, "{body}");
    assert!(body.contains("lab"), "{body}");
    closed_within(&mut idle, Duration::from_secs(30)).await;
    for s in &mut stalled {
        closed_within(s, Duration::from_secs(30)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_address_cannot_take_every_connection_slot() {
    // 8 slots, 3 per address, a header timeout beyond the test: only the per-address share
    // keeps a slot for another client.
    let l = ServerLimits {
        max_connections_per_ip: 3,
        ..limits(60, 5, 8)
    };
    let (addr, _dir) = start(None, l).await;
    let flood: std::net::IpAddr = "127.0.0.1".parse().unwrap();
    let other: std::net::IpAddr = "127.0.0.2".parse().unwrap();
    let mut stalled = Vec::new();
    for _ in 0..16 {
        let mut s = slag_common::testing::connect_from(flood, &addr).await;
        let _ = s.write_all(b"GET /v1/scenes HTTP/1.1\r\n").await;
        stalled.push(s);
    }
    let (status, _, body) = tokio::time::timeout(
        Duration::from_secs(20),
        slag_common::testing::exchange_from(other, &addr, &get("/v1/scenes", "")),
    )
    .await
    .expect("another address is answered while one address floods the server");
    assert_eq!(status, 200, "{body}");
    let mut s = slag_common::testing::connect_from(flood, &addr).await;
    let (status, head, body) = slag_common::testing::read_answer(&mut s).await;
    assert_eq!(status, 429, "{head}\n{body}");
    assert_json_error(429, &head, &body);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_authorization_headers_get_401() {
    let (addr, _dir) = start(Some("tok"), limits(10, 5, 64)).await;
    let one = "Authorization: Bearer tok\r\n";
    slag_common::testing::assert_two_authorizations_refused(&addr, "/v1/scenes", one).await;
}

/// A client that stops reading is dropped after the write timeout instead of holding its
/// answer: the body is cut short. Served by the same loop as the store routes
/// ([`slag_common::http::serve`]), with a body larger than the socket buffers can hold.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_stops_reading_is_dropped_after_the_write_timeout() {
    const LEN: usize = 64 << 20;
    let router = axum::Router::new().route("/big", axum::routing::get(|| async { vec![7u8; LEN] }));
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    tokio::spawn(slag_common::http::serve(
        listener,
        router,
        limits(5, 1, 16),
        std::future::pending(),
    ));
    let sock = tokio::net::TcpSocket::new_v4().unwrap();
    sock.set_recv_buffer_size(4096).unwrap();
    let mut s = sock.connect(addr).await.unwrap();
    s.write_all(b"GET /big HTTP/1.1\r\nHost: x\r\n\r\n")
        .await
        .unwrap();
    // Read nothing for well past the 1 s write timeout.
    tokio::time::sleep(Duration::from_secs(4)).await;
    let mut got = Vec::new();
    let _ = tokio::time::timeout(Duration::from_secs(30), s.read_to_end(&mut got))
        .await
        .expect("the server closed the connection");
    assert!(
        got.len() < LEN,
        "the whole {LEN}-byte answer arrived: the stalled client was never dropped"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn errors_have_the_json_body_and_the_bearer_scheme_is_case_insensitive() {
    let (addr, _dir) = start(Some("s3cret"), ServerLimits::default()).await;
    let auth = "Authorization: bearer s3cret\r\n";
    let (s, head, body) = exchange(&addr, &get("/v1/scenes", auth)).await;
    assert_eq!(s, 200, "{head}{body}");
    let (s, _, _) = exchange(
        &addr,
        &get("/v1/scenes", "Authorization: BEARER s3cret\r\n"),
    )
    .await;
    assert_eq!(s, 200);
    let (s, head, body) = exchange(
        &addr,
        format!("POST /v1/scenes HTTP/1.1\r\nHost: x\r\nConnection: close\r\n{auth}Content-Length: 0\r\n\r\n")
            .as_bytes(),
    )
    .await;
    assert_eq!(s, 405, "{head}");
    assert_json_error(405, &head, &body);
    let (s, head, body) = exchange(&addr, &get(&format!("/v1/{}", "a".repeat(9000)), auth)).await;
    assert_eq!(s, 414, "{head}");
    assert_json_error(414, &head, &body);
    let pad = format!("{auth}X-Pad: {}\r\n", "p".repeat(20_000));
    let (s, head, body) = exchange(&addr, &get("/v1/scenes", &pad)).await;
    assert_eq!(s, 431, "{head}");
    assert_json_error(431, &head, &body);
    let (s, head, body) = exchange(&addr, &get("/v1/scenes/lab/codebook", auth)).await;
    assert_eq!(s, 404, "{head}");
    assert_json_error(404, &head, &body);
    // 416 keeps its Content-Range and gets the JSON body.
    let (_, _, m) = exchange(&addr, &get("/v1/scenes/lab/manifest", auth)).await;
    let m = slag_common::shards::Manifest::from_json(m.as_bytes(), "http").unwrap();
    let t = &m.tiles[0];
    let range = format!("{auth}Range: bytes={}-\r\n", t.bytes);
    let (s, head, body) = exchange(
        &addr,
        &get(&format!("/v1/scenes/lab/shards/{}", t.id), &range),
    )
    .await;
    assert_eq!(s, 416, "{head}");
    assert!(
        head.to_ascii_lowercase()
            .contains(&format!("content-range: bytes */{}", t.bytes)),
        "{head}"
    );
    assert_json_error(416, &head, &body);
}

#[test]
fn a_blank_shard_token_in_the_environment_refuses_to_start() {
    let dir = tempfile::tempdir().unwrap();
    for blank in ["", "  \t"] {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_slag-shards"))
            .args(["serve", "--bind", "127.0.0.1:0", "--store"])
            .arg(dir.path())
            .env("SLAG_SHARD_TOKEN", blank)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "started with a blank token: {err}");
        assert!(
            err.contains("SLAG_SHARD_TOKEN") && err.contains("blank"),
            "{err}"
        );
        assert!(err.contains("hint:"), "{err}");
    }
}
