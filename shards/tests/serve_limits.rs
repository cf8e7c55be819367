//! The shard server against hostile clients: stalled and idle sockets closed within the header
//! timeout, a client that stops reading dropped after the write timeout, the connection limit,
//! JSON error bodies for 405 / 414 / 431 / 416, the bearer scheme in any case, and a blank
//! `SLAG_SHARD_TOKEN` refused at start-up.
#![allow(clippy::unwrap_used)]

mod support;

use std::time::Duration;

use slag_common::http::ServerLimits;
use slag_common::testing::{
    assert_answered_while_stalled, assert_blank_token_refused, assert_json_error, closed_within,
    exchange, exchange_error, flood_from_one_address, get_request as get,
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
    assert_answered_while_stalled(&addr, 24, "/v1/scenes", "lab").await;
    closed_within(&mut idle, Duration::from_secs(30)).await;
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
    flood_from_one_address(&addr, 16, b"GET /v1/scenes HTTP/1.1\r\n", "/v1/scenes").await;
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
    let post = format!(
        "POST /v1/scenes HTTP/1.1\r\nHost: x\r\nConnection: close\r\n{auth}Content-Length: 0\r\n\r\n"
    );
    exchange_error(&addr, post.as_bytes(), 405).await;
    exchange_error(&addr, &get(&format!("/v1/{}", "a".repeat(9000)), auth), 414).await;
    let pad = format!("{auth}X-Pad: {}\r\n", "p".repeat(20_000));
    exchange_error(&addr, &get("/v1/scenes", &pad), 431).await;
    exchange_error(&addr, &get("/v1/scenes/lab/codebook", auth), 404).await;
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
            .args(["serve", "--listen", "127.0.0.1:0", "--shard-store"])
            .arg(dir.path())
            .env("SLAG_SHARD_TOKEN", blank)
            .output()
            .unwrap();
        assert_blank_token_refused(&out, "SLAG_SHARD_TOKEN");
    }
}
