//! The HTTP/1.1 server loop of both servers (`slag-edge serve`, `slag-shards serve`), with
//! their connection limits and timeouts, and the JSON error body every answer of theirs uses
//! (behind the cargo feature `server`).
//!
//! # Timeouts and limits ([`ServerLimits`])
//!
//! - **Header-read timeout** ([`ServerLimits::header_timeout`], default
//!   [`DEFAULT_HEADER_TIMEOUT`]): hyper's own `header_read_timeout`. A connection that has not
//!   sent a whole request head within it is closed. hyper starts the same timer when a kept-alive
//!   connection goes idle after an answer, so it is also the **idle keep-alive timeout**: an idle
//!   connection is closed after it.
//! - **Write timeout** ([`ServerLimits::write_timeout`], default [`DEFAULT_WRITE_TIMEOUT`]): a
//!   write to the socket that cannot make progress for this long (a client that stopped reading
//!   its answer) closes the connection and frees the answer (`tokio-io-timeout`).
//! - **Connection limit** ([`ServerLimits::max_connections`], default
//!   [`DEFAULT_MAX_CONNECTIONS`]): at most this many connections are open; the next one waits in
//!   the kernel's listen queue until one closes (it is not accepted, so it holds no descriptor of
//!   this process). [`check_connection_limit`] keeps the limit [`FD_HEADROOM`] descriptors below
//!   the process's open-file limit (`ulimit -n`, systemd's `LimitNOFILE`), clamping it with a
//!   warning where it is not.
//! - **Request line and headers**: a request whose target is longer than [`MAX_URI_BYTES`] gets
//!   414 and one whose header block is larger than [`MAX_HEADER_BYTES`] gets 431, both with the
//!   JSON body. Beyond hyper's own parser limits (a target over 64 KiB, more than 100 headers)
//!   hyper answers 414 / 431 itself, with an empty body, before any handler runs.
//!
//! # Error bodies
//!
//! Every error answer is `{"error": message, "status": code}` with `Content-Type:
//! application/json` ([`error_response`]). [`json_errors`] adds the layers that make it so for the
//! answers axum and tower-http produce themselves (405 with `Allow`, 408, 413, 416, 414, 431).

use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use axum::Router;
use axum::extract::Request;
use axum::http::{HeaderValue, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;

use crate::{Error, Result};

/// Default header-read (and idle keep-alive) timeout: 10 s.
pub const DEFAULT_HEADER_TIMEOUT: Duration = Duration::from_secs(10);
/// Default write timeout: 30 s without progress on a socket write.
pub const DEFAULT_WRITE_TIMEOUT: Duration = Duration::from_secs(30);
/// Default connection limit: 512 open connections.
pub const DEFAULT_MAX_CONNECTIONS: usize = 512;
/// Descriptors kept free for the process's own files (store, database, model, logs) below the
/// open-file limit: the connection limit must be at most `RLIMIT_NOFILE − FD_HEADROOM`.
pub const FD_HEADROOM: u64 = 64;
/// Longest request target (path and query) answered; longer gets 414: 8 KiB.
pub const MAX_URI_BYTES: usize = 8 * 1024;
/// Largest header block (names and values) answered; larger gets 431: 16 KiB.
pub const MAX_HEADER_BYTES: usize = 16 * 1024;

/// Timeouts and limits of one server (module doc).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ServerLimits {
    /// Time a connection has to send a whole request head, also the idle keep-alive timeout.
    pub header_timeout: Duration,
    /// Time a socket write may make no progress before the connection is closed.
    pub write_timeout: Duration,
    /// Connections open at once (≥ 1).
    pub max_connections: usize,
}

impl Default for ServerLimits {
    fn default() -> Self {
        ServerLimits {
            header_timeout: DEFAULT_HEADER_TIMEOUT,
            write_timeout: DEFAULT_WRITE_TIMEOUT,
            max_connections: DEFAULT_MAX_CONNECTIONS,
        }
    }
}

impl ServerLimits {
    /// Checks the settings.
    ///
    /// Errors: [`Error::Param`] `header_timeout` / `write_timeout` of zero, `max_connections`
    /// of zero.
    pub fn validate(&self) -> Result<()> {
        if self.header_timeout.is_zero() {
            return Err(Error::param("header_timeout", "0", "a duration > 0 s"));
        }
        if self.write_timeout.is_zero() {
            return Err(Error::param("write_timeout", "0", "a duration > 0 s"));
        }
        if self.max_connections == 0 {
            return Err(Error::param("max_connections", 0, "at least 1"));
        }
        Ok(())
    }
}

/// The process's soft open-file limit (`RLIMIT_NOFILE`, from `/proc/self/limits`); `None`
/// where it cannot be read (not Linux) or is unlimited.
pub fn open_files_limit() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/limits").ok()?;
    let line = s.lines().find(|l| l.starts_with("Max open files"))?;
    line.split_whitespace().nth(3)?.parse().ok()
}

/// The connection limit to use under an open-file limit of `nofile` descriptors (`None`:
/// unknown, `limits.max_connections` is kept): `max_connections` when it is at most
/// `nofile − FD_HEADROOM`, else that bound, with a warning naming both (clamped, so that
/// accepting connections can never exhaust the descriptors the process needs for itself).
///
/// Errors: [`Error::Param`] `max_connections` when the open-file limit leaves fewer than 16
/// connections (raise `ulimit -n` / `LimitNOFILE`).
pub fn check_connection_limit(
    limits: ServerLimits,
    nofile: Option<u64>,
) -> Result<(ServerLimits, Option<String>)> {
    limits.validate()?;
    let Some(nofile) = nofile else {
        return Ok((limits, None));
    };
    let room = nofile.saturating_sub(FD_HEADROOM);
    if room < 16 {
        return Err(Error::param(
            "max_connections",
            limits.max_connections,
            format!(
                "a connection limit below the open-file limit ({nofile}) minus {FD_HEADROOM} \
                 descriptors of headroom, which leaves {room}; raise the open-file limit \
                 (ulimit -n, or LimitNOFILE in the systemd unit) to at least {}",
                limits.max_connections as u64 + FD_HEADROOM
            ),
        ));
    }
    if limits.max_connections as u64 <= room {
        return Ok((limits, None));
    }
    let clamped = ServerLimits {
        max_connections: room as usize,
        ..limits
    };
    let warning = format!(
        "connection limit {} lowered to {room}: the open-file limit is {nofile} and {FD_HEADROOM} \
         descriptors are kept for the process's own files; raise the open-file limit (ulimit -n, \
         LimitNOFILE) to {} to keep {}",
        limits.max_connections,
        limits.max_connections as u64 + FD_HEADROOM,
        limits.max_connections
    );
    Ok((clamped, Some(warning)))
}

/// Serves `router` on `listener` under `limits` until `shutdown` completes, then lets open
/// connections finish their request (idle ones close at once).
///
/// The connection limit is applied as given: check it first with [`check_connection_limit`].
/// Errors on accepting a connection (a peer that reset, the rare descriptor shortage) are logged
/// and the loop goes on after a short pause; the function itself does not fail.
pub async fn serve(
    listener: tokio::net::TcpListener,
    router: Router,
    limits: ServerLimits,
    shutdown: impl Future<Output = ()> + Send,
) {
    let permits = Arc::new(tokio::sync::Semaphore::new(limits.max_connections.max(1)));
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let mut shutdown = std::pin::pin!(shutdown);
    loop {
        // A free connection slot first: at the limit the next connection stays in the kernel's
        // listen queue, holding no descriptor of ours.
        let permit = tokio::select! {
            p = permits.clone().acquire_owned() => match p {
                Ok(p) => p,
                Err(_) => break,
            },
            () = &mut shutdown => break,
        };
        let (stream, peer) = tokio::select! {
            a = listener.accept() => match a {
                Ok(a) => a,
                Err(e) => {
                    accept_error(&e).await;
                    continue;
                }
            },
            () = &mut shutdown => break,
        };
        let router = router.clone();
        let mut stop = stop_rx.clone();
        tokio::spawn(async move {
            let _permit = permit;
            serve_connection(stream, peer, router, limits, &mut stop).await;
        });
    }
    drop(listener);
    let _ = stop_tx.send(true);
    // Every connection task holds a permit: when all are back, every connection has closed.
    let _ = permits
        .acquire_many(limits.max_connections.max(1) as u32)
        .await;
}

async fn accept_error(e: &std::io::Error) {
    use std::io::ErrorKind::*;
    if matches!(
        e.kind(),
        ConnectionRefused | ConnectionAborted | ConnectionReset
    ) {
        return;
    }
    tracing::warn!("accept: {e}");
    tokio::time::sleep(Duration::from_millis(100)).await;
}

async fn serve_connection(
    stream: tokio::net::TcpStream,
    peer: SocketAddr,
    router: Router,
    limits: ServerLimits,
    stop: &mut tokio::sync::watch::Receiver<bool>,
) {
    let _ = stream.set_nodelay(true);
    let mut io = tokio_io_timeout::TimeoutStream::new(stream);
    io.set_write_timeout(Some(limits.write_timeout));
    let io = TokioIo::new(Box::pin(io));
    let service = TowerToHyperService::new(router);
    let mut builder = hyper::server::conn::http1::Builder::new();
    builder
        .timer(TokioTimer::new())
        .header_read_timeout(limits.header_timeout)
        .keep_alive(true);
    let conn = builder.serve_connection(io, service);
    let mut conn = std::pin::pin!(conn);
    let mut stopping = *stop.borrow();
    if stopping {
        conn.as_mut().graceful_shutdown();
    }
    loop {
        tokio::select! {
            r = conn.as_mut() => {
                if let Err(e) = r {
                    tracing::debug!("connection {peer}: {e}");
                }
                break;
            }
            changed = stop.changed(), if !stopping => {
                if changed.is_err() || *stop.borrow() {
                    stopping = true;
                    conn.as_mut().graceful_shutdown();
                }
            }
        }
    }
}

/// The JSON error answer: `{"error": message, "status": code}`, `Content-Type:
/// application/json`.
pub fn error_response(status: StatusCode, message: impl Into<String>) -> Response {
    let body = serde_json::json!({ "error": message.into(), "status": status.as_u16() });
    (
        status,
        [(header::CONTENT_TYPE, "application/json")],
        body.to_string(),
    )
        .into_response()
}

/// `router` with the layers that give every error answer the JSON body (module doc): a
/// method-not-allowed fallback (405 naming the allowed methods), 414 / 431 for an overlong
/// target or header block, and a response mapper that gives any other error answer without a
/// JSON body (tower-http's 408 and 413, a 416) one, keeping its headers. Add it last (outermost).
pub fn json_errors(router: Router) -> Router {
    router
        .layer(axum::middleware::map_response(json_error_body))
        .layer(axum::middleware::from_fn(head_limits))
}

async fn head_limits(req: Request, next: Next) -> Response {
    let target = req.uri().path_and_query().map_or(0, |p| p.as_str().len());
    if target > MAX_URI_BYTES {
        return error_response(
            StatusCode::URI_TOO_LONG,
            format!(
                "request target of {target} bytes; at most {MAX_URI_BYTES}: send long queries \
                 as POST /query with a JSON body"
            ),
        );
    }
    let head: usize = req
        .headers()
        .iter()
        .map(|(k, v)| k.as_str().len() + v.len() + 4)
        .sum();
    if head > MAX_HEADER_BYTES {
        return error_response(
            StatusCode::REQUEST_HEADER_FIELDS_TOO_LARGE,
            format!("request headers of {head} bytes; at most {MAX_HEADER_BYTES}"),
        );
    }
    next.run(req).await
}

/// The value of header `name` of `r` as text; empty when absent or not visible ASCII.
fn header_text(r: &Response, name: header::HeaderName) -> &str {
    r.headers()
        .get(name)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
}

async fn json_error_body(r: Response) -> Response {
    let status = r.status();
    if !(status.is_client_error() || status.is_server_error()) {
        return r;
    }
    let is_json = header_text(&r, header::CONTENT_TYPE).starts_with("application/json");
    if is_json {
        return r;
    }
    let message = match status {
        StatusCode::METHOD_NOT_ALLOWED => {
            let allow = header_text(&r, header::ALLOW);
            format!("method not allowed on this route; use {allow}")
        }
        StatusCode::REQUEST_TIMEOUT => {
            "the request took longer than the server's request timeout; retry later, or ask \
             for less (fewer queries, a smaller top_k)"
                .to_string()
        }
        StatusCode::PAYLOAD_TOO_LARGE => {
            "request body too large; send a smaller body (fewer queries per batch)".to_string()
        }
        StatusCode::RANGE_NOT_SATISFIABLE => {
            let range = header_text(&r, header::CONTENT_RANGE);
            format!("range not satisfiable ({range}); ask for bytes within the file's length")
        }
        s => s.canonical_reason().unwrap_or("error").to_string(),
    };
    let (mut parts, _) = r.into_parts();
    let body = serde_json::json!({ "error": message, "status": status.as_u16() }).to_string();
    parts.headers.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/json"),
    );
    parts.headers.remove(header::CONTENT_LENGTH);
    Response::from_parts(parts, axum::body::Body::from(body))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn the_connection_limit_stays_below_the_open_file_limit() {
        let l = ServerLimits::default();
        assert_eq!(check_connection_limit(l, None).unwrap(), (l, None));
        assert_eq!(check_connection_limit(l, Some(4096)).unwrap(), (l, None));
        let (c, w) = check_connection_limit(l, Some(256)).unwrap();
        assert_eq!(c.max_connections, 256 - FD_HEADROOM as usize);
        let w = w.unwrap();
        assert!(w.contains("LimitNOFILE") && w.contains("256"), "{w}");
        let e = check_connection_limit(l, Some(70)).unwrap_err();
        assert!(
            matches!(
                e,
                Error::Param {
                    name: "max_connections",
                    ..
                }
            ),
            "{e}"
        );
        let zero = ServerLimits {
            max_connections: 0,
            ..l
        };
        assert!(check_connection_limit(zero, None).is_err());
    }

    #[test]
    fn the_open_file_limit_is_read_on_linux() {
        if cfg!(target_os = "linux") {
            assert!(open_files_limit().is_some_and(|n| n > 0));
        }
    }
}
