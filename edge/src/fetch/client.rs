//! The HTTP side of a fetch: the client (rustls, with a private CA's certificates), URLs, one
//! request's failure (transient or not) and the error a status means, the pace every transfer
//! must keep ([`Pace`]), and the manifest's download (streamed under its size cap).
//!
//! Errors name the URL that answered (after a redirect, the last one), and a wrong scheme (an
//! `https://` URL for a plain HTTP port, `http://` for a TLS port) is named with its fix.

use std::time::{Duration, Instant};

use futures_util::StreamExt;
use slag_common::shards::{MAX_MANIFEST_BYTES, Manifest, manifest_too_large};
use slag_common::{Error, Result};

use crate::store::parse_checksum;

pub(super) fn url_join(server: &str, path: &str) -> String {
    format!("{}/{}", server.trim_end_matches('/'), path)
}

/// A failure of one request: transient ones are retried.
pub(super) struct Attempt {
    pub(super) error: Error,
    pub(super) transient: bool,
}

pub(super) fn transient(error: Error) -> Attempt {
    Attempt {
        error,
        transient: true,
    }
}

pub(super) fn permanent(error: Error) -> Attempt {
    Attempt {
        error,
        transient: false,
    }
}

/// The deadline a transfer keeps: the request's head within the fetch's timeout, and after that
/// every byte at the least mean rate ([`super::FetchParams::min_rate`]), so a server that sends
/// a file a few bytes at a time (never idle long enough for the idle timeout) is cut off too.
#[derive(Debug, Clone, Copy)]
pub(super) struct Pace {
    start: Instant,
    grace: Duration,
    min_rate: u64,
}

impl Pace {
    /// A transfer starting now, with `grace` (the fetch's timeout) before the rate counts and
    /// `min_rate` bytes per second after (0: no deadline).
    pub(super) fn new(grace: Duration, min_rate: u64) -> Pace {
        Pace {
            start: Instant::now(),
            grace,
            min_rate,
        }
    }

    /// When the first `bytes` bytes of the body must have arrived (`None`: never).
    pub(super) fn due(&self, bytes: u64) -> Option<tokio::time::Instant> {
        (self.min_rate > 0).then(|| {
            let rest = Duration::from_secs_f64(bytes as f64 / self.min_rate as f64);
            tokio::time::Instant::from_std(self.start + self.grace + rest)
        })
    }

    /// `fut` (the head of a request, or the next chunk after `bytes` bytes) within its deadline.
    ///
    /// Errors: [`Error::Network`] naming `url`, the bytes received, the rate and the flags.
    pub(super) async fn within<T>(
        &self,
        url: &str,
        bytes: u64,
        fut: impl std::future::Future<Output = T>,
    ) -> std::result::Result<T, Attempt> {
        let Some(due) = self.due(bytes + 1) else {
            return Ok(fut.await);
        };
        tokio::time::timeout_at(due, fut).await.map_err(|_| {
            transient(Error::network(
                url,
                format!(
                    "{bytes} bytes in {:.1} s: slower than the least rate of {} bytes/s after \
                     the first {:.1} s (--min-rate, --timeout); the link is too slow or the \
                     server stalls",
                    self.start.elapsed().as_secs_f64(),
                    self.min_rate,
                    self.grace.as_secs_f64()
                ),
            ))
        })
    }
}

/// The URL a reqwest error is about (the one that answered, after a redirect), else `url`;
/// without user name and password.
fn answering_url(url: &str, e: &reqwest::Error) -> String {
    let u = e.url().map_or(url, reqwest::Url::as_str);
    slag_common::auth::redact_url(u).into_owned()
}

/// What a failed request says of a wrong scheme, with its fix: an `https://` URL for a port that
/// speaks plain HTTP (the TLS handshake reads an HTTP answer), or `http://` for a TLS port (the
/// HTTP parser reads a TLS record).
fn wrong_scheme(url: &str, causes: &str) -> Option<&'static str> {
    let c = causes.to_ascii_lowercase();
    if url.starts_with("https://")
        && (c.contains("invalidcontenttype")
            || c.contains("corrupt message")
            || c.contains("wrong version number")
            || c.contains("invalid message"))
    {
        Some(
            "the server does not speak TLS on this port: use http:// for a plain HTTP server \
             (or the port its TLS listens on)",
        )
    } else if url.starts_with("http://")
        && (c.contains("invalid http version") || c.contains("invalid http status"))
    {
        Some(
            "the server answered with something that is not HTTP, as a TLS port does: use \
             https:// (with --ca-cert for a private CA)",
        )
    } else {
        None
    }
}

pub(super) fn net_error(url: &str, e: reqwest::Error) -> Attempt {
    let causes = slag_common::error::causes_once(&e);
    let url = &answering_url(url, &e);
    if let Some(fix) = wrong_scheme(url, &causes) {
        // Not transient: the same port answers the same way on every retry.
        return permanent(Error::network(url, format!("{fix} ({causes})")));
    }
    if e.is_connect() && causes.contains("certificate") {
        // Not transient: the same certificate fails the same way on every retry.
        return permanent(Error::network(
            url,
            format!(
                "the server's TLS certificate is not trusted for this address; trust the \
                 certificate of the CA that issued it ({causes})"
            ),
        ));
    }
    let what = if e.is_timeout() {
        "timed out; check the link or raise the timeout"
    } else if e.is_connect() {
        "cannot connect; is `slag-encoder serve` running there and reachable?"
    } else {
        "transfer failed"
    };
    transient(Error::network(url, format!("{what} ({causes})")))
}

pub(super) fn status_error(url: &str, status: reqwest::StatusCode, body: &str) -> Attempt {
    // What the status means for a fetch; `slag-edge` adds the flag (its hint reads `status`).
    let hint = match status.as_u16() {
        401 | 403 => "the server wants a bearer token (the fetch's token)",
        404 => {
            "not on the server: check the scene id, or fetch again if the scene was \
                re-partitioned"
        }
        _ => "",
    };
    let error = Error::http_status(
        url,
        status.as_u16(),
        format!(
            "HTTP {status}: {} {hint}",
            body.chars().take(300).collect::<String>()
        ),
    );
    if status.is_server_error() || status.as_u16() == 429 {
        transient(error)
    } else {
        permanent(error)
    }
}

/// Builds the HTTP client (rustls, timeouts, no proxy surprises).
///
/// Errors: [`Error::Internal`] if the TLS backend cannot be initialised.
pub fn client(timeout: Duration) -> Result<reqwest::Client> {
    client_trusting(timeout, None)
}

/// [`client`] that also trusts the CA certificates in the PEM file `ca_cert` for `https://`
/// servers: in addition to the built-in roots (Mozilla's list, compiled in), so a public server
/// still verifies; the server's name (or IP address) must be in its certificate either way.
///
/// Errors: [`Error::Io`] when `ca_cert` cannot be read, [`Error::Format`] when it holds no PEM
/// certificate; [`Error::Internal`] if the TLS backend cannot be initialised.
pub fn client_trusting(
    timeout: Duration,
    ca_cert: Option<&std::path::Path>,
) -> Result<reqwest::Client> {
    let mut b = reqwest::Client::builder()
        .connect_timeout(timeout)
        .read_timeout(timeout)
        .user_agent(concat!("slag-edge/", env!("CARGO_PKG_VERSION")));
    if let Some(path) = ca_cert {
        let pem = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        let certs = reqwest::Certificate::from_pem_bundle(&pem)
            .ok()
            .filter(|c| !c.is_empty())
            .ok_or_else(|| {
                Error::format(
                    path,
                    "no PEM certificate (-----BEGIN CERTIFICATE-----): pass the CA certificate \
                     that issued the shard server's certificate",
                )
            })?;
        for c in certs {
            b = b.add_root_certificate(c);
        }
    }
    b.build()
        .map_err(|e| Error::internal(format!("HTTP client: {e}")))
}

/// Downloads and parses the scene's manifest.
///
/// Errors: [`Error::Network`] (unreachable, non-2xx), [`Error::Limit`]
/// [`slag_common::Resource::ManifestBytes`] (more than [`MAX_MANIFEST_BYTES`]), [`Error::Format`]
/// (not a manifest, sizes the shard format does not allow, or one of another scene).
pub async fn fetch_manifest(
    client: &reqwest::Client,
    server: &str,
    scene: &str,
    token: Option<&str>,
) -> Result<Manifest> {
    fetch_manifest_bytes(client, server, scene, token)
        .await
        .map(|(_, m)| m)
}

/// A body read by [`get_capped`]: its status, the URL that answered (after a redirect, the last
/// one; without user name and password) and its bytes.
pub(super) struct Answer {
    pub(super) status: reqwest::StatusCode,
    pub(super) url: String,
    pub(super) body: Vec<u8>,
}

/// GETs `url` (with the bearer `token`) and reads its body at `pace`, refusing more than `cap`
/// bytes with `too_large(bytes seen)`: streamed with the cap, so a server that sends more is cut
/// off there, whatever its Content-Length said.
///
/// Errors: [`Error::Network`] (a transfer slower than `pace` too); `too_large`'s error.
pub(super) async fn get_capped(
    client: &reqwest::Client,
    url: &str,
    token: Option<&str>,
    cap: u64,
    pace: Pace,
    too_large: impl Fn(u64) -> Error,
) -> Result<Answer> {
    let mut req = client.get(url);
    if let Some(t) = token {
        req = req.bearer_auth(t);
    }
    let resp = pace
        .within(url, 0, req.send())
        .await
        .map_err(|a| a.error)?
        .map_err(|e| net_error(url, e).error)?;
    let status = resp.status();
    let answered = slag_common::auth::redact_url(resp.url().as_str()).into_owned();
    if let Some(len) = resp.content_length()
        && len > cap
    {
        return Err(too_large(len));
    }
    let mut body = Vec::new();
    let mut stream = resp.bytes_stream();
    loop {
        let next = pace.within(&answered, body.len() as u64, stream.next());
        let Some(chunk) = next.await.map_err(|a| a.error)? else {
            break;
        };
        let chunk = chunk.map_err(|e| net_error(&answered, e).error)?;
        if (body.len() + chunk.len()) as u64 > cap {
            return Err(too_large((body.len() + chunk.len()) as u64));
        }
        body.extend_from_slice(&chunk);
    }
    Ok(Answer {
        status,
        url: answered,
        body,
    })
}

/// [`fetch_manifest`], also returning the manifest's bytes exactly as the server sent them
/// (what a signature covers).
///
/// Errors: as [`fetch_manifest`].
pub async fn fetch_manifest_bytes(
    client: &reqwest::Client,
    server: &str,
    scene: &str,
    token: Option<&str>,
) -> Result<(Vec<u8>, Manifest)> {
    fetch_manifest_paced(client, server, scene, token, Pace::new(Duration::ZERO, 0)).await
}

/// [`fetch_manifest_bytes`] at `pace`.
///
/// Errors: as [`fetch_manifest`]; a transfer slower than `pace` ([`Error::Network`]).
pub(super) async fn fetch_manifest_paced(
    client: &reqwest::Client,
    server: &str,
    scene: &str,
    token: Option<&str>,
    pace: Pace,
) -> Result<(Vec<u8>, Manifest)> {
    let (url, body) = get_manifest(client, server, scene, token, pace).await?;
    let m = parse_manifest(&body, &url, scene)?;
    Ok((body, m))
}

/// The manifest's bytes as the server sent them, and its URL (the one that answered); not
/// parsed.
///
/// Errors: [`Error::Network`] (unreachable, non-2xx, slower than `pace`), [`Error::Limit`]
/// [`slag_common::Resource::ManifestBytes`] (more than [`MAX_MANIFEST_BYTES`]).
pub(super) async fn get_manifest(
    client: &reqwest::Client,
    server: &str,
    scene: &str,
    token: Option<&str>,
    pace: Pace,
) -> Result<(String, Vec<u8>)> {
    let url = url_join(server, &format!("v1/scenes/{scene}/manifest"));
    let a = get_capped(client, &url, token, MAX_MANIFEST_BYTES, pace, |n| {
        manifest_too_large(n, &url)
    })
    .await?;
    if !a.status.is_success() {
        return Err(status_error(&a.url, a.status, &String::from_utf8_lossy(&a.body)).error);
    }
    Ok((a.url, a.body))
}

/// Parses the manifest `body` from `url` for `scene` and checks what a fetch needs of it: the
/// format's checks ([`Manifest::from_json`]), the scene id, every tile's checksum.
///
/// Errors: [`Error::Format`] (not a manifest, sizes the shard format does not allow, another
/// scene's, a checksum that is not 8 hex digits).
pub(super) fn parse_manifest(body: &[u8], url: &str, scene: &str) -> Result<Manifest> {
    let m = Manifest::from_json(body, url)?;
    if m.scene_id != scene {
        return Err(Error::format(
            url,
            format!("manifest is for scene {}, asked for {scene}", m.scene_id),
        ));
    }
    for t in &m.tiles {
        parse_checksum(t)?;
    }
    Ok(m)
}
