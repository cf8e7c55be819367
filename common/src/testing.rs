//! Raw-socket clients for the integration tests of the HTTP servers (`slag-edge serve`, the shard
//! server): one request on a fresh connection, the JSON error body, and waiting for the server
//! to close a connection. Behind the `testing` feature, which only dev-dependencies turn on;
//! these helpers panic (with what went wrong) instead of returning errors.

use std::time::{Duration, Instant};

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// Sends `raw` on a fresh connection to `addr` (`host:port`) and reads until the server closes
/// it (at most 30 s): (status, head, body). Status 0 when the answer has no status line.
///
/// Panics when the connection fails or stays open for 30 s.
pub async fn exchange(addr: &str, raw: &[u8]) -> (u16, String, String) {
    let mut s = TcpStream::connect(addr).await.expect("connect");
    s.write_all(raw).await.expect("send the request");
    read_answer(&mut s).await
}

/// [`exchange`] from the local address `source` (another loopback address such as 127.0.0.2 is
/// another client to the server's per-address share).
///
/// Panics as [`exchange`].
pub async fn exchange_from(
    source: std::net::IpAddr,
    addr: &str,
    raw: &[u8],
) -> (u16, String, String) {
    let mut s = connect_from(source, addr).await;
    s.write_all(raw).await.expect("send the request");
    read_answer(&mut s).await
}

/// A connection to `addr` (`ip:port`) from the local address `source` (any port).
///
/// Panics when `addr` is not `ip:port` or the connection fails.
pub async fn connect_from(source: std::net::IpAddr, addr: &str) -> TcpStream {
    let to: std::net::SocketAddr = addr.parse().expect("addr is ip:port");
    let sock = if source.is_ipv4() {
        tokio::net::TcpSocket::new_v4()
    } else {
        tokio::net::TcpSocket::new_v6()
    }
    .expect("socket");
    sock.bind(std::net::SocketAddr::new(source, 0))
        .expect("bind the source address");
    sock.connect(to).await.expect("connect")
}

/// Reads an answer until the server closes `s` (at most 30 s): (status, head, body). Status 0
/// when the answer has no status line.
///
/// Panics when the read fails or the connection stays open for 30 s.
pub async fn read_answer(s: &mut TcpStream) -> (u16, String, String) {
    let mut out = Vec::new();
    tokio::time::timeout(Duration::from_secs(30), s.read_to_end(&mut out))
        .await
        .expect("the server answers and closes within 30 s")
        .expect("read the answer");
    let text = String::from_utf8_lossy(&out).into_owned();
    let (head, body) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
    let status = head.split(' ').nth(1).unwrap_or("0").parse().unwrap_or(0);
    (status, head.to_string(), body.to_string())
}

/// An HTTP/1.1 `GET path` that asks the server to close the connection after its answer;
/// `extra` is more header lines, each ending in `\r\n`.
pub fn get_request(path: &str, extra: &str) -> Vec<u8> {
    format!("GET {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n{extra}\r\n").into_bytes()
}

/// Asserts that an answer is the servers' JSON error body with `status`: a JSON content type,
/// `"status": status` and a non-empty `"error"`.
pub fn assert_json_error(status: u16, head: &str, body: &str) {
    assert!(
        head.to_ascii_lowercase()
            .contains("content-type: application/json"),
        "{status}: {head}"
    );
    let v: serde_json::Value = serde_json::from_str(body).unwrap_or_else(|e| panic!("{e}: {body}"));
    assert_eq!(v["status"], status, "{v}");
    assert!(v["error"].as_str().is_some_and(|e| !e.is_empty()), "{v}");
}

/// Waits (at most `bound`) until the server closes `s`, reading and dropping what it sends;
/// returns how long that took. Panics when the connection is still open after `bound`.
pub async fn closed_within(s: &mut TcpStream, bound: Duration) -> Duration {
    let t0 = Instant::now();
    let mut buf = [0u8; 4096];
    loop {
        match tokio::time::timeout(bound.saturating_sub(t0.elapsed()), s.read(&mut buf)).await {
            Ok(Ok(0) | Err(_)) => return t0.elapsed(),
            Ok(Ok(_)) => {}
            Err(_) => panic!("the connection is still open after {bound:?}"),
        }
    }
}
