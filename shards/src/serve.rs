//! `slag-encoder serve`: HTTP access to a [`ShardStore`] (axum 0.8 + tokio).
//!
//! Routes:
//! - `GET /v1/scenes` → `{"scenes": [..]}`;
//! - `GET /v1/scenes/{scene}/manifest` → the current manifest's JSON, the exact bytes the store
//!   holds (and its signature covers), strong `ETag` = CRC-32 of the JSON, `If-None-Match` → 304;
//! - `GET /v1/scenes/{scene}/manifest.sig` → the detached signature of those bytes
//!   ([`slag_common::shards::signature::ManifestSignature`], JSON): the one stored with a
//!   generation partitioned with a signing key, or, when the server has a signing key of its own
//!   ([`router_signed`], `serve --signing-key`), a signature by that key (it then signs every
//!   manifest it serves, stored signatures aside). 404 when the manifest is unsigned and the
//!   server has no key;
//! - `GET /v1/scenes/{scene}/shards/{id}` → shard bytes (`application/octet-stream`), strong
//!   `ETag` = `"<crc32 hex>"` (the manifest checksum), `If-None-Match` → 304, single
//!   `Range: bytes=a-b | a- | -n` → 206 with `Content-Range`, unsatisfiable → 416 with
//!   `Content-Range: bytes */len`; `If-Range` with another ETag → full 200. Multi-range requests
//!   get the full body (200), as RFC 9110 allows;
//! - `GET /v1/scenes/{scene}/codebook` → the codebook file of a mixture scene (same headers,
//!   ETag and ranges as a shard; 404 for a dense scene).
//!
//! Errors are JSON `{"error": message, "status": code}`: invalid scene id (`[A-Za-z0-9_.-]`,
//! 1..=64, not starting with `.`) or non-decimal shard id → 400, unknown scene/shard → 404,
//! store failures → 500. Ids are never used as file paths.
//!
//! With a bearer token ([`router_with_token`], `slag-encoder serve --token-file F` or env
//! `SLAG_SHARD_TOKEN`) every route requires `Authorization: Bearer <token>` (compared in constant
//! time); otherwise 401 JSON with `WWW-Authenticate: Bearer`. `slag-edge fetch --token` sends it.
//!
//! Every error answer, those axum produces itself included (405 with `Allow`, 414, 431, 416), has
//! the JSON body ([`slag_common::http::json_errors`]). [`serve_with_limits`] applies the
//! header-read / idle timeout, the body-read deadline, the write timeout, the connection limit
//! and its per-address share of [`slag_common::http::ServerLimits`]; [`serve_with_tls`] the same
//! over HTTPS (`--tls-cert` / `--tls-key`; `SIGHUP` reloads the certificate). A shard or codebook is answered from the store's own
//! buffer (the value sled holds), shared by every connection answering it and by ranges of it:
//! no copy per connection, so a client that reads slowly holds no shard of its own.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::Arc;

use axum::Router;
use axum::body::Bytes;
use axum::extract::{FromRequestParts, Path, State};
use axum::http::request::Parts;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use slag_common::http::ServerLimits;
use slag_common::shards::signature::SigningKey;
use slag_common::shards::{shard_checksum, valid_scene_id};

use crate::store::ShardStore;

/// Builds the router over `store`.
pub fn router(store: ShardStore) -> Router {
    router_signed(store, None)
}

/// [`router`] whose `manifest.sig` route signs every manifest it serves with `key` when given
/// (module doc).
pub fn router_signed(store: ShardStore, key: Option<SigningKey>) -> Router {
    let signer = Arc::new(Signer {
        store: store.clone(),
        key,
    });
    Router::new()
        .route("/v1/scenes", get(scenes))
        .route("/v1/scenes/{scene}/manifest", get(manifest))
        .route(
            "/v1/scenes/{scene}/manifest.sig",
            get(signature).with_state(signer),
        )
        .route("/v1/scenes/{scene}/shards/{id}", get(shard))
        .route("/v1/scenes/{scene}/codebook", get(codebook))
        .fallback(|| async {
            error(
                StatusCode::NOT_FOUND,
                "no such route; see /v1/scenes/{scene}/manifest".into(),
            )
        })
        .method_not_allowed_fallback(|| async {
            error(
                StatusCode::METHOD_NOT_ALLOWED,
                "method not allowed: every route of the shard server answers GET (and HEAD)".into(),
            )
        })
        .with_state(Arc::new(store))
}

/// [`router`] behind a bearer token when `token` is `Some` (module doc); `None` is [`router`].
/// The JSON error layers ([`slag_common::http::json_errors`]) are outermost, so a 401 or 405
/// and an overlong request all get the JSON body.
pub fn router_with_token(store: ShardStore, token: Option<String>) -> Router {
    router_with_token_signed(store, token, None)
}

/// [`router_with_token`] over [`router_signed`].
pub fn router_with_token_signed(
    store: ShardStore,
    token: Option<String>,
    key: Option<SigningKey>,
) -> Router {
    let r = router_signed(store, key);
    let r = match token {
        None => r,
        Some(t) => r.layer(axum::middleware::from_fn_with_state(
            Arc::new(t),
            require_token,
        )),
    };
    slag_common::http::json_errors(r)
}

async fn require_token(
    State(token): State<Arc<String>>,
    req: axum::extract::Request,
    next: axum::middleware::Next,
) -> Response {
    // Exactly one Authorization header: with two, which one counts would be a guess.
    if slag_common::auth::authorized_once(req.headers().get_all(header::AUTHORIZATION), &token) {
        return next.run(req).await;
    }
    let mut r = error(
        StatusCode::UNAUTHORIZED,
        "missing or wrong bearer token: send one Authorization: Bearer <token> header (slag-edge fetch \
         --token, or SLAG_SHARD_TOKEN)"
            .into(),
    );
    r.headers_mut()
        .insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
    r
}

/// Binds `addr` and serves until Ctrl-C. Returns the bound address through `on_bound` (useful
/// with port 0).
///
/// Errors: the address cannot be bound ([`slag_common::Error::Io`]).
pub async fn serve(
    store: ShardStore,
    addr: SocketAddr,
    on_bound: impl FnOnce(SocketAddr),
) -> slag_common::Result<()> {
    serve_with_token(store, addr, None, on_bound).await
}

/// [`serve`] behind an optional bearer token ([`router_with_token`]), with the default
/// [`ServerLimits`].
///
/// Errors: the address cannot be bound ([`slag_common::Error::Io`]).
pub async fn serve_with_token(
    store: ShardStore,
    addr: SocketAddr,
    token: Option<String>,
    on_bound: impl FnOnce(SocketAddr),
) -> slag_common::Result<()> {
    serve_with_limits(store, addr, token, ServerLimits::default(), on_bound).await
}

/// [`serve_with_token`] under `limits`: header-read (and idle keep-alive) timeout, body-read
/// deadline, write timeout, connection limit and per-address share ([`slag_common::http`]). The connection limit is first checked
/// against the open-file limit ([`slag_common::http::check_connection_limit`]: lowered with a
/// warning where it leaves fewer than 64 descriptors free).
///
/// Errors: invalid limits or an open-file limit too low for any connection limit
/// ([`slag_common::Error::Param`]); the address cannot be bound ([`slag_common::Error::Io`]).
pub async fn serve_with_limits(
    store: ShardStore,
    addr: SocketAddr,
    token: Option<String>,
    limits: ServerLimits,
    on_bound: impl FnOnce(SocketAddr),
) -> slag_common::Result<()> {
    serve_with_tls(store, addr, token, limits, None, on_bound).await
}

/// [`serve_with_limits`] over HTTPS with `tls` (plain HTTP with `None`): the same limits and
/// timeouts, the TLS handshake within the header-read timeout, and `SIGHUP` reading the
/// certificate and key again ([`slag_common::tls`]).
///
/// Errors: as [`serve_with_limits`].
pub async fn serve_with_tls(
    store: ShardStore,
    addr: SocketAddr,
    token: Option<String>,
    limits: ServerLimits,
    tls: Option<Arc<slag_common::tls::ServerTls>>,
    on_bound: impl FnOnce(SocketAddr),
) -> slag_common::Result<()> {
    serve_with_tls_signed(store, addr, token, limits, tls, None, on_bound).await
}

/// [`serve_with_tls`] whose `manifest.sig` route signs every manifest with `key` when given
/// ([`router_signed`]).
///
/// Errors: as [`serve_with_limits`].
pub async fn serve_with_tls_signed(
    store: ShardStore,
    addr: SocketAddr,
    token: Option<String>,
    limits: ServerLimits,
    tls: Option<Arc<slag_common::tls::ServerTls>>,
    key: Option<SigningKey>,
    on_bound: impl FnOnce(SocketAddr),
) -> slag_common::Result<()> {
    let (limits, warning) =
        slag_common::http::check_connection_limit(limits, slag_common::http::open_files_limit())?;
    if let Some(w) = warning {
        tracing::warn!("{w}");
    }
    let listener = tokio::net::TcpListener::bind(addr)
        .await
        .map_err(|e| slag_common::Error::io(addr.to_string(), e))?;
    let local = listener
        .local_addr()
        .map_err(|e| slag_common::Error::io(addr.to_string(), e))?;
    on_bound(local);
    let router = router_with_token_signed(store, token, key);
    slag_common::http::serve_with_tls(listener, router, limits, tls, async {
        let _ = tokio::signal::ctrl_c().await;
    })
    .await;
    Ok(())
}

fn error(status: StatusCode, message: String) -> Response {
    slag_common::http::error_response(status, message)
}

/// A store error as a response, its status by who has to act ([`slag_common::Error::kind`], one
/// arm per kind, no `_`): a store fault on this side or a slag bug is a 500.
fn internal(e: slag_common::Error) -> Response {
    use slag_common::ErrorKind;
    let status = match e.kind() {
        ErrorKind::UserInput => StatusCode::BAD_REQUEST,
        ErrorKind::Conflict => StatusCode::CONFLICT,
        ErrorKind::Upstream => StatusCode::BAD_GATEWAY,
        ErrorKind::Environment | ErrorKind::Internal => StatusCode::INTERNAL_SERVER_ERROR,
    };
    error(status, e.to_string())
}

/// The `{scene}` segment of a route, checked by [`valid_scene_id`]: any other id is answered
/// 400 before the handler runs (and is never used to look anything up).
struct SceneId(String);

impl<S: Send + Sync> FromRequestParts<S> for SceneId {
    type Rejection = Response;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, Response> {
        let Path(mut params) = Path::<HashMap<String, String>>::from_request_parts(parts, state)
            .await
            .map_err(IntoResponse::into_response)?;
        let scene = params.remove("scene").unwrap_or_default();
        if !valid_scene_id(&scene) {
            return Err(error(
                StatusCode::BAD_REQUEST,
                format!("invalid scene id {scene:?}: use 1-64 characters of A-Z a-z 0-9 _ - ."),
            ));
        }
        Ok(SceneId(scene))
    }
}

async fn scenes(State(store): State<Arc<ShardStore>>) -> Response {
    match store.scenes() {
        Ok(s) => axum::Json(serde_json::json!({ "scenes": s })).into_response(),
        Err(e) => internal(e),
    }
}

/// True when an `If-None-Match` header lists `etag` (or `*`). Weak comparison per RFC 9110.
fn none_match(headers: &HeaderMap, etag: &str) -> bool {
    headers
        .get_all(header::IF_NONE_MATCH)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .any(|v| {
            v.split(',')
                .map(str::trim)
                .any(|t| t == "*" || t.trim_start_matches("W/") == etag)
        })
}

async fn manifest(
    State(store): State<Arc<ShardStore>>,
    SceneId(scene): SceneId,
    headers: HeaderMap,
) -> Response {
    let json = match store.stored_manifest(&scene) {
        Ok(Some(m)) => Bytes::from_owner(m.bytes),
        Ok(None) => return error(StatusCode::NOT_FOUND, format!("unknown scene {scene:?}")),
        Err(e) => return internal(e),
    };
    let etag = format!("\"{:08x}\"", shard_checksum(&json));
    let etag_h = HeaderValue::from_str(&etag).unwrap_or(HeaderValue::from_static("\"0\""));
    if none_match(&headers, &etag) {
        return (StatusCode::NOT_MODIFIED, [(header::ETAG, etag_h)]).into_response();
    }
    (
        StatusCode::OK,
        [
            (
                header::CONTENT_TYPE,
                HeaderValue::from_static("application/json"),
            ),
            (header::ETAG, etag_h),
        ],
        json,
    )
        .into_response()
}

/// The state of the `manifest.sig` route: the store and the server's own signing key, if any.
struct Signer {
    store: ShardStore,
    key: Option<SigningKey>,
}

/// `GET /v1/scenes/{scene}/manifest.sig` (module doc).
async fn signature(State(signer): State<Arc<Signer>>, SceneId(scene): SceneId) -> Response {
    let m = match signer.store.stored_manifest(&scene) {
        Ok(Some(m)) => m,
        Ok(None) => return error(StatusCode::NOT_FOUND, format!("unknown scene {scene:?}")),
        Err(e) => return internal(e),
    };
    let body = match (&signer.key, m.signature) {
        (Some(k), _) => Bytes::from(k.sign(&m.bytes).to_json()),
        (None, Some(s)) => Bytes::from_owner(s),
        (None, None) => {
            return error(
                StatusCode::NOT_FOUND,
                format!(
                    "scene {scene:?} generation {} is not signed: partition it with a signing \
                     key, or serve with one",
                    m.generation
                ),
            );
        }
    };
    (
        StatusCode::OK,
        [(
            header::CONTENT_TYPE,
            HeaderValue::from_static("application/json"),
        )],
        body,
    )
        .into_response()
}

/// Outcome of parsing a `Range` header against a body of `len` bytes.
#[derive(Debug, PartialEq, Eq)]
enum RangeReq {
    /// Serve everything (no header, malformed, multi-range, or a non-`bytes` unit).
    Full,
    /// Inclusive byte range.
    Part(u64, u64),
    /// 416.
    Unsatisfiable,
}

fn parse_range(v: &str, len: u64) -> RangeReq {
    let Some(spec) = v.trim().strip_prefix("bytes=") else {
        return RangeReq::Full;
    };
    if spec.contains(',') {
        return RangeReq::Full;
    }
    let Some((a, b)) = spec.trim().split_once('-') else {
        return RangeReq::Full;
    };
    let num = |s: &str| {
        if s.bytes().all(|c| c.is_ascii_digit()) && !s.is_empty() {
            s.parse::<u64>().ok()
        } else {
            None
        }
    };
    match (a.trim(), b.trim()) {
        ("", "") => RangeReq::Full,
        ("", n) => match num(n) {
            Some(0) => RangeReq::Unsatisfiable,
            Some(_) if len == 0 => RangeReq::Unsatisfiable,
            Some(n) => RangeReq::Part(len.saturating_sub(n), len - 1),
            None => RangeReq::Full,
        },
        (s, e) => match (
            num(s),
            if e.is_empty() {
                Some(None)
            } else {
                num(e).map(Some)
            },
        ) {
            (Some(s), Some(e)) => {
                if e.is_some_and(|e| e < s) {
                    RangeReq::Full
                } else if s >= len {
                    RangeReq::Unsatisfiable
                } else {
                    RangeReq::Part(s, e.map_or(len - 1, |e| e.min(len - 1)))
                }
            }
            _ => RangeReq::Full,
        },
    }
}

async fn shard(
    State(store): State<Arc<ShardStore>>,
    SceneId(scene): SceneId,
    Path((_, id)): Path<(String, String)>,
    headers: HeaderMap,
) -> Response {
    let tile = match (id.len() <= 20 && id.bytes().all(|b| b.is_ascii_digit()))
        .then(|| id.parse::<u64>().ok())
        .flatten()
    {
        Some(t) => t,
        None => {
            return error(
                StatusCode::BAD_REQUEST,
                format!("invalid shard id {id:?}: use the decimal tile id from the manifest"),
            );
        }
    };
    let bytes = match store.shard(&scene, tile) {
        Ok(Some(b)) => b,
        Ok(None) => {
            return error(
                StatusCode::NOT_FOUND,
                format!("unknown shard {tile} of scene {scene:?}"),
            );
        }
        Err(e) => return internal(e),
    };
    file_response(bytes, &headers)
}

async fn codebook(
    State(store): State<Arc<ShardStore>>,
    SceneId(scene): SceneId,
    headers: HeaderMap,
) -> Response {
    match store.codebook(&scene) {
        Ok(Some(b)) => file_response(b, &headers),
        Ok(None) => error(
            StatusCode::NOT_FOUND,
            format!("scene {scene:?} has no codebook (unknown, or partitioned dense)"),
        ),
        Err(e) => internal(e),
    }
}

/// A stored file (shard or codebook) with its CRC-32 ETag, `If-None-Match` and single ranges.
/// The body is the store's buffer itself (`Bytes::from_owner`), never a copy.
fn file_response(stored: sled::IVec, headers: &HeaderMap) -> Response {
    let bytes = Bytes::from_owner(stored);
    let etag = format!("\"{:08x}\"", shard_checksum(&bytes));
    let etag_h = HeaderValue::from_str(&etag).unwrap_or(HeaderValue::from_static("\"0\""));
    if none_match(headers, &etag) {
        return (StatusCode::NOT_MODIFIED, [(header::ETAG, etag_h)]).into_response();
    }
    let len = bytes.len() as u64;
    let if_range_ok = headers
        .get(header::IF_RANGE)
        .is_none_or(|v| v.to_str().is_ok_and(|v| v.trim() == etag));
    let range = match headers.get(header::RANGE).and_then(|v| v.to_str().ok()) {
        Some(v) if if_range_ok => parse_range(v, len),
        _ => RangeReq::Full,
    };
    let common = [
        (header::ETAG, etag_h),
        (header::ACCEPT_RANGES, HeaderValue::from_static("bytes")),
        (
            header::CONTENT_TYPE,
            HeaderValue::from_static("application/octet-stream"),
        ),
    ];
    match range {
        RangeReq::Full => (StatusCode::OK, common, bytes).into_response(),
        RangeReq::Part(a, b) => {
            let cr = HeaderValue::from_str(&format!("bytes {a}-{b}/{len}"))
                .unwrap_or(HeaderValue::from_static("bytes */0"));
            let body = bytes.slice(a as usize..=b as usize);
            (
                StatusCode::PARTIAL_CONTENT,
                common,
                [(header::CONTENT_RANGE, cr)],
                body,
            )
                .into_response()
        }
        RangeReq::Unsatisfiable => {
            let cr = HeaderValue::from_str(&format!("bytes */{len}"))
                .unwrap_or(HeaderValue::from_static("bytes */0"));
            let mut r = error(
                StatusCode::RANGE_NOT_SATISFIABLE,
                format!(
                    "range not satisfiable: the file has {len} bytes; ask within 0-{}",
                    len.saturating_sub(1)
                ),
            );
            r.headers_mut().insert(header::CONTENT_RANGE, cr);
            r
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn range_parsing_follows_rfc9110() {
        assert_eq!(parse_range("bytes=0-9", 100), RangeReq::Part(0, 9));
        assert_eq!(parse_range("bytes=90-", 100), RangeReq::Part(90, 99));
        assert_eq!(parse_range("bytes=90-500", 100), RangeReq::Part(90, 99));
        assert_eq!(parse_range("bytes=-10", 100), RangeReq::Part(90, 99));
        assert_eq!(parse_range("bytes=-500", 100), RangeReq::Part(0, 99));
        assert_eq!(parse_range("bytes=100-", 100), RangeReq::Unsatisfiable);
        assert_eq!(parse_range("bytes=-0", 100), RangeReq::Unsatisfiable);
        assert_eq!(parse_range("bytes=5-2", 100), RangeReq::Full);
        assert_eq!(parse_range("bytes=0-1,5-6", 100), RangeReq::Full);
        assert_eq!(parse_range("items=0-1", 100), RangeReq::Full);
        assert_eq!(parse_range("bytes=x-1", 100), RangeReq::Full);
    }
}
