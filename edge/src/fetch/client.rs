//! The HTTP side of a fetch: the client (rustls, with a private CA's certificates), URLs, one
//! request's failure (transient or not) and the error a status means, and the manifest's
//! download (streamed under its size cap).

use std::time::Duration;

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

pub(super) fn net_error(url: &str, e: reqwest::Error) -> Attempt {
    let causes = slag_common::error::causes_once(&e);
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

/// GETs `url` (with the bearer `token`) and reads its body, refusing more than `cap` bytes
/// with `too_large(bytes seen)`: streamed with the cap, so a server that sends more is cut off
/// there, whatever its Content-Length said. Returns the status and the body.
///
/// Errors: [`Error::Network`]; `too_large`'s error.
pub(super) async fn get_capped(
    client: &reqwest::Client,
    url: &str,
    token: Option<&str>,
    cap: u64,
    too_large: impl Fn(u64) -> Error,
) -> Result<(reqwest::StatusCode, Vec<u8>)> {
    let mut req = client.get(url);
    if let Some(t) = token {
        req = req.bearer_auth(t);
    }
    let resp = req.send().await.map_err(|e| net_error(url, e).error)?;
    let status = resp.status();
    if let Some(len) = resp.content_length()
        && len > cap
    {
        return Err(too_large(len));
    }
    let mut body = Vec::new();
    let mut stream = resp.bytes_stream();
    while let Some(chunk) = stream.next().await {
        let chunk = chunk.map_err(|e| net_error(url, e).error)?;
        if (body.len() + chunk.len()) as u64 > cap {
            return Err(too_large((body.len() + chunk.len()) as u64));
        }
        body.extend_from_slice(&chunk);
    }
    Ok((status, body))
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
    let url = url_join(server, &format!("v1/scenes/{scene}/manifest"));
    let (status, body) = get_capped(client, &url, token, MAX_MANIFEST_BYTES, |n| {
        manifest_too_large(n, &url)
    })
    .await?;
    if !status.is_success() {
        return Err(status_error(&url, status, &String::from_utf8_lossy(&body)).error);
    }
    let m = Manifest::from_json(&body, &url)?;
    if m.scene_id != scene {
        return Err(Error::format(
            &url,
            format!(
                "manifest is for scene {:?}, asked for {scene:?}",
                m.scene_id
            ),
        ));
    }
    for t in &m.tiles {
        parse_checksum(t)?;
    }
    Ok((body, m))
}
