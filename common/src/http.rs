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
//! - **Body-read timeout** ([`ServerLimits::body_timeout`], default [`DEFAULT_BODY_TIMEOUT`]):
//!   the whole request body must arrive within this time of the request head, at the header
//!   timeout's pace (a deadline, not a per-read timer, so a body sent one byte at a time cannot
//!   stretch it). A body still incomplete at the deadline fails the request: the answer is 408
//!   with the JSON body and `Connection: close`, and the connection closes, freeing its slot.
//!   A request the handler answers without reading its body does not wait for the body either:
//!   hyper closes the connection after the answer instead of draining a stalled body.
//! - **Connection limit** ([`ServerLimits::max_connections`], default
//!   [`DEFAULT_MAX_CONNECTIONS`]): at most this many connections are open; the next one waits in
//!   the kernel's listen queue until one closes (it is not accepted, so it holds no descriptor of
//!   this process). [`check_connection_limit`] keeps the limit [`FD_HEADROOM`] descriptors below
//!   the process's open-file limit (`ulimit -n`, systemd's `LimitNOFILE`), clamping it with a
//!   warning where it is not.
//! - **Share of one remote address** ([`ServerLimits::max_connections_per_ip`], default
//!   [`DEFAULT_MAX_CONNECTIONS_PER_IP`]): at most this many of the connection slots are held by
//!   one remote address (an IPv4 address, or an IPv6 /64 prefix, which one host usually holds
//!   whole: [`address_key`]). One more connection from that address is accepted, answered **429
//!   Too Many Requests** with `Retry-After: 1` and the JSON body, and closed at once, so one
//!   client that floods the server with stalled sockets cannot take the slots of the others.
//!   The share is checked after `accept` (the address is not known before), so the refused
//!   connection costs one descriptor for the time of one write. Clients behind one NAT address
//!   share one share: raise the setting for such a site.
//! - **Request line and headers**: a request whose target is longer than [`MAX_URI_BYTES`] gets
//!   414 and one whose header block is larger than [`MAX_HEADER_BYTES`] gets 431, both with the
//!   JSON body. Beyond hyper's own parser limits (a target over 64 KiB, more than 100 headers)
//!   hyper answers 414 / 431 itself, with an empty body, before any handler runs.
//!
//! # TLS
//!
//! [`serve_with_tls`] with a [`ServerTls`] speaks HTTPS (module [`crate::tls`]) on the same loop:
//! the connection limit, the per-address share, the header-read, body and write timeouts all hold
//! for TLS connections. The TLS handshake must end within the header-read timeout (a deadline: a
//! client that stalls its handshake, or sends it one byte at a time, is closed then and frees
//! its slot), and the request head then has the header-read timeout again. A connection over its
//! address's share gets its 429 over TLS: the refusal runs the handshake (under the same
//! deadline) in one of at most [`TLS_REFUSALS`] refusal slots of its own, apart from the
//! connection slots; when all are busy the connection is closed without an answer. SIGHUP reads
//! the certificate and key files again ([`crate::tls::reload_on_hangup`]). A plain-HTTP request
//! on a TLS port is answered a plain `400` whose body names the `https://` URL to use, and
//! logged at warn level (module `plain_on_tls`).
//!
//! # Error bodies
//!
//! Every error answer is `{"error": message, "status": code}` with `Content-Type:
//! application/json` ([`error_response`]). [`json_errors`] adds the layers that make it so for the
//! answers axum and tower-http produce themselves (405 with `Allow`, 408, 413, 416, 414, 431).

use std::collections::HashMap;
use std::future::Future;
use std::net::{IpAddr, Ipv6Addr, SocketAddr};
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;

use axum::Router;
use axum::extract::Request;
use axum::http::{HeaderValue, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;

use crate::tls::ServerTls;
use crate::{Error, Result};

mod plain_on_tls;

/// Default header-read (and idle keep-alive) timeout: 10 s.
pub const DEFAULT_HEADER_TIMEOUT: Duration = Duration::from_secs(10);
/// Default write timeout: 30 s without progress on a socket write.
pub const DEFAULT_WRITE_TIMEOUT: Duration = Duration::from_secs(30);
/// Default body-read timeout: 10 s from the request head to the end of its body, the header
/// timeout's pace.
pub const DEFAULT_BODY_TIMEOUT: Duration = Duration::from_secs(10);
/// Default connection limit: 512 open connections.
pub const DEFAULT_MAX_CONNECTIONS: usize = 512;
/// Default share of the connection slots one remote address may hold: 64 (an eighth of
/// [`DEFAULT_MAX_CONNECTIONS`]; a browser opens 6, a robot's nodes a handful).
pub const DEFAULT_MAX_CONNECTIONS_PER_IP: usize = 64;
/// Descriptors kept free for the process's own files (store, database, model, logs) below the
/// open-file limit: the connection limit must be at most `RLIMIT_NOFILE − FD_HEADROOM`.
pub const FD_HEADROOM: u64 = 64;
/// TLS connections over their address's share that may be in their refusal (handshake, 429,
/// close) at once (module doc, "TLS"); these hold descriptors of the [`FD_HEADROOM`].
pub const TLS_REFUSALS: usize = 16;
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
    /// Time from the end of a request head to the end of its body; a body still incomplete
    /// then gets 408 and its connection is closed.
    pub body_timeout: Duration,
    /// Connections open at once (≥ 1).
    pub max_connections: usize,
    /// Connections one remote address ([`address_key`]) may hold at once (≥ 1; at most
    /// `max_connections` is used); one more is answered 429 and closed.
    pub max_connections_per_ip: usize,
}

impl Default for ServerLimits {
    fn default() -> Self {
        ServerLimits {
            header_timeout: DEFAULT_HEADER_TIMEOUT,
            write_timeout: DEFAULT_WRITE_TIMEOUT,
            body_timeout: DEFAULT_BODY_TIMEOUT,
            max_connections: DEFAULT_MAX_CONNECTIONS,
            max_connections_per_ip: DEFAULT_MAX_CONNECTIONS_PER_IP,
        }
    }
}

impl ServerLimits {
    /// Checks the settings.
    ///
    /// Errors: [`Error::Param`] `header_timeout` / `write_timeout` / `body_timeout` of zero,
    /// `max_connections` / `max_connections_per_ip` of zero.
    pub fn validate(&self) -> Result<()> {
        for (name, t) in [
            ("header_timeout", self.header_timeout),
            ("write_timeout", self.write_timeout),
            ("body_timeout", self.body_timeout),
        ] {
            if t.is_zero() {
                return Err(Error::param(name, "0", "a duration > 0 s"));
            }
        }
        if self.max_connections == 0 {
            return Err(Error::param("max_connections", 0, "at least 1"));
        }
        if self.max_connections_per_ip == 0 {
            return Err(Error::param("max_connections_per_ip", 0, "at least 1"));
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
/// connections finish their request (idle ones close at once). Plain HTTP: [`serve_with_tls`]
/// without TLS.
pub async fn serve(
    listener: tokio::net::TcpListener,
    router: Router,
    limits: ServerLimits,
    shutdown: impl Future<Output = ()> + Send,
) {
    serve_with_tls(listener, router, limits, None, shutdown).await;
}

/// Serves `router` on `listener` under `limits`, over TLS with `tls` (module doc, "TLS"), until
/// `shutdown` completes, then lets open connections finish their request (idle ones close at
/// once). With `tls`, `SIGHUP` reloads its certificate while the loop runs.
///
/// The connection limit is applied as given: check it first with [`check_connection_limit`].
/// Each remote address holds at most `max_connections_per_ip` of its slots (one more connection
/// from it is answered 429 and closed), and every request body must end within `body_timeout`
/// of its head (module doc). Errors on accepting a connection (a peer that reset, the rare
/// descriptor shortage) are logged and the loop goes on after a short pause; a failed TLS
/// handshake closes its connection (logged at debug level); the function itself does not fail.
pub async fn serve_with_tls(
    listener: tokio::net::TcpListener,
    router: Router,
    limits: ServerLimits,
    tls: Option<Arc<ServerTls>>,
    shutdown: impl Future<Output = ()> + Send,
) {
    let permits = Arc::new(tokio::sync::Semaphore::new(limits.max_connections.max(1)));
    let refusals = Arc::new(tokio::sync::Semaphore::new(TLS_REFUSALS));
    let shares = Arc::new(AddressShares::new(
        limits.max_connections_per_ip.min(limits.max_connections),
    ));
    let router = with_body_deadline(router, limits.body_timeout);
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    if let Some(t) = &tls {
        let mut stop = stop_rx.clone();
        crate::tls::reload_on_hangup(t.clone(), async move {
            let _ = stop.wait_for(|s| *s).await;
        });
    }
    let acceptor = tls.as_ref().map(|t| t.acceptor());
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
        let Some(share) = shares.open(peer.ip()) else {
            match &acceptor {
                None => refuse_over_share(&stream, peer, shares.max),
                Some(a) => refuse_over_share_tls(stream, peer, shares.max, a, &refusals, limits),
            }
            continue;
        };
        let router = router.clone();
        let mut stop = stop_rx.clone();
        let acceptor = acceptor.clone();
        tokio::spawn(async move {
            let _permit = permit;
            let _share = share;
            match acceptor {
                None => {
                    let io = timed(stream, limits);
                    serve_connection(io, peer, router, limits, &mut stop).await;
                }
                Some(a) => {
                    if let Some(io) = handshake(&a, stream, peer, limits).await {
                        serve_connection(io, peer, router, limits, &mut stop).await;
                    }
                }
            }
        });
    }
    drop(listener);
    let _ = stop_tx.send(true);
    // Every connection task holds a permit: when all are back, every connection has closed.
    let _ = permits
        .acquire_many(limits.max_connections.max(1) as u32)
        .await;
}

/// A connection's socket with the write timeout (module doc), no Nagle delay.
type Timed = Pin<Box<tokio_io_timeout::TimeoutStream<tokio::net::TcpStream>>>;

fn timed(stream: tokio::net::TcpStream, limits: ServerLimits) -> Timed {
    let _ = stream.set_nodelay(true);
    let mut io = tokio_io_timeout::TimeoutStream::new(stream);
    io.set_write_timeout(Some(limits.write_timeout));
    Box::pin(io)
}

/// The server side of a TLS handshake on `stream`, which must end within the header-read
/// timeout (a deadline); `None` (logged at debug level) when it fails or does not end in time.
/// A plain-HTTP request in place of the handshake is answered 400 naming `https://` instead
/// ([`plain_on_tls`]).
async fn handshake(
    acceptor: &tokio_rustls::TlsAcceptor,
    stream: tokio::net::TcpStream,
    peer: SocketAddr,
    limits: ServerLimits,
) -> Option<tokio_rustls::server::TlsStream<Timed>> {
    let deadline = tokio::time::Instant::now() + limits.header_timeout;
    let mut first = [0u8; 1];
    let accepted = match tokio::time::timeout_at(deadline, stream.peek(&mut first)).await {
        Ok(Ok(n)) if n > 0 && plain_on_tls::is_plain_http(first[0]) => {
            plain_on_tls::answer(stream, peer, deadline, limits.write_timeout).await;
            return None;
        }
        Ok(_) => tokio::time::timeout_at(deadline, acceptor.accept(timed(stream, limits))).await,
        Err(elapsed) => Err(elapsed),
    };
    match accepted {
        Ok(Ok(s)) => Some(s),
        Ok(Err(e)) => {
            tracing::debug!("connection {peer}: TLS handshake failed: {e}");
            None
        }
        Err(_) => {
            tracing::debug!(
                "connection {peer}: no TLS handshake within {} s",
                limits.header_timeout.as_secs_f64()
            );
            None
        }
    }
}

/// The key one remote address's share is counted under: an IPv4 address (an IPv4-mapped IPv6
/// address counts as its IPv4 address), or the /64 prefix of an IPv6 address (one host, or one
/// network's SLAAC addresses, usually holds a whole /64: counting single IPv6 addresses would
/// give it 2^64 shares).
pub fn address_key(ip: IpAddr) -> IpAddr {
    match ip.to_canonical() {
        IpAddr::V6(v6) => {
            let prefix = u128::from(v6) & !((1u128 << 64) - 1);
            IpAddr::V6(Ipv6Addr::from(prefix))
        }
        v4 => v4,
    }
}

/// Connections open per remote address ([`address_key`]), each at most `max`.
struct AddressShares {
    open: Mutex<HashMap<IpAddr, usize>>,
    max: usize,
}

/// One connection's place in its address's share; given back when dropped.
struct AddressShare {
    shares: Arc<AddressShares>,
    key: IpAddr,
}

impl AddressShares {
    fn new(max: usize) -> AddressShares {
        AddressShares {
            open: Mutex::new(HashMap::new()),
            max: max.max(1),
        }
    }

    /// A place for one more connection from `ip`; `None` when its address already holds `max`.
    fn open(self: &Arc<Self>, ip: IpAddr) -> Option<AddressShare> {
        let key = address_key(ip);
        let mut open = self.open.lock().unwrap_or_else(|p| p.into_inner());
        let n = open.entry(key).or_insert(0);
        if *n >= self.max {
            return None;
        }
        *n += 1;
        Some(AddressShare {
            shares: self.clone(),
            key,
        })
    }
}

impl Drop for AddressShare {
    fn drop(&mut self) {
        let mut open = self.shares.open.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(n) = open.get_mut(&self.key) {
            *n = n.saturating_sub(1);
            if *n == 0 {
                open.remove(&self.key);
            }
        }
    }
}

/// The 429 answer to a connection over its address's share (`Retry-After: 1`, the JSON body,
/// `Connection: close`), as bytes on the wire.
fn over_share_answer(peer: SocketAddr, max: usize) -> String {
    let status = StatusCode::TOO_MANY_REQUESTS;
    let body = serde_json::json!({
        "error": format!(
            "too many connections from {}: at most {max} at once per address; close idle \
             connections or reuse one (keep-alive), then retry",
            address_key(peer.ip())
        ),
        "status": status.as_u16(),
    })
    .to_string();
    format!(
        "HTTP/1.1 429 Too Many Requests\r\ncontent-type: application/json\r\n\
         content-length: {}\r\nretry-after: 1\r\nconnection: close\r\n\r\n{body}",
        body.len()
    )
}

/// Answers a connection over its address's share: [`over_share_answer`], written without waiting
/// (a full socket buffer drops the answer, not the loop), then the connection is closed as
/// `stream` drops.
fn refuse_over_share(stream: &tokio::net::TcpStream, peer: SocketAddr, max: usize) {
    let _ = stream.try_write(over_share_answer(peer, max).as_bytes());
    // What the client already sent is read and dropped, so that closing sends FIN rather than
    // a reset that could discard the answer before the client reads it.
    let mut sink = [0u8; 4096];
    for _ in 0..4 {
        if !matches!(stream.try_read(&mut sink), Ok(n) if n > 0) {
            break;
        }
    }
    tracing::debug!("connection {peer}: refused, its address holds {max} connections");
}

/// [`refuse_over_share`] over TLS (module doc, "TLS"): in a refusal slot of its own, the
/// handshake under the header-read deadline, the 429 under the write timeout, then close; with
/// no refusal slot free the connection is closed at once.
fn refuse_over_share_tls(
    stream: tokio::net::TcpStream,
    peer: SocketAddr,
    max: usize,
    acceptor: &tokio_rustls::TlsAcceptor,
    refusals: &Arc<tokio::sync::Semaphore>,
    limits: ServerLimits,
) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let Ok(slot) = refusals.clone().try_acquire_owned() else {
        tracing::debug!("connection {peer}: closed, its address holds {max} connections");
        return;
    };
    let acceptor = acceptor.clone();
    tokio::spawn(async move {
        let _slot = slot;
        let Some(mut tls) = handshake(&acceptor, stream, peer, limits).await else {
            return;
        };
        let answer = over_share_answer(peer, max);
        let _ = tokio::time::timeout(limits.write_timeout, async {
            tls.write_all(answer.as_bytes()).await?;
            tls.shutdown().await
        })
        .await;
        // As in `refuse_over_share`: read what the client sent so that closing sends FIN.
        let mut sink = [0u8; 4096];
        let _ = tokio::time::timeout(Duration::from_millis(200), async {
            while matches!(tls.read(&mut sink).await, Ok(n) if n > 0) {}
        })
        .await;
        tracing::debug!("connection {peer}: refused, its address holds {max} connections");
    });
}

/// `router` with the body-read deadline (module doc): every request body must end within
/// `timeout` of the request head, else the answer is 408 with `Connection: close`.
fn with_body_deadline(router: Router, timeout: Duration) -> Router {
    router.layer(axum::middleware::from_fn(
        move |req: Request, next: Next| body_deadline(timeout, req, next),
    ))
}

async fn body_deadline(timeout: Duration, req: Request, next: Next) -> Response {
    use axum::body::HttpBody;
    if req.body().is_end_stream() {
        return next.run(req).await;
    }
    let expired = Arc::new(AtomicBool::new(false));
    let deadline = tokio::time::Instant::now() + timeout;
    let req = req.map(|inner| {
        axum::body::Body::new(DeadlineBody {
            inner,
            sleep: Box::pin(tokio::time::sleep_until(deadline)),
            expired: expired.clone(),
        })
    });
    let answer = next.run(req).await;
    if !expired.load(Ordering::SeqCst) {
        return answer;
    }
    let mut r = error_response(
        StatusCode::REQUEST_TIMEOUT,
        format!(
            "the request body did not arrive within {} s of the request head; send the \
             whole body at once",
            timeout.as_secs_f64()
        ),
    );
    r.headers_mut()
        .insert(header::CONNECTION, HeaderValue::from_static("close"));
    r
}

/// A request body that fails once its deadline passes before it has ended.
struct DeadlineBody {
    inner: axum::body::Body,
    sleep: Pin<Box<tokio::time::Sleep>>,
    expired: Arc<AtomicBool>,
}

impl axum::body::HttpBody for DeadlineBody {
    type Data = axum::body::Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<std::result::Result<hyper::body::Frame<Self::Data>, Self::Error>>> {
        let this = &mut *self;
        if let Poll::Ready(frame) = Pin::new(&mut this.inner).poll_frame(cx) {
            return Poll::Ready(frame);
        }
        if this.sleep.as_mut().poll(cx).is_ready() {
            this.expired.store(true, Ordering::SeqCst);
            return Poll::Ready(Some(Err(axum::Error::new(std::io::Error::new(
                std::io::ErrorKind::TimedOut,
                "request body timed out",
            )))));
        }
        Poll::Pending
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> hyper::body::SizeHint {
        self.inner.size_hint()
    }
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

async fn serve_connection<I>(
    io: I,
    peer: SocketAddr,
    router: Router,
    limits: ServerLimits,
    stop: &mut tokio::sync::watch::Receiver<bool>,
) where
    I: tokio::io::AsyncRead + tokio::io::AsyncWrite + Send + Unpin + 'static,
{
    let io = TokioIo::new(io);
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
    fn one_share_per_ipv4_address_and_per_ipv6_64_prefix() {
        let ip = |s: &str| s.parse::<IpAddr>().unwrap();
        assert_eq!(address_key(ip("10.0.0.7")), ip("10.0.0.7"));
        assert_eq!(address_key(ip("::ffff:10.0.0.7")), ip("10.0.0.7"));
        assert_eq!(
            address_key(ip("2001:db8:1:2:aaaa::1")),
            ip("2001:db8:1:2::")
        );
        assert_eq!(
            address_key(ip("2001:db8:1:2:ffff::9")),
            address_key(ip("2001:db8:1:2::5"))
        );
        assert_ne!(address_key(ip("2001:db8:1:3::1")), ip("2001:db8:1:2::"));
        let shares = Arc::new(AddressShares::new(2));
        let a = shares.open(ip("10.0.0.7")).unwrap();
        let _b = shares.open(ip("10.0.0.7")).unwrap();
        assert!(shares.open(ip("10.0.0.7")).is_none());
        assert!(shares.open(ip("10.0.0.8")).is_some());
        drop(a);
        assert!(shares.open(ip("10.0.0.7")).is_some());
        let zero = ServerLimits {
            body_timeout: Duration::ZERO,
            ..ServerLimits::default()
        };
        assert!(zero.validate().is_err());
    }

    #[test]
    fn the_open_file_limit_is_read_on_linux() {
        if cfg!(target_os = "linux") {
            assert!(open_files_limit().is_some_and(|n| n > 0));
        }
    }
}
