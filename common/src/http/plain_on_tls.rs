//! A plain-HTTP request on a TLS port (module doc of [`super`], "TLS"): instead of a failed
//! handshake the client cannot read, it gets a plain `HTTP/1.1 400` whose JSON body names the
//! fix (`use https://HOST/PATH`), and the server logs the request at warn level.
//!
//! A TLS connection opens with a record whose first byte is its content type (a ClientHello is a
//! handshake record, 22); an HTTP/1 request opens with its method, a token of capital letters.
//! So the first byte, peeked without being consumed, tells them apart, and a TLS client's
//! handshake is not touched.

use std::net::SocketAddr;
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::time::Instant;

/// Most bytes of a plain request's head read for its request line and `Host` (the answer does
/// not need more; the rest is drained at close).
const HEAD_BYTES: usize = 8 * 1024;
/// Longest host and path echoed in the answer and the log (longer: the generic advice).
const ECHO_BYTES: usize = 256;

/// Whether a connection to a TLS port whose first byte is `first` speaks plain HTTP/1 (a method
/// token: `GET`, `POST`, …) rather than TLS (a record type byte, 20–24).
pub(super) fn is_plain_http(first: u8) -> bool {
    first.is_ascii_uppercase()
}

/// The request line's method and path (without its query) and the `Host` header of a plain
/// HTTP request head `head` (possibly cut short), each when present and printable.
fn request_of(head: &[u8]) -> (Option<String>, Option<String>, Option<String>) {
    let text = String::from_utf8_lossy(head);
    let mut lines = text.split("\r\n");
    let mut first = lines.next().unwrap_or("").split(' ');
    let printable = |s: &str| {
        (!s.is_empty() && s.len() <= ECHO_BYTES && s.bytes().all(|b| b.is_ascii_graphic()))
            .then(|| s.to_string())
    };
    let method = first.next().and_then(printable);
    let path = first
        .next()
        .and_then(|t| t.split('?').next())
        .filter(|p| p.starts_with('/'))
        .and_then(printable);
    let host = lines
        .take_while(|l| !l.is_empty())
        .find_map(|l| {
            let (name, value) = l.split_once(':')?;
            name.eq_ignore_ascii_case("host").then(|| value.trim())
        })
        .filter(|h| {
            h.bytes()
                .all(|b| b.is_ascii_alphanumeric() || b".-:[]".contains(&b))
        })
        .and_then(printable);
    (method, path, host)
}

/// The advice of the answer: `use https://HOST/PATH` when the request named its host, otherwise
/// the scheme to change.
fn advice(host: Option<&str>, path: Option<&str>) -> String {
    match host {
        Some(h) => format!(
            "this port speaks HTTPS (TLS), not plain HTTP: use https://{h}{}",
            path.unwrap_or("/")
        ),
        None => "this port speaks HTTPS (TLS), not plain HTTP: use https:// instead of http:// \
                 in the URL"
            .to_string(),
    }
}

/// The whole 400 answer on the wire for `message` (JSON error body, `Connection: close`).
fn answer_bytes(message: &str) -> String {
    let body = serde_json::json!({ "error": message, "status": 400 }).to_string();
    format!(
        "HTTP/1.1 400 Bad Request\r\ncontent-type: application/json\r\ncontent-length: {}\r\n\
         connection: close\r\n\r\n{body}",
        body.len()
    )
}

/// Answers the plain-HTTP request on `stream` (from `peer`) and closes it: its head read until
/// `deadline` (at most [`HEAD_BYTES`]), the 400 of [`advice`] written within `write_timeout`,
/// the line logged, then what the client still sends drained briefly, so that closing sends FIN
/// rather than a reset that could discard the answer.
pub(super) async fn answer(
    mut stream: tokio::net::TcpStream,
    peer: SocketAddr,
    deadline: Instant,
    write_timeout: Duration,
) {
    let mut head = Vec::with_capacity(1024);
    let _ = tokio::time::timeout_at(deadline, async {
        let mut buf = [0u8; 1024];
        while head.len() < HEAD_BYTES && !head.windows(4).any(|w| w == b"\r\n\r\n") {
            match stream.read(&mut buf).await {
                Ok(n) if n > 0 => head.extend_from_slice(&buf[..n]),
                _ => break,
            }
        }
    })
    .await;
    let (method, path, host) = request_of(&head);
    let message = advice(host.as_deref(), path.as_deref());
    let _ = tokio::time::timeout(write_timeout, async {
        stream.write_all(answer_bytes(&message).as_bytes()).await?;
        stream.shutdown().await
    })
    .await;
    tracing::warn!(
        "connection {peer}: a plain HTTP request ({} {}) on this HTTPS port, answered 400: the \
         client must use https://",
        method.as_deref().unwrap_or("?"),
        path.as_deref().unwrap_or("?"),
    );
    let mut sink = [0u8; 4096];
    let _ = tokio::time::timeout(Duration::from_millis(200), async {
        while matches!(stream.read(&mut sink).await, Ok(n) if n > 0) {}
    })
    .await;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tls_records_and_http_methods_are_told_apart() {
        for tls in [20u8, 21, 22, 23, 24] {
            assert!(!is_plain_http(tls), "{tls}");
        }
        for m in [
            "GET", "POST", "HEAD", "PUT", "DELETE", "OPTIONS", "PATCH", "CONNECT",
        ] {
            assert!(is_plain_http(m.as_bytes()[0]), "{m}");
        }
    }

    #[test]
    fn the_advice_names_the_https_url_of_the_request() {
        let head = b"GET /query?text=chair HTTP/1.1\r\nhost: 10.0.0.2:8080\r\naccept: */*\r\n\r\n";
        let (m, p, h) = request_of(head);
        assert_eq!(
            (m.as_deref(), p.as_deref(), h.as_deref()),
            (Some("GET"), Some("/query"), Some("10.0.0.2:8080"))
        );
        let a = advice(h.as_deref(), p.as_deref());
        assert!(a.ends_with("use https://10.0.0.2:8080/query"), "{a}");
        // A host that is no host name is not echoed; a head cut short still answers.
        let (_, p, h) = request_of(b"GET / HTTP/1.1\r\nHost: a\"b\r\n\r\n");
        assert_eq!(h, None);
        assert!(advice(h.as_deref(), p.as_deref()).contains("use https:// instead of http://"));
        assert_eq!(request_of(b"GE"), (Some("GE".into()), None, None));
        let wire = answer_bytes("x \"y\"");
        assert!(wire.starts_with("HTTP/1.1 400 Bad Request\r\n"), "{wire}");
        assert!(
            wire.ends_with(r#"{"error":"x \"y\"","status":400}"#),
            "{wire}"
        );
    }
}
