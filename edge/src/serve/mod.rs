//! `slag-edge serve`: HTTP text queries over the fetched shards (axum 0.8 + tokio).
//!
//! Routes (JSON in and out; errors are `{"error": message, "status": code}`):
//! - `GET /health` → `{"status": "ok", …}` (never needs the token: for liveness probes);
//! - `GET /stats` → shards, Gaussians, bytes per Gaussian, memory (vectors, index, process RSS),
//!   store size, queries served, prompt-cache size, last fetch;
//! - `GET /query?text=chair[&top_k=100][&threshold=0.28|none][&mode=cosine|relevancy]
//!   [&bbox=minx,miny,minz,maxx,maxy,maxz][&index=exact|hnsw][&frame=map|scene]` →
//!   [`QueryAnswer`] (coordinates and `bbox` in the robot's map frame when the manifest has a
//!   scene-to-map transform, unless `frame=scene`; the answer's `frame` says which);
//! - `GET /query.ply?text=…` (same parameters, plus `color`, `dim`) → the loaded Gaussians as a
//!   3DGS `.ply` with the matches painted, and `GET /` → a web page that renders it
//!   ([`web`]; the page, its script and `/vendor/*` need no token);
//! - `POST /query` with `{"queries": [{"text": …, …}, …]}` (at most [`MAX_BATCH`]) →
//!   `{"answers": [QueryAnswer | {"error": …}, …]}` in order;
//! - `POST /fetch` with `{"center": [x, y] | [x, y, z], "radius": r, "prune": bool,
//!   "frame": "map" | "scene"}` (map metres by default when the manifest has a transform) → fetches
//!   from the server of the last fetch (or `"server"`; with the body's `"token"`, else
//!   [`ServeOptions::shard_token`]) into the store this process holds, then
//!   reloads; `POST /reload` reloads the store. With [`ServeOptions::trusted_keys`] the fetch
//!   accepts only what the publisher signed ([`crate::fetch`], "Signed manifests"): a refusal
//!   is answered 502 naming the failed check, logged as one error line, counted in `/stats`
//!   (`fetch_refusals`, `last_refusal`), and the scene served before keeps answering.
//!
//! Bad parameters → 400 naming the field; a missing/wrong bearer token (when configured) → 401;
//! bodies over [`MAX_BODY_BYTES`] → 413; requests over the timeout → 408; a method a route does
//! not answer → 405; an overlong target or header block → 414 / 431. Every one of them has the
//! JSON error body ([`slag_common::http::json_errors`]).
//!
//! # Timeouts, connections and answer size
//!
//! [`serve`] runs [`slag_common::http::serve`] under [`ServeOptions::limits`]: a header-read
//! timeout that is also the idle keep-alive timeout, a body-read deadline (a body still
//! incomplete then gets 408 and its connection is closed), a write timeout that drops a client
//! that stopped reading its answer, a connection limit kept below the open-file limit (lowered
//! with a warning at start-up where it is not) and a share of it per remote address (one more
//! connection from an address at its share gets 429). One request may ask for at most
//! [`ServeOptions::max_matches`] matches in all (default [`DEFAULT_MAX_MATCHES`]): the sum of
//! `top_k` over a `POST /query` batch, or one query's `top_k` (a threshold query returns at most
//! its `top_k` best matches too). More is refused with 400 naming the limit, before any scan, so
//! the largest answer one request can build is bounded.
//!
//! # TLS
//!
//! With [`ServeOptions::tls`] the same loop speaks HTTPS ([`slag_common::tls`]: rustls, ALPN
//! `http/1.1`, every limit and timeout above also for TLS connections, the handshake within the
//! header-read timeout). `SIGHUP` and `POST /reload` read the certificate and key files again:
//! new connections get the new certificate, open ones finish with theirs; a file that does not
//! load is refused (logged, and `POST /reload` answers the error) and the certificate in use
//! stays. `POST /reload` answers the new certificate's `tls_certificate_sha256`.
//!
//! # Admission control
//!
//! Every scan (`GET`/`POST /query`, `GET /query.ply`) is answered by the query engine
//! ([`QueryEngine::query`]) and so passes its FIFO gate ([`Admission`], [`crate::engine::admission`]:
//! [`ServeOptions::max_scans`] scans at once, default [`DEFAULT_MAX_SCANS`] = 1) after its
//! parameters are validated; the ROS 2 node's prompts pass the same gate. At most
//! [`ServeOptions::scan_queue`] (default [`DEFAULT_SCAN_QUEUE`]) queries wait; one more gets
//! **503 Service Unavailable** with a `Retry-After` header (whole seconds, at least 1: the
//! estimated time to drain the queue, from a moving average of recent scan times) and a JSON
//! error, so the latency of accepted requests stays bounded by the queue length. A waiting
//! request that reaches the request timeout gets 408 and leaves the queue; a running batch that
//! reaches it gets 408 and stops after the query it is on, freeing its scan slot. `GET /stats`
//! reports the gate under `"scans"`.

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use axum::Router;
use axum::extract::rejection::JsonRejection;
use axum::extract::{Request, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use slag_common::http::ServerLimits;
use slag_common::{Error, ErrorKind, Result};

pub mod web;

pub use crate::engine::{
    Admission, Busy, DEFAULT_MAX_MATCHES, DEFAULT_MAX_SCANS, DEFAULT_SCAN_QUEUE, Engine,
    EngineOptions, HNSW_EF_CONSTRUCTION, HNSW_EF_SEARCH, HNSW_M, QueryEngine, ServedEngine,
    check_matches, compact_answer,
};
use crate::fetch::{self, Center, FetchFailure, FetchParams};
use crate::query::{self, RawQuery, TextEmbedder};
pub use crate::scan::hnsw::HnswBackend;
use crate::store::EdgeStore;

/// Most queries in one `POST /query`.
pub const MAX_BATCH: usize = 64;
/// Largest request body accepted.
pub const MAX_BODY_BYTES: usize = 64 * 1024;

/// Server settings. Its `Debug` form shows whether each token is set, never the token.
#[derive(Clone)]
pub struct ServeOptions {
    /// Scene to serve.
    pub scene: String,
    /// Bearer token every route but `/health` requires (`None`: open).
    pub token: Option<String>,
    /// Cosine threshold used when a query gives none.
    pub threshold: f32,
    /// Build the approximate (HNSW) index at load, for `index=hnsw` queries.
    pub hnsw: bool,
    /// Which implementation builds it ([`HnswBackend`]; default instant-distance). `qdrant-edge`
    /// needs a binary built with the cargo feature `qdrant-edge`: [`AppState::new`] refuses it
    /// otherwise, whether or not `hnsw` is set.
    pub hnsw_backend: HnswBackend,
    /// Per-request timeout.
    pub request_timeout: Duration,
    /// Scans running at once (≥ 1; module doc, "Admission control").
    pub max_scans: usize,
    /// Requests that may wait for a scan; one more is answered 503 with `Retry-After`.
    pub scan_queue: usize,
    /// Matches one request may ask for in all (Σ `top_k` over a batch; module doc).
    pub max_matches: usize,
    /// Header-read / idle timeout, write timeout and connection limit of the server.
    pub limits: ServerLimits,
    /// Bearer token `POST /fetch` sends to the shard server when its body gives none (`None`:
    /// no token).
    pub shard_token: Option<String>,
    /// The publisher's public key `POST /fetch` requires signatures of
    /// ([`FetchParams::trusted_keys`]); `None`: unsigned maps are accepted.
    pub trusted_keys: Option<slag_common::shards::signature::TrustedKeys>,
    /// Serve HTTPS with this certificate (`None`: plain HTTP); `SIGHUP` and `POST /reload` read
    /// its files again (module doc, "TLS").
    pub tls: Option<Arc<slag_common::tls::ServerTls>>,
    /// A private CA (PEM) `POST /fetch` trusts beside the built-in roots for an `https://` shard
    /// server ([`FetchParams::ca_cert`]).
    pub ca_cert: Option<std::path::PathBuf>,
}

impl std::fmt::Debug for ServeOptions {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let secret = |t: &Option<String>| t.as_ref().map(|_| "***");
        f.debug_struct("ServeOptions")
            .field("scene", &self.scene)
            .field("token", &secret(&self.token))
            .field("threshold", &self.threshold)
            .field("hnsw", &self.hnsw)
            .field("hnsw_backend", &self.hnsw_backend)
            .field("request_timeout", &self.request_timeout)
            .field("max_scans", &self.max_scans)
            .field("scan_queue", &self.scan_queue)
            .field("max_matches", &self.max_matches)
            .field("limits", &self.limits)
            .field("shard_token", &secret(&self.shard_token))
            .field(
                "trusted_keys",
                &self.trusted_keys.as_ref().map(|k| k.key_ids()),
            )
            .field("tls", &self.tls)
            .field("ca_cert", &self.ca_cert)
            .finish()
    }
}

impl ServeOptions {
    /// Options for `scene` with the defaults of `slag-edge serve`: no token, plain HTTP, no
    /// private CA, threshold 0.28
    /// (the paper's), no HNSW (backend instant-distance when enabled), 30 s request timeout,
    /// [`DEFAULT_MAX_SCANS`], [`DEFAULT_SCAN_QUEUE`], [`DEFAULT_MAX_MATCHES`] and the default
    /// [`ServerLimits`].
    pub fn new(scene: impl Into<String>) -> ServeOptions {
        ServeOptions {
            scene: scene.into(),
            token: None,
            threshold: slag_common::similarity::PAPER_THRESHOLD,
            hnsw: false,
            hnsw_backend: HnswBackend::InstantDistance,
            request_timeout: Duration::from_secs(30),
            max_scans: DEFAULT_MAX_SCANS,
            scan_queue: DEFAULT_SCAN_QUEUE,
            max_matches: DEFAULT_MAX_MATCHES,
            limits: ServerLimits::default(),
            shard_token: None,
            trusted_keys: None,
            tls: None,
            ca_cert: None,
        }
    }

    /// The query engine's part of these options: the scene, the approximate index to build
    /// (`Some(hnsw_backend)` when `hnsw`), the default threshold and the admission limits.
    pub fn engine_options(&self) -> EngineOptions {
        EngineOptions {
            scene: self.scene.clone(),
            index: self.hnsw.then_some(self.hnsw_backend),
            threshold: self.threshold,
            max_scans: self.max_scans,
            scan_queue: self.scan_queue,
            max_matches: self.max_matches,
            trusted_keys: self.trusted_keys.clone(),
        }
    }
}

/// Shared server state: the query engine and what only HTTP needs (options, counters, the
/// fetch lock).
pub struct AppState {
    engine: QueryEngine,
    edge: EdgeStore,
    pub(crate) opts: ServeOptions,
    pub(crate) rejected: AtomicU64,
    pub(crate) web_dir: Option<std::path::PathBuf>,
    started: Instant,
    fetching: tokio::sync::Mutex<()>,
    refusals: Refusals,
}

/// Fetches refused because the trusted key did not vouch for what the server sent
/// ([`Error::Untrusted`]), for `/stats`.
#[derive(Default)]
struct Refusals {
    count: AtomicU64,
    last: std::sync::Mutex<Option<String>>,
}

impl Refusals {
    /// Counts `e` and keeps its message as the last refusal; logs it as one error line.
    fn note(&self, scene: &str, e: &Error) {
        tracing::error!("fetch of scene {scene} refused, still serving the generation before: {e}");
        self.count.fetch_add(1, Ordering::Relaxed);
        *self
            .last
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner) = Some(e.to_string());
    }

    /// `{"fetch_refusals": n, "last_refusal": message | null}`.
    fn stats(&self) -> (u64, Option<String>) {
        let last = self
            .last
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone();
        (self.count.load(Ordering::Relaxed), last)
    }
}

impl AppState {
    /// Loads the scene (building the approximate index when [`ServeOptions::hnsw`]) and embeds
    /// the canonical negatives once; with [`ServeOptions::trusted_keys`] a signed generation's
    /// tiles are verified in the background ([`QueryEngine::new`]) and served once verified.
    ///
    /// Errors: [`Error::Param`] `hnsw_backend` first, before the store is read, for a backend
    /// this binary was built without ([`HnswBackend::require`]); as [`Engine::load_with`]; a
    /// text model of another CLIP model than the stored embeddings
    /// ([`Error::ModelMismatch`]) or whose width differs from theirs.
    pub fn new(edge: EdgeStore, text: Arc<dyn TextEmbedder>, opts: ServeOptions) -> Result<Self> {
        Self::new_gated(edge, text, opts, None)
    }

    /// [`Self::new`], whose background verification of a signed generation's tiles (with
    /// [`ServeOptions::trusted_keys`]) waits at `gate` before each tile
    /// ([`QueryEngine::new_gated`]): a test queries the server while every tile is pending,
    /// then after each tile it releases.
    ///
    /// Errors: as [`Self::new`].
    pub fn new_gated(
        edge: EdgeStore,
        text: Arc<dyn TextEmbedder>,
        opts: ServeOptions,
        gate: Option<crate::engine::VerifyGate>,
    ) -> Result<Self> {
        opts.hnsw_backend.require()?;
        let engine = QueryEngine::new_gated(edge.clone(), text, opts.engine_options(), gate)?;
        Ok(AppState {
            engine,
            edge,
            rejected: AtomicU64::new(0),
            started: Instant::now(),
            fetching: tokio::sync::Mutex::new(()),
            web_dir: None,
            refusals: Refusals::default(),
            opts,
        })
    }

    /// Serves the web page from `dir` instead of the compiled-in files ([`web`]):
    /// `index.html` and `app.js` where present, the viewer from `<dir>/vendor` only
    /// (`scripts/web-vendor.sh`). `None` keeps the compiled-in page and viewer.
    pub fn with_web_dir(mut self, dir: Option<std::path::PathBuf>) -> Self {
        if dir.is_some() {
            self.web_dir = dir;
        }
        self
    }

    /// The generation served now.
    pub(crate) fn engine(&self) -> Arc<Engine> {
        self.engine.current()
    }

    /// The query engine this server answers from (shared with a ROS 2 node).
    pub fn query_engine(&self) -> &QueryEngine {
        &self.engine
    }
}

/// The query engine of a server's state: `slag-edge serve --ros2` starts its node on the one
/// the HTTP routes answer from ([`crate::ros2::start`]).
impl From<Arc<AppState>> for QueryEngine {
    fn from(state: Arc<AppState>) -> QueryEngine {
        state.engine.clone()
    }
}

/// Builds the router (auth, body limit, timeout and JSON error layers included).
pub fn router(state: Arc<AppState>) -> Router {
    let timeout = state.opts.request_timeout;
    // POST /fetch keeps its own request timeout, whose 408 speaks of the fetch (fetch_post).
    let fetching = Router::new().route("/fetch", post(fetch_post));
    let router = Router::new()
        .route("/health", get(health))
        .route("/stats", get(stats))
        .route("/query", get(query_get).post(query_post))
        .route("/query.ply", get(web::query_ply))
        .route("/", get(web::index))
        .route("/index.html", get(web::index))
        .route("/app.js", get(web::app_js))
        .route("/vendor/{name}", get(web::vendor))
        .route("/reload", post(reload))
        .layer(tower_http::timeout::TimeoutLayer::with_status_code(
            StatusCode::REQUEST_TIMEOUT,
            timeout,
        ))
        .merge(fetching)
        .fallback(|| async {
            error(
                StatusCode::NOT_FOUND,
                "no such route; use GET /query?text=…, GET /query.ply?text=…, POST /query, GET /, \
                 GET /health, GET /stats"
                    .into(),
            )
        })
        .method_not_allowed_fallback(|| async {
            error(
                StatusCode::METHOD_NOT_ALLOWED,
                "method not allowed on this route: GET /query, /query.ply, /health, /stats and \
                 the page; POST /query, /fetch and /reload"
                    .into(),
            )
        })
        .layer(middleware::from_fn_with_state(state.clone(), auth))
        .layer(tower_http::limit::RequestBodyLimitLayer::new(
            MAX_BODY_BYTES,
        ))
        .with_state(state);
    slag_common::http::json_errors(router)
}

/// Binds `addr` and serves until Ctrl-C or SIGTERM under [`ServeOptions::limits`] (module doc);
/// `on_bound` receives the bound address. The connection limit is first checked against the
/// open-file limit ([`slag_common::http::check_connection_limit`]): lowered, with a warning
/// logged, where it leaves fewer than [`slag_common::http::FD_HEADROOM`] descriptors free.
///
/// Errors: invalid limits or an open-file limit too low to serve ([`Error::Param`]
/// `max_connections`, ...); the address cannot be bound ([`Error::Io`]).
pub async fn serve(
    state: Arc<AppState>,
    addr: SocketAddr,
    on_bound: impl FnOnce(SocketAddr),
) -> Result<()> {
    let (limits, warning) = slag_common::http::check_connection_limit(
        state.opts.limits,
        slag_common::http::open_files_limit(),
    )?;
    if let Some(w) = warning {
        tracing::warn!("{w}");
    }
    let listener = tokio::net::TcpListener::bind(addr)
        .await
        .map_err(|e| Error::io(addr.to_string(), e))?;
    let local = listener
        .local_addr()
        .map_err(|e| Error::io(addr.to_string(), e))?;
    on_bound(local);
    let tls = state.opts.tls.clone();
    slag_common::http::serve_with_tls(listener, router(state), limits, tls, shutdown()).await;
    Ok(())
}

async fn shutdown() {
    #[cfg(unix)]
    {
        let term = async {
            match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
                Ok(mut s) => {
                    s.recv().await;
                }
                Err(_) => std::future::pending::<()>().await,
            }
        };
        tokio::select! {
            _ = tokio::signal::ctrl_c() => {}
            _ = term => {}
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}

pub(crate) fn error(status: StatusCode, message: String) -> Response {
    slag_common::http::error_response(status, message)
}

/// The 503 answer to a query the admission gate turned away: `Retry-After` header and a JSON
/// error saying what to do.
pub(crate) fn busy(b: &Busy) -> Response {
    let mut r = error(
        StatusCode::SERVICE_UNAVAILABLE,
        format!(
            "server busy: {} queries already wait for a scan; retry after {} s (Retry-After)",
            b.waiting, b.retry_after_s
        ),
    );
    r.headers_mut().insert(
        header::RETRY_AFTER,
        header::HeaderValue::from(b.retry_after_s),
    );
    r
}

/// Maps a slag error to an HTTP status by who has to act ([`slag_common::Error::kind`], one
/// exhaustive arm per kind, no `_`): the client's input 400, a text model of another CLIP model
/// 409, an upstream shard server 502, this side (files, stored shards, models, GPU, limits) and
/// slag's own faults (a panicked task) 500.
pub(crate) fn status_of(e: &Error) -> StatusCode {
    match e.kind() {
        ErrorKind::UserInput => StatusCode::BAD_REQUEST,
        ErrorKind::Conflict => StatusCode::CONFLICT,
        ErrorKind::Upstream => StatusCode::BAD_GATEWAY,
        ErrorKind::Environment | ErrorKind::Internal => StatusCode::INTERNAL_SERVER_ERROR,
    }
}

async fn auth(
    State(state): State<Arc<AppState>>,
    headers: HeaderMap,
    req: Request,
    next: Next,
) -> Response {
    let Some(token) = state.opts.token.as_deref() else {
        return next.run(req).await;
    };
    if req.uri().path() == "/health" || web::is_public_path(req.uri().path()) {
        return next.run(req).await;
    }
    // Exactly one Authorization header: with two, which one counts would be a guess.
    if slag_common::auth::authorized_once(headers.get_all(header::AUTHORIZATION), token) {
        next.run(req).await
    } else {
        state.rejected.fetch_add(1, Ordering::Relaxed);
        let mut r = error(
            StatusCode::UNAUTHORIZED,
            "missing or wrong bearer token: send one Authorization: Bearer <token> header".into(),
        );
        r.headers_mut().insert(
            header::WWW_AUTHENTICATE,
            header::HeaderValue::from_static("Bearer"),
        );
        r
    }
}

async fn health(State(state): State<Arc<AppState>>) -> Response {
    let e = state.engine();
    axum::Json(serde_json::json!({
        "status": "ok",
        "scene": state.opts.scene,
        "gaussians": e.store.len(),
        "uptime_s": state.started.elapsed().as_secs(),
    }))
    .into_response()
}

async fn stats(State(state): State<Arc<AppState>>) -> Response {
    // Everything about the scene from the one generation the engine holds (its fetch record
    // included), not from the store, where a fetch may be committing another.
    let e = state.engine();
    let edge = state.edge.clone();
    let disk = tokio::task::spawn_blocking(move || edge.disk_bytes())
        .await
        .unwrap_or(0);
    let mut record = e.record.clone();
    // A record written before URLs with credentials were refused may still hold one.
    if let Some(r) = record.as_mut() {
        r.server = slag_common::auth::redact_url(&r.server).into_owned();
    }
    let n = e.store.len();
    let (fetch_refusals, last_refusal) = state.refusals.stats();
    axum::Json(serde_json::json!({
        "scene": state.opts.scene,
        "generation": e.manifest.generation,
        "embedding_model": e.manifest.model,
        "text_model": state.engine.text().name(),
        "dim": e.store.dim(),
        "dtype": e.manifest.dtype,
        "tiles_in_manifest": e.manifest.tiles.len(),
        "frames": e.manifest.frames,
        "shards_loaded": e.load.loaded_tiles.len(),
        "shards_absent": e.load.absent_tiles,
        "shards_rejected": e.load.rejected,
        "shards_hashed": e.load.hashed,
        "verification": state.engine.verification(),
        "tiles_verified": e.load.hashed,
        "tiles_pending_verification": e.load.pending_verification,
        "tiles_dropped": e.load.rejected.len(),
        "gaussians": n,
        "memory": {
            "vectors_bytes": e.store.memory_bytes(),
            "bytes_per_gaussian": if n > 0 { e.store.memory_bytes() as f64 / n as f64 } else { 0.0 },
            "hnsw_bytes": e.hnsw.as_ref().map(|h| h.memory_bytes()),
            "hnsw_backend": e.hnsw.as_ref().map(|h| h.backend().name()),
            "process_rss_bytes": slag_common::util::rss_bytes(),
        },
        "store_disk_bytes": disk,
        "last_fetch": record,
        "signed_fetches": state.opts.trusted_keys.as_ref().map(|k| k.key_ids()),
        "fetch_refusals": fetch_refusals,
        "last_refusal": last_refusal,
        "queries_served": state.engine.queries_served(),
        "requests_rejected": state.rejected.load(Ordering::Relaxed),
        "prompt_cache_entries": state.engine.text().cached(),
        "scans": state.engine.admission().stats(),
        "uptime_s": state.started.elapsed().as_secs(),
    }))
    .into_response()
}

/// Keys of the `GET` routes' query strings, for naming the field of a refused value.
const QUERY_KEYS: [&str; 15] = [
    "text",
    "top_k",
    "threshold",
    "mode",
    "bbox",
    "index",
    "frame",
    "max_objects",
    "near",
    "object_gap",
    "object_min_gaussians",
    "smooth",
    "color",
    "color_by",
    "dim",
];

/// `%XX` escapes decoded and `+` read as a space (`application/x-www-form-urlencoded`); a `%`
/// not followed by two hex digits stays as it is. Bytes, not text: see [`query_pairs`].
fn percent_decode(s: &str) -> Vec<u8> {
    let b = s.as_bytes();
    let hex = |c: u8| (c as char).to_digit(16);
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        match (
            b[i],
            b.get(i + 1).copied().and_then(hex),
            b.get(i + 2).copied().and_then(hex),
        ) {
            (b'%', Some(hi), Some(lo)) => {
                out.push((hi * 16 + lo) as u8);
                i += 3;
            }
            (b'+', ..) => {
                out.push(b' ');
                i += 1;
            }
            (c, ..) => {
                out.push(c);
                i += 1;
            }
        }
    }
    out
}

/// A query string's pairs (`a=1&b=2`), percent-decoded as **strict** UTF-8: a key or value whose
/// bytes are not UTF-8 once decoded (`text=%FF`) is refused, never replaced by U+FFFD and
/// answered, so every route refuses what `POST /query` and ROS 2 refuse. A key given twice is
/// refused too (which one counts would be a guess). `None` (no `?`) is no pairs.
///
/// Errors: [`Error::Query`] naming the key (`query` for a key that is itself not UTF-8 or not
/// one of the routes' keys) and saying what to send.
pub fn query_pairs(query: Option<&str>) -> Result<std::collections::HashMap<String, String>> {
    let mut pairs = std::collections::HashMap::new();
    for part in query.unwrap_or("").split('&').filter(|p| !p.is_empty()) {
        let (k, v) = part.split_once('=').unwrap_or((part, ""));
        let key = String::from_utf8(percent_decode(k)).map_err(|_| {
            Error::query(
                "query",
                "a query-string key is not UTF-8 once percent-decoded; percent-encode UTF-8 text",
            )
        })?;
        let field = QUERY_KEYS
            .iter()
            .find(|&&f| f == key)
            .copied()
            .unwrap_or("query");
        let value = String::from_utf8(percent_decode(v)).map_err(|e| {
            let at = e.utf8_error().valid_up_to();
            Error::query(
                field,
                format!(
                    "{key}: not UTF-8 once percent-decoded (byte {:#04x} at {at}); \
                     percent-encode the UTF-8 bytes of the text",
                    e.as_bytes()[at]
                ),
            )
        })?;
        if pairs.insert(key.clone(), value).is_some() {
            return Err(Error::query(
                field,
                format!("{key} given twice in the query string; give it once"),
            ));
        }
    }
    Ok(pairs)
}

/// The `GET /query?…` path: decoded query-string pairs ([`query_pairs`]) to a [`RawQuery`]
/// (unknown keys rejected like a `POST` item).
///
/// Errors: [`Error::Query`] naming an unknown key.
pub fn raw_from_pairs(pairs: std::collections::HashMap<String, String>) -> Result<RawQuery> {
    let obj: serde_json::Map<String, serde_json::Value> = pairs
        .into_iter()
        .map(|(k, v)| (k, serde_json::Value::String(v)))
        .collect();
    RawQuery::from_json(&serde_json::Value::Object(obj))
}

async fn query_get(State(state): State<Arc<AppState>>, uri: axum::http::Uri) -> Response {
    let params = query_pairs(uri.query())
        .and_then(raw_from_pairs)
        .and_then(|r| r.validate(state.opts.threshold))
        .and_then(|p| {
            state
                .engine
                .check_matches(std::slice::from_ref(&p))
                .map(|()| p)
        });
    let params = match params {
        Ok(p) => p,
        Err(e) => {
            state.rejected.fetch_add(1, Ordering::Relaxed);
            return error(status_of(&e), e.to_string());
        }
    };
    match state.engine.query_one(params).await {
        Ok(Ok(a)) => axum::Json(a).into_response(),
        Ok(Err(e)) => error(status_of(&e), e.to_string()),
        Err(b) => busy(&b),
    }
}

async fn query_post(
    State(state): State<Arc<AppState>>,
    body: std::result::Result<axum::Json<serde_json::Value>, JsonRejection>,
) -> Response {
    let bad = |m: String| {
        state.rejected.fetch_add(1, Ordering::Relaxed);
        error(StatusCode::BAD_REQUEST, m)
    };
    let body = match body {
        Ok(axum::Json(b)) => b,
        Err(e) if e.status() == StatusCode::PAYLOAD_TOO_LARGE => {
            state.rejected.fetch_add(1, Ordering::Relaxed);
            return error(
                StatusCode::PAYLOAD_TOO_LARGE,
                format!(
                    "body over {MAX_BODY_BYTES} bytes; send fewer queries (at most {MAX_BATCH})"
                ),
            );
        }
        Err(e) => {
            return bad(format!(
                "body: {e}; send {{\"queries\": [{{\"text\": \"chair\"}}]}}"
            ));
        }
    };
    let Some(items) = body.get("queries").and_then(|q| q.as_array()) else {
        return bad("body must be {\"queries\": [{\"text\": \"chair\"}, …]}".into());
    };
    if items.is_empty() || items.len() > MAX_BATCH {
        return bad(format!(
            "{} queries in the batch; send 1..={MAX_BATCH}",
            items.len()
        ));
    }
    // Validate everything first: one bad item fails the whole batch with its index.
    let mut params = Vec::with_capacity(items.len());
    for (i, it) in items.iter().enumerate() {
        match RawQuery::from_json(it)
            .and_then(|r| r.validate_for(state.opts.threshold, query::Interface::HttpPost))
        {
            Ok(p) => params.push(p),
            Err(e) => return bad(format!("queries[{i}]: {e}")),
        }
    }
    if let Err(e) = state.engine.check_matches(&params) {
        return bad(e.to_string());
    }
    let answers = match state.engine.query(params).await {
        Ok(a) => a,
        Err(b) => return busy(&b),
    };
    // Serialised straight from the answers (no intermediate JSON tree per match).
    #[derive(serde::Serialize)]
    #[serde(untagged)]
    enum Item {
        Answer(Box<query::QueryAnswer>),
        Error { error: String, status: u16 },
    }
    #[derive(serde::Serialize)]
    struct Answers {
        answers: Vec<Item>,
    }
    let answers = answers
        .into_iter()
        .map(|r| match r {
            Ok(a) => Item::Answer(Box::new(a)),
            Err(e) => Item::Error {
                error: e.to_string(),
                status: status_of(&e).as_u16(),
            },
        })
        .collect();
    axum::Json(Answers { answers }).into_response()
}

/// `POST /reload`: the store, then the TLS certificate when serving HTTPS (module doc, "TLS").
async fn reload(State(state): State<Arc<AppState>>) -> Response {
    if let Err(e) = state.engine.reload().await {
        return error(status_of(&e), e.to_string());
    }
    let e = state.engine();
    let mut answer = serde_json::json!({
        "reloaded": true, "gaussians": e.store.len(), "shards": e.load.loaded_tiles.len()
    });
    if let Some(tls) = &state.opts.tls {
        match slag_common::tls::log_reload(tls, "POST /reload") {
            Ok(f) => answer["tls_certificate_sha256"] = f.into(),
            Err(e) => {
                return error(
                    status_of(&e),
                    format!(
                        "the store was reloaded, the TLS certificate was not and the one in use \
                         stays (SHA-256 {}): {e}",
                        tls.fingerprint()
                    ),
                );
            }
        }
    }
    axum::Json(answer).into_response()
}

/// `POST /fetch` body.
#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct FetchBody {
    center: Vec<f64>,
    radius: f64,
    #[serde(default)]
    prune: bool,
    /// `map` | `scene` (default: map when the manifest has a transform).
    frame: Option<String>,
    server: Option<String>,
    token: Option<String>,
}

/// `POST /fetch`: fetches into the store this process holds (one fetch at a time), then reloads
/// (module doc).
async fn fetch_post(
    State(state): State<Arc<AppState>>,
    body: std::result::Result<axum::Json<FetchBody>, JsonRejection>,
) -> Response {
    let params = match fetch_params(&state, body) {
        Ok(p) => p,
        Err(m) => return error(StatusCode::BAD_REQUEST, m),
    };
    let limit = state.opts.request_timeout;
    let Ok(fetched) = tokio::time::timeout(limit, async {
        let _guard = state.fetching.lock().await;
        fetch::fetch_classified(&state.edge, &params).await
    })
    .await
    else {
        return error(
            StatusCode::REQUEST_TIMEOUT,
            format!(
                "the fetch did not finish within the server's request timeout ({:.0} s, \
                 --request-timeout): the shards it completed are kept and the scene served \
                 before keeps answering; POST /fetch again to resume the partial downloads, \
                 fetch a smaller radius, or raise --request-timeout",
                limit.as_secs_f64()
            ),
        );
    };
    if let Err(f) = &fetched
        && matches!(f.error, Error::Untrusted { .. })
    {
        state.refusals.note(&state.opts.scene, &f.error);
    }
    match fetched {
        Ok(summary) => match state.engine.reload().await {
            Ok(()) => axum::Json(summary).into_response(),
            Err(e) => error(status_of(&e), e.to_string()),
        },
        Err(f) => fetch_failed(f),
    }
}

/// The fetch a `POST /fetch` body asks for: its frame, centre (2 numbers on the ground, 3 in
/// the world), radius and pruning, from its server or the last fetch's, with its token or the
/// server's [`ServeOptions::shard_token`], under the server's trusted key and CA.
///
/// Errors: the message of the 400 answer (a bad body, frame or centre; no server to fetch from).
fn fetch_params(
    state: &AppState,
    body: std::result::Result<axum::Json<FetchBody>, JsonRejection>,
) -> std::result::Result<FetchParams, String> {
    let b = match body {
        Ok(axum::Json(b)) => b,
        Err(e) => {
            return Err(format!(
                "body: {e}; send {{\"center\": [x, y], \"radius\": 50}}"
            ));
        }
    };
    let frame = match b.frame.as_deref() {
        None | Some("auto") => query::FrameChoice::Auto,
        Some("map") => query::FrameChoice::Map,
        Some("scene") => query::FrameChoice::Scene,
        Some(f) => return Err(format!("frame {f:?}: use map or scene")),
    };
    let center = match b.center[..] {
        [x, y] if x.is_finite() && y.is_finite() => Center::Ground([x, y]),
        [x, y, z] if [x, y, z].iter().all(|v| v.is_finite()) => Center::World([x, y, z]),
        _ => return Err("center: 2 (ground) or 3 (world) finite numbers".into()),
    };
    let last_server = || {
        state
            .edge
            .fetch_record(&state.opts.scene)
            .ok()
            .flatten()
            .map(|r| r.server)
    };
    let Some(server) = b.server.clone().or_else(last_server) else {
        return Err("no previous fetch to take the server from: pass \"server\"".into());
    };
    Ok(FetchParams {
        server,
        ca_cert: state.opts.ca_cert.clone(),
        scene: state.opts.scene.clone(),
        center,
        radius: b.radius,
        prune: b.prune,
        jobs: 4,
        retries: 3,
        timeout: Duration::from_secs(30),
        min_rate: crate::fetch::DEFAULT_MIN_RATE,
        token: b.token.or_else(|| state.opts.shard_token.clone()),
        progress: false,
        frame,
        trusted_keys: state.opts.trusted_keys.clone(),
    })
}

/// The answer to a failed `POST /fetch`: a manifest the shard server sent that cannot be used is
/// its fault (502, not this side's); a token the shard server wants or refused says where the
/// token comes from; anything else by its kind ([`status_of`]).
fn fetch_failed(f: FetchFailure) -> Response {
    const TOKEN_HINT: &str = "send \"token\" in the body, or start slag-edge serve with the shard \
                              server's token (SLAG_SHARD_TOKEN, or shard_token_file in its config)";
    match f {
        FetchFailure {
            error: e,
            bad_manifest: true,
        } => error(
            StatusCode::BAD_GATEWAY,
            format!(
                "the shard server's manifest is bad, so nothing was fetched and the scene served \
                 before keeps answering: {e}"
            ),
        ),
        FetchFailure {
            error:
                e @ Error::Network {
                    status: Some(401 | 403),
                    ..
                },
            ..
        } => error(status_of(&e), format!("{e}; {TOKEN_HINT}")),
        FetchFailure {
            error: e @ Error::Param { name: "server", .. },
            ..
        } => error(status_of(&e), format!("{e}: {TOKEN_HINT}")),
        FetchFailure { error: e, .. } => error(status_of(&e), e.to_string()),
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod status_tests {
    use super::*;

    #[test]
    fn the_debug_form_of_the_options_shows_no_token() {
        let o = ServeOptions {
            token: Some("edge-secret".into()),
            shard_token: Some("shard-secret".into()),
            ..ServeOptions::new("s")
        };
        let d = format!("{o:?}");
        assert!(!d.contains("secret") && d.contains("***"), "{d}");
    }

    #[test]
    fn query_strings_are_strict_utf8() {
        let p = query_pairs(Some("text=caf%C3%A9+noir&top_k=3&x=50%")).unwrap();
        assert_eq!(p["text"], "café noir");
        assert_eq!(p["x"], "50%");
        assert!(query_pairs(None).unwrap().is_empty());
        for (q, field) in [
            ("text=%FF", "text"),
            ("top_k=1&text=a%C3", "text"),
            ("%FF=1", "query"),
            ("text=a&text=b", "text"),
        ] {
            match query_pairs(Some(q)) {
                Err(Error::Query { field: f, .. }) => assert_eq!(f, field, "{q}"),
                other => panic!("{q}: {other:?}"),
            }
        }
    }

    #[test]
    fn client_faults_4xx_server_faults_5xx() {
        for e in [
            Error::Invalid("k".into()),
            Error::query("top_k", "top_k \"x\": use an integer"),
            Error::param("radius", -1, "a finite number ≥ 0"),
        ] {
            assert_eq!(status_of(&e), StatusCode::BAD_REQUEST, "{e}");
        }
        assert_eq!(
            status_of(&Error::mismatch(
                slag_common::Mismatched::EmbeddingWidth,
                "512 vs 768"
            )),
            StatusCode::CONFLICT
        );
        assert_eq!(
            status_of(&Error::network("http://s", "down")),
            StatusCode::BAD_GATEWAY
        );
        for e in [
            Error::internal("query task failed: panicked"),
            Error::Shard(slag_common::shards::ShardError::BadMagic),
            Error::limit(slag_common::Resource::GpuMemory, "1 GiB", "0"),
            Error::limit(
                slag_common::Resource::Memory,
                "1e9 rows",
                "what the allocator gave",
            ),
            Error::Gpu("lost".into()),
        ] {
            assert_eq!(status_of(&e), StatusCode::INTERNAL_SERVER_ERROR, "{e}");
            assert!(!e.is_user_input(), "{e}");
        }
        assert!(Error::Invalid("k".into()).is_user_input());
    }
}
