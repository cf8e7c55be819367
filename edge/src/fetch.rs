//! `slag-edge fetch`: download the shards around the robot into the [`EdgeStore`].
//!
//! 1. `GET {server}/v1/scenes/{scene}/manifest` (the shard server of `slag-encoder serve`);
//! 2. tiles whose footprint meets the closed disc (centre, radius) on the manifest's ground plane
//!    ([`select_tiles`] → [`slag_common::shards::TileIndex::select_tiles`], an `rstar` R-tree);
//!    centre and radius are in the robot's map frame (metres) when the manifest has a
//!    scene-to-map transform, converted by [`selection_disc`];
//!    The manifest is read as a stream and refused past
//!    [`slag_common::shards::MAX_MANIFEST_BYTES`]; its declared sizes must be ones the shard
//!    format allows ([`Manifest::check_sizes`]), so a manifest declaring a 10^12-byte tile is
//!    refused before anything is written;
//! 3. every selected tile's stored file is checked ([`EdgeStore::check_stored`]: length, CRC-32,
//!    header); one that fails (flipped bytes, truncated, appended to, another tile's bytes, a
//!    folder in its place) is set aside into the store's `quarantine/` ([`EdgeStore::set_aside`])
//!    and downloaded again, like a tile never stored. Before any download, the bytes still to
//!    come are compared with the free space of the store's file system ([`Error::Limit`]
//!    [`slag_common::Resource::DiskSpace`]);
//! 4. each selected tile not already stored and verified is downloaded into
//!    `partial/<scene>-<tile>-<checksum>.part`, resumed with `Range: bytes=N-` + `If-Range` when a
//!    previous run was interrupted, verified ([`crate::store::verify_shard`]) and renamed into the
//!    store's shard folder ([`EdgeStore::commit_partial`]);
//!    A mixture scene's codebook (manifest [`slag_common::shards::MixtureInfo`]) is fetched the
//!    same way first, as `partial/<scene>-<u64::MAX>-<checksum>.part` from
//!    `{server}/v1/scenes/{scene}/codebook`, verified ([`crate::store::verify_codebook`]: length,
//!    CRC-32, header) and renamed into place ([`EdgeStore::commit_codebook_partial`]);
//! 5. when every selected tile is stored, the manifest and a [`FetchRecord`] are committed in one
//!    transaction (a new partition generation becomes visible at once, never half);
//! 6. shards that no manifest references any more (an older generation) are dropped; shards of the
//!    current manifest outside the disc are kept unless [`FetchParams::prune`] is set.
//!
//! # Signed manifests
//!
//! With [`FetchParams::trusted_key`] the manifest must come with the publisher's signature
//! (`GET {server}/v1/scenes/{scene}/manifest.sig`, [`slag_common::shards::signature`]) over its
//! exact bytes, which name the generation and every file's SHA-256. Before anything is
//! downloaded the fetch refuses ([`Error::Untrusted`], naming what failed) a manifest without a
//! signature, signed by another key, changed after signing, without a SHA-256 for every file,
//! or of an older generation than the store holds (a replay). Each download is checked against
//! its SHA-256 before it is committed (a tile rewritten on the way, or another scene's tile,
//! is refused), and stored files the fetch would keep are hashed too
//! ([`EdgeStore::check_stored_signed`]). On any refusal nothing of the new generation is
//! committed: the store keeps its last committed generation. The manifest's bytes and
//! signature are committed with the generation ([`EdgeStore::commit_fetch_signed`]), so
//! `slag-edge check` can verify them again offline. Without a trusted key nothing of this is
//! asked or checked (the manifest's CRC-32s only).
//!
//! # Fault injection (tests only)
//!
//! Every step of a fetch that changes the disk is a durability boundary of
//! [`slag_common::fault`], named `site:step`: `fetch.partial:create` (a partial file opened
//! empty), `fetch.partial:write` (each chunk written), `fetch.partial:fsync`, `fetch.partial:
//! remove_oversized`; in the store ([`EdgeStore`]) the verified partial file's `rename` into
//! `shards/` and the folder syncs (`store.commit_shard:*`, `store.commit_codebook:*`), the
//! scene folder's creation, a damaged file set aside (`store.set_aside:*`), the manifest and
//! fetch-record copies (`store.manifest_copy:*`, `store.fetch_record_copy:*`: write, fsync,
//! rename, folder sync; for a signed fetch `store.signature_copy:*` too, or its removal by an
//! unsigned one), the sled transaction and flush of the commit
//! (`store.commit_fetch:transaction`, `:flush`), each eviction (`store.evict_shard:remove`,
//! `store.evict_codebook:remove`), each partial file cleaned away and the final flush; and
//! `fetch:before_commit`, the moment every shard of the new generation is in place and nothing
//! is committed yet. With `SLAG_FAULT_EXIT_AT=<n>` the process exits with status 137 (as if
//! SIGKILLed) at the n-th boundary; with `SLAG_FAULT_LIST=<path>` it lists the boundaries it
//! passes; `edge/tests/crash_points.rs` stops a fetch (and a `serve` fetching through
//! `POST /fetch`) at every one in turn and checks what a restart serves. Unset (the normal
//! case) each costs one atomic load. With `SLAG_FAULT_ENOSPC_AT=<n>` the n-th write to a partial
//! file fails as if the disk were full ([`slag_common::fault::enospc`]).
//!
//! # Partial files after a failure
//!
//! A fetch that fails for a network reason (timeout, dropped connection, 5xx after its retries)
//! keeps its partial files, so the next run resumes them with `Range` requests; they never exceed
//! the manifest's sizes, which the free-space check counted. Any other failure (the disk full or
//! failing, a shard that fails verification, a store error) removes the scene's partial files
//! before the error is returned.

use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use futures_util::{StreamExt, TryStreamExt};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use slag_common::fault::boundary;
use slag_common::shards::{
    CODEBOOK_TILE, MAP_FRAME, MAX_MANIFEST_BYTES, Manifest, SCENE_FRAME, TileInfo,
    manifest_too_large, valid_scene_id,
};
use slag_common::{Error, Result};
use tokio::io::AsyncWriteExt;

use crate::query::{FrameChoice, answer_frame};
use crate::store::{EdgeStore, FetchRecord, SignedManifest, Stored, codebook_tile, parse_checksum};
use slag_common::shards::signature::{self, MAX_SIGNATURE_BYTES, TrustedKey};

/// The disc to select, on the manifest's ground plane: `(centre (g0, g1), radius in scene
/// units, frame name)`. In the map frame (module doc of [`Center`]) the centre is mapped back by
/// the inverse scene-to-map transform and the radius divided by its scale (`r` metres =
/// `r / s` scene units).
///
/// Errors: [`Error::Param`] `radius` for a negative or non-finite radius, [`Error::Query`]
/// `frame` for `frame` map when the manifest has no transform.
pub fn selection_disc(
    manifest: &Manifest,
    center: Center,
    radius: f64,
    frame: FrameChoice,
) -> Result<([f64; 2], f64, &'static str)> {
    let map = answer_frame(frame, manifest.frames.scene_to_map.as_ref())?;
    if !(radius.is_finite() && radius >= 0.0) {
        return Err(Error::param(
            "radius",
            radius,
            format!(
                "a finite number ≥ 0 ({})",
                if map.is_some() {
                    "metres of the map frame"
                } else {
                    "scene units"
                }
            ),
        ));
    }
    let ground = |w: [f64; 3]| {
        let g = manifest
            .ground
            .to_ground([w[0] as f32, w[1] as f32, w[2] as f32]);
        [g[0], g[1]]
    };
    Ok(match map {
        None => {
            let c = match center {
                Center::Ground(g) => g,
                Center::World(w) => ground(w),
            };
            (c, radius, SCENE_FRAME)
        }
        Some(t) => {
            let m = match center {
                Center::Ground([x, y]) => [x, y, 0.0],
                Center::World(w) => w,
            };
            // The ground projection in f64 (to_ground takes f32 points): far-away map origins
            // (UTM) would lose centimetres in f32.
            let s = t.to_scene(m);
            let r = manifest
                .ground
                .world_to_ground
                .map(|row| row.map(f64::from));
            let g = [0, 1].map(|i| r[i][0] * s[0] + r[i][1] * s[1] + r[i][2] * s[2]);
            (g, t.map_to_scene_distance(radius), MAP_FRAME)
        }
    })
}

/// The manifest's tiles whose footprint meets the disc of [`selection_disc`] (ascending id):
/// what a fetch downloads.
///
/// Errors: as [`selection_disc`].
pub fn select_tiles(
    manifest: &Manifest,
    center: Center,
    radius: f64,
    frame: FrameChoice,
) -> Result<Vec<TileInfo>> {
    let (c, r, _) = selection_disc(manifest, center, radius, frame)?;
    Ok(manifest
        .tile_index()
        .select_tiles(c, r)
        .into_iter()
        .filter_map(|id| manifest.tiles.iter().find(|t| t.id == id).cloned())
        .collect())
}

/// Where the disc is centred.
///
/// In the **map frame** (metres) when the manifest has a scene-to-map transform and the fetch's
/// [`FetchParams::frame`] is auto or map: `X,Y` is the map point `(X, Y, 0)` and `X,Y,Z` the map
/// point itself; either is taken back to the scene with the inverse transform and projected onto
/// the manifest's ground plane (partitions with a transform tile on the map's ground, whose up is
/// the map's z, so the height of a map point then does not change the disc). In the **scene
/// frame** otherwise, as below.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Center {
    /// Scene frame: ground-plane coordinates `(g0, g1)` of the manifest's
    /// [`slag_common::shards::GroundFrame`]. Map frame: the map point `(X, Y, 0)`.
    Ground([f64; 2]),
    /// Scene frame: a world point, projected onto the ground plane with
    /// [`slag_common::shards::GroundFrame::to_ground`]. Map frame: a map point.
    World([f64; 3]),
}

impl std::str::FromStr for Center {
    type Err = String;
    /// `"X,Y"` (ground) or `"X,Y,Z"` (world); finite numbers.
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        let v: Vec<f64> = s
            .split(',')
            .map(|p| p.trim().parse::<f64>())
            .collect::<std::result::Result<_, _>>()
            .map_err(|e| format!("center {s:?}: {e}; use X,Y (ground) or X,Y,Z (world)"))?;
        if !v.iter().all(|x| x.is_finite()) {
            return Err(format!("center {s:?} has a non-finite coordinate"));
        }
        match v[..] {
            [x, y] => Ok(Center::Ground([x, y])),
            [x, y, z] => Ok(Center::World([x, y, z])),
            _ => Err(format!(
                "center {s:?}: expected 2 (ground X,Y) or 3 (world X,Y,Z) numbers"
            )),
        }
    }
}

/// What to fetch and how.
#[derive(Debug, Clone)]
pub struct FetchParams {
    /// Shard server base URL, e.g. `http://10.0.0.2:8090`.
    pub server: String,
    /// A private CA's certificate(s), PEM, trusted for an `https://` server in addition to the
    /// built-in roots ([`client_trusting`]); `None`: the built-in roots alone.
    pub ca_cert: Option<std::path::PathBuf>,
    /// Scene id.
    pub scene: String,
    /// Disc centre.
    pub center: Center,
    /// Disc radius (≥ 0, finite): metres in the map frame, scene units in the scene frame.
    pub radius: f64,
    /// Frame of `center` and `radius`: auto (the default) = the map frame when the manifest has
    /// a scene-to-map transform, else the scene frame ([`selection_disc`]).
    pub frame: FrameChoice,
    /// Drop stored shards outside the disc.
    pub prune: bool,
    /// Parallel downloads (≥ 1).
    pub jobs: usize,
    /// Retries per shard after a transient failure (connection drop, timeout, 5xx).
    pub retries: u32,
    /// Connect and read (idle) timeout per request.
    pub timeout: Duration,
    /// Bearer token for the shard server, if it requires one.
    pub token: Option<String>,
    /// Draw a progress bar on stderr (when it is a terminal).
    pub progress: bool,
    /// The publisher's public key: only a manifest it signed, and files matching that
    /// manifest's SHA-256s, are accepted (module doc, "Signed manifests"). `None`: unsigned
    /// manifests are accepted as they are.
    pub trusted_key: Option<TrustedKey>,
}

/// What a fetch did.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct FetchSummary {
    /// Scene id.
    pub scene: String,
    /// Partition generation of the manifest now current.
    pub generation: u64,
    /// Frame the centre and radius were read in: `"map"` (metres) or `"scene"` (scene units).
    pub frame: String,
    /// The radius in scene units on the manifest's ground plane (= the radius in the scene frame,
    /// radius / scale in the map frame).
    pub scene_radius: f64,
    /// Tiles in the disc.
    pub selected: usize,
    /// Of those, already stored and verified (length, CRC-32, header).
    pub skipped: usize,
    /// Stored files of selected tiles that failed verification (or were not files), set aside
    /// into the store's `quarantine/` folder and downloaded again.
    pub set_aside: usize,
    /// Downloaded in this run (including resumed ones).
    pub downloaded: usize,
    /// Downloads that continued a partial file with a `Range` request.
    pub resumed: usize,
    /// Shards dropped: older generations, plus those outside the disc with `--prune`.
    pub evicted: usize,
    /// Tiles of the manifest stored outside the disc (kept without `--prune`).
    pub kept_outside: usize,
    /// Gaussians in the selected tiles.
    pub gaussians: u64,
    /// Shard bytes in the selected tiles.
    pub shard_bytes: u64,
    /// Bytes received over the network in this run.
    pub bytes_received: u64,
    /// Store size on disk afterwards.
    pub store_bytes: u64,
    /// Mixture scenes: bytes of the scene's codebook (downloaded now or already stored); 0 for
    /// a dense scene.
    pub codebook_bytes: u64,
}

impl std::fmt::Display for FetchSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "scene {} generation {} ({} frame{}): {} shards in the radius ({} downloaded, {} \
             resumed, {} already stored and verified, {} damaged set aside), {} Gaussians, {:.1} \
             MB of shards, {:.1} MB received; {} outside the radius kept, {} evicted; store {:.1} \
             MB on disk{}",
            self.scene,
            self.generation,
            self.frame,
            if self.frame == MAP_FRAME {
                format!(", radius {:.6} scene units", self.scene_radius)
            } else {
                String::new()
            },
            self.selected,
            self.downloaded,
            self.resumed,
            self.skipped,
            self.set_aside,
            self.gaussians,
            self.shard_bytes as f64 / 1e6,
            self.bytes_received as f64 / 1e6,
            self.kept_outside,
            self.evicted,
            self.store_bytes as f64 / 1e6,
            if self.codebook_bytes > 0 {
                format!(
                    " (mixture scene: codebook {:.1} MB)",
                    self.codebook_bytes as f64 / 1e6
                )
            } else {
                String::new()
            }
        )
    }
}

fn url_join(server: &str, path: &str) -> String {
    format!("{}/{}", server.trim_end_matches('/'), path)
}

/// A failure of one request: transient ones are retried.
struct Attempt {
    error: Error,
    transient: bool,
}

fn transient(error: Error) -> Attempt {
    Attempt {
        error,
        transient: true,
    }
}
fn permanent(error: Error) -> Attempt {
    Attempt {
        error,
        transient: false,
    }
}

fn net_error(url: &str, e: reqwest::Error) -> Attempt {
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

fn status_error(url: &str, status: reqwest::StatusCode, body: &str) -> Attempt {
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
async fn get_capped(
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

/// The scene's manifest, and with [`FetchParams::trusted_key`] its verified signature (module
/// doc, "Signed manifests"): the signature file is fetched, checked against the manifest's
/// exact bytes, the manifest must name every file's SHA-256, and its generation must not be
/// older than the one `store` holds.
///
/// Errors: as [`fetch_manifest`]; [`Error::Untrusted`] naming the failed check.
pub async fn fetch_trusted_manifest(
    client: &reqwest::Client,
    store: &EdgeStore,
    p: &FetchParams,
) -> Result<(Manifest, Option<SignedManifest>)> {
    let Some(key) = &p.trusted_key else {
        let token = p.token.as_deref();
        let (_, manifest) = fetch_manifest_bytes(client, &p.server, &p.scene, token).await?;
        return Ok((manifest, None));
    };
    // The publisher may commit a generation between the two requests, so that the signature
    // is of the other generation's bytes: one more pair settles it.
    let (manifest, signed) = match fetch_signed_manifest(client, p, key).await {
        Err(Error::Untrusted {
            what: slag_common::Untrusted::BadSignature,
            ..
        }) => fetch_signed_manifest(client, p, key).await?,
        r => r?,
    };
    let origin = url_join(&p.server, &format!("v1/scenes/{}/manifest", p.scene));
    signature::check_hashes(&manifest, &origin)?;
    // A stored manifest that no longer parses (a damaged store) does not block the fetch that
    // repairs it.
    if let Ok(Some(held)) = store.manifest(&p.scene) {
        signature::check_generation(&p.scene, held.generation, manifest.generation, &origin)?;
    }
    Ok((manifest, Some(signed)))
}

/// One request for the manifest and one for its signature
/// (`GET {server}/v1/scenes/{scene}/manifest.sig`), the signature checked with `key` against the
/// manifest's exact bytes.
///
/// Errors: as [`fetch_manifest`]; [`Error::Untrusted`] for no signature (404), another key's,
/// or one that does not hold.
async fn fetch_signed_manifest(
    client: &reqwest::Client,
    p: &FetchParams,
    key: &TrustedKey,
) -> Result<(Manifest, SignedManifest)> {
    let token = p.token.as_deref();
    let (bytes, manifest) = fetch_manifest_bytes(client, &p.server, &p.scene, token).await?;
    let origin = url_join(&p.server, &format!("v1/scenes/{}/manifest", p.scene));
    let sig_url = format!("{origin}.sig");
    let (status, sig) = get_capped(client, &sig_url, token, MAX_SIGNATURE_BYTES, |n| {
        Error::untrusted(
            slag_common::Untrusted::BadSignature,
            &sig_url,
            format!("{n} bytes, more than a signature file ({MAX_SIGNATURE_BYTES})"),
        )
    })
    .await?;
    if status == reqwest::StatusCode::NOT_FOUND {
        return Err(Error::untrusted(
            slag_common::Untrusted::Unsigned,
            &origin,
            format!(
                "the server has no signature for generation {} ({sig_url} answered 404), and a \
                 trusted key is required: the publisher has to sign the scene with its key; to \
                 accept an unsigned map, fetch without a trusted key",
                manifest.generation
            ),
        ));
    }
    if !status.is_success() {
        return Err(status_error(&sig_url, status, &String::from_utf8_lossy(&sig)).error);
    }
    key.verify(&bytes, &sig, &origin)?;
    Ok((
        manifest,
        SignedManifest {
            bytes,
            signature: sig,
        },
    ))
}

/// Runs a fetch (steps in the module doc). Fetches into one store run one at a time; steps 5
/// and 6 hold the store's generation lock, so a concurrent load sees one committed generation.
///
/// Errors: bad parameters ([`Error::Param`]; `server` for a URL with a user name or password,
/// [`slag_common::auth::refuse_credentials_in_url`]), the server ([`Error::Network`]), a manifest too
/// large or whose sizes the shard format does not allow ([`Error::Limit`], [`Error::Format`]),
/// not enough free disk space for what is to be downloaded ([`Error::Limit`]
/// [`slag_common::Resource::DiskSpace`], naming the folder), a shard that fails verification
/// twice ([`Error::Format`]), with [`FetchParams::trusted_key`] a manifest or file the key does
/// not vouch for ([`Error::Untrusted`], module doc "Signed manifests"), store I/O. On error the
/// store keeps every shard completed so far and the previous manifest stays current; rerunning
/// resumes (partial files are kept only after a network failure: module doc).
pub async fn fetch(store: &EdgeStore, p: &FetchParams) -> Result<FetchSummary> {
    fetch_classified(store, p).await.map_err(|f| f.error)
}

/// A failed [`fetch_classified`]: the error [`fetch`] returns, and whether it is the shard
/// server's manifest that was refused.
#[derive(Debug)]
pub struct FetchFailure {
    /// What went wrong, as [`fetch`] returns it.
    pub error: Error,
    /// The manifest the shard server sent was refused by [`fetch_manifest`]: not a manifest,
    /// too large, sizes the shard format does not allow, not a set of tiles, another scene's, or
    /// (with a trusted key) not signed by it, without SHA-256s or of an older generation.
    /// The server's fault, not this side's; nothing was downloaded. `false` for a network
    /// failure ([`Error::Network`] says that already) and every later step.
    pub bad_manifest: bool,
}

/// [`fetch`], telling a manifest the shard server sent that cannot be used from every other
/// failure ([`FetchFailure::bad_manifest`]).
///
/// Errors: as [`fetch`].
pub async fn fetch_classified(
    store: &EdgeStore,
    p: &FetchParams,
) -> std::result::Result<FetchSummary, FetchFailure> {
    // One fetch at a time per store (a second one waits): [`EdgeStore::lock_fetching`].
    let _one = store.lock_fetching().await;
    let mut bad_manifest = false;
    let r = fetch_inner(store, p, &mut bad_manifest).await;
    if let Err(e) = &r
        && !matches!(e, Error::Network { .. })
    {
        let store = store.clone();
        let scene = p.scene.clone();
        let cleaned = tokio::task::spawn_blocking(move || store.clean_partials(&scene, &[])).await;
        match cleaned {
            // A refusal by the trusted key is reported once, as the error itself.
            Ok(Ok(n)) if n > 0 && matches!(e, Error::Untrusted { .. }) => {
                tracing::debug!("removed {n} partial download(s) of scene {}", p.scene)
            }
            Ok(Ok(n)) if n > 0 => {
                tracing::warn!(
                    "removed {n} partial download(s) of scene {} after: {e}",
                    p.scene
                )
            }
            Ok(Ok(_)) => {}
            Ok(Err(c)) => tracing::warn!("partial downloads not removed: {c}"),
            Err(c) => tracing::warn!("partial downloads not removed: {c}"),
        }
    }
    r.map_err(|error| FetchFailure {
        error,
        bad_manifest,
    })
}

/// [`fetch`] without the clean-up of partial files after a failure; sets `bad_manifest` when
/// [`fetch_manifest`] refuses what the server sent.
async fn fetch_inner(
    store: &EdgeStore,
    p: &FetchParams,
    bad_manifest: &mut bool,
) -> Result<FetchSummary> {
    check_fetch_params(p)?;
    let client = client_trusting(p.timeout, p.ca_cert.as_deref())?;
    let (manifest, signed) = fetch_trusted_manifest(&client, store, p)
        .await
        .inspect_err(|e| *bad_manifest = !matches!(e, Error::Network { .. }))?;
    let hashed = signed.is_some();
    let (center, scene_radius, frame) = selection_disc(&manifest, p.center, p.radius, p.frame)?;
    let selected = select_tiles(&manifest, p.center, p.radius, p.frame)?;

    let mut summary = FetchSummary {
        scene: p.scene.clone(),
        generation: manifest.generation,
        frame: frame.into(),
        scene_radius,
        selected: selected.len(),
        gaussians: selected.iter().map(|t| t.count).sum(),
        shard_bytes: selected.iter().map(|t| t.bytes).sum(),
        ..Default::default()
    };
    // "Already stored" means verified (module doc, step 3): anything else at a tile's path is
    // set aside and the tile downloaded again. The codebook of a mixture scene is checked the
    // same way, first: no row can be scored without it.
    let codebook = codebook_tile(&manifest);
    if let Some(t) = &codebook {
        summary.codebook_bytes = t.bytes;
    }
    let tiles: Vec<TileInfo> = codebook.iter().chain(&selected).cloned().collect();
    let (checked, manifest) = check_stored_tiles(store, manifest, tiles, hashed).await?;
    let (todo, codebook_todo) = plan_downloads(checked, codebook.as_ref(), &mut summary);
    let total: u64 = todo.iter().chain(&codebook_todo).map(|t| t.bytes).sum();
    check_free_space(store, &manifest, todo.iter().chain(&codebook_todo))?;
    let downloads = Downloads {
        client: &client,
        store,
        manifest: Arc::new(manifest),
        p,
        pb: progress_bar(p.progress, total, todo.len()),
    };
    downloads.run(codebook_todo, todo, &mut summary).await?;

    let record = FetchRecord {
        server: p.server.clone(),
        center,
        radius: scene_radius,
        completed_unix_s: SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map(|d| d.as_secs())
            .unwrap_or(0),
        tiles: None,
    };
    let manifest = downloads.manifest;
    let (evicted, kept_outside) = {
        let (store, manifest, prune) = (store.clone(), manifest.clone(), p.prune);
        tokio::task::spawn_blocking(move || {
            commit_and_evict(&store, &manifest, signed.as_ref(), &selected, record, prune)
        })
        .await
        .map_err(|e| Error::internal(format!("store task failed: {e}")))??
    };
    summary.evicted += evicted;
    summary.kept_outside += kept_outside;
    summary.evicted += tidy_after_commit(store, &p.scene, &manifest)?;
    summary.store_bytes = store.disk_bytes();
    Ok(summary)
}

/// Refuses the parameters of a fetch before anything is logged, requested or recorded.
///
/// Errors: [`Error::Param`] `server` for a URL with a user name or password (a secret in the
/// URL would be logged, requested and recorded), `scene_id`, `radius` (not finite or
/// negative), `jobs` (0).
fn check_fetch_params(p: &FetchParams) -> Result<()> {
    slag_common::auth::refuse_credentials_in_url(&p.server, "server")?;
    if !valid_scene_id(&p.scene) {
        return Err(Error::param(
            "scene_id",
            format!("{:?}", p.scene),
            "1-64 characters of A-Z a-z 0-9 _ - .",
        ));
    }
    if !(p.radius.is_finite() && p.radius >= 0.0) {
        return Err(Error::param(
            "radius",
            p.radius,
            "a finite number ≥ 0 (metres with a map frame, else scene units)",
        ));
    }
    if p.jobs == 0 {
        return Err(Error::param("jobs", 0, "at least 1 download at a time"));
    }
    Ok(())
}

/// Step 3 of the module doc on the blocking pool: checks what the store holds for each of
/// `tiles` against `manifest` (hashes too when `hashed`), setting a damaged file aside under the
/// generation lock. Returns each tile with what was found, and `manifest` back.
///
/// Errors: store I/O; a failed task ([`Error::Internal`]).
async fn check_stored_tiles(
    store: &EdgeStore,
    manifest: Manifest,
    tiles: Vec<TileInfo>,
    hashed: bool,
) -> Result<(Vec<(TileInfo, Stored)>, Manifest)> {
    let store = store.clone();
    tokio::task::spawn_blocking(move || {
        let mut out = Vec::with_capacity(tiles.len());
        for t in tiles {
            let state = match store.check_stored_signed(&manifest, &t, hashed)? {
                Stored::Damaged { path, why } => {
                    // A load in progress reads the committed generation whole.
                    let _generation = store.lock_generation();
                    store.set_aside(&path, &why)?;
                    Stored::Damaged { path, why }
                }
                s => s,
            };
            out.push((t, state));
        }
        Ok::<_, Error>((out, manifest))
    })
    .await
    .map_err(|e| Error::internal(format!("store task failed: {e}")))?
}

/// What to download after [`check_stored_tiles`]: the shards not verified in the store, and the
/// codebook (`codebook`'s tile) when it is not; counts the verified shards (`skipped`) and the
/// files set aside in `summary`.
fn plan_downloads(
    checked: Vec<(TileInfo, Stored)>,
    codebook: Option<&TileInfo>,
    summary: &mut FetchSummary,
) -> (Vec<TileInfo>, Option<TileInfo>) {
    let mut todo = Vec::new();
    let mut codebook_todo = None;
    for (t, state) in checked {
        let is_codebook = codebook.is_some_and(|c| c.id == t.id);
        match state {
            Stored::Verified if is_codebook => {}
            Stored::Verified => summary.skipped += 1,
            Stored::Missing | Stored::Damaged { .. } => {
                summary.set_aside += matches!(state, Stored::Damaged { .. }) as usize;
                if is_codebook {
                    codebook_todo = Some(t);
                } else {
                    todo.push(t);
                }
            }
        }
    }
    (todo, codebook_todo)
}

/// The progress bar of a fetch's downloads (`total` bytes, `shards` named in its message) on
/// stderr when `show`, else hidden.
fn progress_bar(show: bool, total: u64, shards: usize) -> ProgressBar {
    let pb = if show {
        ProgressBar::with_draw_target(Some(total), ProgressDrawTarget::stderr())
    } else {
        ProgressBar::hidden()
    };
    pb.set_style(
        ProgressStyle::with_template(
            "{msg} [{bar:30}] {bytes}/{total_bytes} {bytes_per_sec} eta {eta}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar())
        .progress_chars("=> "),
    );
    pb.set_message(format!("{shards} shards"));
    pb
}

/// After the commit: removes the partial files of tiles now stored (a kill between a shard
/// commit and the file's removal) or of older generations, keeping those of this manifest's
/// other tiles for a later fetch, and the codebooks of older generations (or of a scene now
/// partitioned dense); flushes the store. Returns the codebooks removed.
///
/// Errors: store I/O.
fn tidy_after_commit(store: &EdgeStore, scene: &str, manifest: &Manifest) -> Result<usize> {
    let mut keep = Vec::new();
    for t in &manifest.tiles {
        if !store.has_shard(scene, t)? {
            keep.push(store.partial_path(scene, t));
        }
    }
    let current_codebook = store.codebook_path(manifest)?;
    let removed = store.remove_other_codebooks(scene, current_codebook.as_deref())?;
    store.clean_partials(scene, &keep)?;
    store.flush()?;
    Ok(removed)
}

/// Steps 5 and 6 of the module doc under the store's generation lock
/// ([`EdgeStore::lock_generation`]), so that a load sees the generation before or after, never
/// between: commits `manifest` (as `signed`'s bytes with their signature, when fetched with a
/// trusted key) with `record` listing the tiles the new generation holds (the
/// disc's `selected`, plus, without `prune`, the manifest's other tiles with a stored file),
/// then evicts the shards it does not hold: older generations' always, those outside the disc
/// with `prune`. Returns (shards evicted, tiles kept outside the disc).
///
/// Errors: store I/O.
fn commit_and_evict(
    store: &EdgeStore,
    manifest: &Manifest,
    signed: Option<&SignedManifest>,
    selected: &[TileInfo],
    mut record: FetchRecord,
    prune: bool,
) -> Result<(usize, usize)> {
    let key = |t: &TileInfo| parse_checksum(t).ok().map(|c| (t.id, c));
    let wanted: std::collections::HashSet<(u64, u32)> = selected.iter().filter_map(key).collect();
    let current: std::collections::HashSet<(u64, u32)> =
        manifest.tiles.iter().filter_map(key).collect();
    let _generation = store.lock_generation();
    let mut tiles: Vec<u64> = Vec::with_capacity(manifest.tiles.len());
    for t in &manifest.tiles {
        let in_disc = key(t).is_some_and(|k| wanted.contains(&k));
        if in_disc || (!prune && store.has_shard(&manifest.scene_id, t)?) {
            tiles.push(t.id);
        }
    }
    tiles.sort_unstable();
    record.tiles = Some(tiles);
    boundary("fetch:before_commit");
    store.commit_fetch_signed(manifest, signed, &record)?;
    let (mut evicted, mut kept_outside) = (0, 0);
    for (tile, checksum, _) in store.stored_shards(&manifest.scene_id)? {
        let in_manifest = current.contains(&(tile, checksum));
        let in_disc = wanted.contains(&(tile, checksum));
        if !in_manifest || (prune && !in_disc) {
            evicted += store.remove_shard(&manifest.scene_id, tile, checksum)? as usize;
        } else if !in_disc {
            kept_outside += 1;
        }
    }
    Ok((evicted, kept_outside))
}

/// Refuses a download that cannot fit: the bytes still to come for `tiles` (their sizes less
/// what their partial files already hold) against [`EdgeStore::free_bytes`], before anything is
/// written.
///
/// Errors: [`Error::Limit`] [`slag_common::Resource::DiskSpace`] naming the store's folder;
/// [`Error::Io`] when the free space cannot be read.
fn check_free_space<'a>(
    store: &EdgeStore,
    manifest: &Manifest,
    tiles: impl Iterator<Item = &'a TileInfo>,
) -> Result<()> {
    let mut needed = 0u64;
    let mut count = 0usize;
    for t in tiles {
        let part = store.partial_path(&manifest.scene_id, t);
        let have = std::fs::symlink_metadata(&part)
            .ok()
            .filter(|m| m.is_file() && m.len() <= t.bytes)
            .map_or(0, |m| m.len());
        needed = needed.saturating_add(t.bytes - have);
        count += 1;
    }
    if needed == 0 {
        return Ok(());
    }
    let free = store.free_bytes()?;
    if needed > free {
        return Err(Error::limit(
            slag_common::Resource::DiskSpace,
            format!(
                "{needed} bytes for {count} shard(s) of scene {}",
                manifest.scene_id
            ),
            format!(
                "{free} bytes free for the store {}",
                store.root().join("partial").display()
            ),
        ));
    }
    Ok(())
}

/// Appends one received chunk to a partial file (through the disk-full hook,
/// [`slag_common::fault::enospc`]).
async fn write_chunk(file: &mut tokio::fs::File, chunk: &[u8]) -> std::io::Result<()> {
    slag_common::fault::enospc()?;
    file.write_all(chunk).await
}

/// Bytes of one tile: received over the network in this run, and shown in the progress bar.
#[derive(Default)]
struct Counts {
    received: u64,
    shown: u64,
}

/// What every download of one fetch shares: the HTTP client, the store, the manifest, the
/// fetch's parameters (server, token, retries, jobs, trusted key) and the progress bar.
struct Downloads<'a> {
    client: &'a reqwest::Client,
    store: &'a EdgeStore,
    manifest: Arc<Manifest>,
    p: &'a FetchParams,
    pb: ProgressBar,
}

impl Downloads<'_> {
    /// Step 4 of the module doc: the codebook first (when `codebook` is due), then the shards of
    /// `todo`, [`FetchParams::jobs`] at a time; counts what was downloaded in `summary`. On a
    /// failure every download still finishes, the store is flushed and the first error returned.
    ///
    /// Errors: as [`Self::tile`]; store I/O.
    async fn run(
        &self,
        codebook: Option<TileInfo>,
        todo: Vec<TileInfo>,
        summary: &mut FetchSummary,
    ) -> Result<()> {
        if let Some(t) = &codebook {
            match self.tile(t).await {
                Ok((_, received)) => summary.bytes_received += received,
                Err(e) => {
                    self.pb.finish_and_clear();
                    self.store.flush()?;
                    return Err(e);
                }
            }
        }
        let results: Vec<Result<(bool, u64)>> = futures_util::stream::iter(
            todo.into_iter().map(|t| async move { self.tile(&t).await }),
        )
        .buffer_unordered(self.p.jobs)
        .collect()
        .await;
        self.pb.finish_and_clear();
        let mut first_error = None;
        for r in results {
            match r {
                Ok((resumed, received)) => {
                    summary.downloaded += 1;
                    summary.resumed += resumed as usize;
                    summary.bytes_received += received;
                }
                Err(e) => {
                    first_error.get_or_insert(e);
                }
            }
        }
        if let Some(e) = first_error {
            self.store.flush()?;
            return Err(e);
        }
        Ok(())
    }

    /// Downloads one tile with retries (transient failures, [`FetchParams::retries`] times with
    /// a growing wait) and commits it verified; a file that fails verification is downloaded
    /// once more. Returns `(resumed, bytes received)`.
    ///
    /// Errors: the server ([`Error::Network`] after the retries, or at once when not transient),
    /// a file rejected twice ([`Error::Format`]), store I/O.
    async fn tile(&self, tile: &TileInfo) -> Result<(bool, u64)> {
        let url = self.tile_url(tile);
        let part = self.store.partial_path(&self.manifest.scene_id, tile);
        self.set_aside_non_file(&part).await?;
        let mut counts = Counts::default();
        let mut resumed = false;
        let mut attempt = 0u32;
        let mut verify_failures = 0u32;
        loop {
            let to = TileFetch {
                url: &url,
                part: &part,
                tile,
            };
            match self.try_download(&to, &mut counts).await {
                Ok(r) => {
                    resumed |= r;
                    match self.commit(tile, &part).await? {
                        Ok(()) => return Ok((resumed, counts.received)),
                        Err(Error::Format { path, message }) => {
                            // Corrupted in transit or on disk: start this shard over once.
                            let _ = tokio::fs::remove_file(&part).await;
                            verify_failures += 1;
                            if verify_failures > 1 {
                                return Err(Error::Format {
                                    path,
                                    message: format!(
                                        "{message}; downloaded twice, rejected twice: the \
                                         server's copy disagrees with its manifest"
                                    ),
                                });
                            }
                            tracing::warn!("{}: {message}; downloading again", path.display());
                        }
                        Err(e) => return Err(e),
                    }
                }
                Err(a) if a.transient && attempt < self.p.retries => {
                    attempt += 1;
                    let wait = Duration::from_millis(200 * 2u64.pow(attempt.min(6)));
                    tracing::warn!(
                        "{} (retry {attempt}/{} in {wait:?})",
                        a.error,
                        self.p.retries
                    );
                    tokio::time::sleep(wait).await;
                }
                Err(a) => return Err(a.error),
            }
        }
    }

    /// Whether `tile` is the codebook of a mixture scene, which travels as a pseudo tile
    /// ([`codebook_tile`]): its own URL and verification.
    fn is_codebook(&self, tile: &TileInfo) -> bool {
        self.manifest.mixture.is_some() && tile.id == CODEBOOK_TILE
    }

    /// The URL of `tile` (or of the codebook) on the shard server.
    fn tile_url(&self, tile: &TileInfo) -> String {
        let scene = &self.manifest.scene_id;
        if self.is_codebook(tile) {
            url_join(&self.p.server, &format!("v1/scenes/{scene}/codebook"))
        } else {
            url_join(
                &self.p.server,
                &format!("v1/scenes/{scene}/shards/{}", tile.id),
            )
        }
    }

    /// Sets aside a folder (or anything but a plain file) where the partial file `part` belongs.
    ///
    /// Errors: store I/O; a failed task ([`Error::Internal`]).
    async fn set_aside_non_file(&self, part: &Path) -> Result<()> {
        if let Ok(m) = tokio::fs::symlink_metadata(part).await
            && !m.is_file()
        {
            let (store, part) = (self.store.clone(), part.to_path_buf());
            tokio::task::spawn_blocking(move || {
                store.set_aside(&part, "not a partial download file")
            })
            .await
            .map_err(|e| Error::internal(format!("store task failed: {e}")))??;
        }
        Ok(())
    }

    /// Verifies the complete partial file `part` of `tile` and moves it into the store (on the
    /// blocking pool; hashes too with a trusted key). The outer error is a failed task, the
    /// inner one the commit's ([`Error::Format`] for a file that fails verification).
    ///
    /// Errors: [`Error::Internal`] when the task fails.
    async fn commit(&self, tile: &TileInfo, part: &Path) -> Result<Result<()>> {
        let is_codebook = self.is_codebook(tile);
        let signed = self.p.trusted_key.is_some();
        let (store, manifest, tile, part) = (
            self.store.clone(),
            self.manifest.clone(),
            tile.clone(),
            part.to_path_buf(),
        );
        tokio::task::spawn_blocking(move || {
            if is_codebook {
                store.commit_codebook_partial_checked(&manifest, &part, signed)
            } else {
                store.commit_partial_checked(&manifest, &tile, &part, signed)
            }
        })
        .await
        .map_err(|e| Error::internal(format!("store task failed: {e}")))
    }

    /// One HTTP attempt: continues `to.part` if it holds a prefix, otherwise starts over. On
    /// success the file holds exactly `to.tile.bytes` bytes (synced). Returns whether a `Range`
    /// request was honoured.
    async fn try_download(
        &self,
        to: &TileFetch<'_>,
        counts: &mut Counts,
    ) -> std::result::Result<bool, Attempt> {
        let tile = to.tile;
        let have = partial_prefix(to.part, tile).await?;
        if have == tile.bytes && have > 0 {
            return Ok(false);
        }
        let mut req = self.client.get(to.url);
        if let Some(t) = self.p.token.as_deref() {
            req = req.bearer_auth(t);
        }
        if have > 0 {
            req = req
                .header(reqwest::header::RANGE, format!("bytes={have}-"))
                .header(reqwest::header::IF_RANGE, format!("\"{}\"", tile.checksum));
        }
        let resp = req.send().await.map_err(|e| net_error(to.url, e))?;
        let Some((file, start, resumed)) = open_partial(&resp, to, have).await? else {
            let status = resp.status();
            let body = resp.text().await.unwrap_or_default();
            return Err(status_error(to.url, status, &body));
        };
        // Keep the bar at "bytes of this tile on disk" across resumes and restarts.
        if start >= counts.shown {
            self.pb.inc(start - counts.shown);
        } else {
            self.pb
                .set_position(self.pb.position().saturating_sub(counts.shown - start));
        }
        counts.shown = start;
        self.receive(resp, file, to, start, counts).await?;
        Ok(resumed)
    }

    /// Appends the body of `resp` to `file` (holding `start` bytes of `to.part`), then flushes
    /// and syncs it. Past the manifest's size the file is removed and the attempt starts over;
    /// a write that fails (disk full) removes it too, never left to fill the disk further; a
    /// body cut short keeps what arrived for the next attempt to resume.
    async fn receive(
        &self,
        resp: reqwest::Response,
        mut file: tokio::fs::File,
        to: &TileFetch<'_>,
        start: u64,
        counts: &mut Counts,
    ) -> std::result::Result<(), Attempt> {
        let (url, part, tile) = (to.url, to.part, to.tile);
        let io = |e: std::io::Error| permanent(Error::io(part, e));
        let mut written = start;
        let mut stream = resp.bytes_stream().map_err(|e| net_error(url, e));
        while let Some(chunk) = stream.next().await {
            let chunk = match chunk {
                Ok(c) => c,
                Err(a) => {
                    let _ = file.flush().await;
                    let _ = file.sync_data().await;
                    return Err(a);
                }
            };
            written += chunk.len() as u64;
            if written > tile.bytes {
                drop(file);
                let _ = tokio::fs::remove_file(part).await;
                return Err(transient(Error::network(
                    url,
                    format!(
                        "more than the manifest's {} bytes; starting over",
                        tile.bytes
                    ),
                )));
            }
            if let Err(e) = write_chunk(&mut file, &chunk).await {
                // The disk is full or failing: the partial file is removed (with those of the
                // rest of the scene, by `fetch`), never left to fill the disk further.
                drop(file);
                let _ = tokio::fs::remove_file(part).await;
                return Err(io(e));
            }
            boundary("fetch.partial:write");
            counts.received += chunk.len() as u64;
            counts.shown += chunk.len() as u64;
            self.pb.inc(chunk.len() as u64);
        }
        file.flush().await.map_err(io)?;
        file.sync_data().await.map_err(io)?;
        boundary("fetch.partial:fsync");
        if written != tile.bytes {
            return Err(transient(Error::network(
                url,
                format!(
                    "connection closed after {written} of {} bytes; will resume",
                    tile.bytes
                ),
            )));
        }
        Ok(())
    }
}

/// One tile's download: where from, where to, what it must be.
struct TileFetch<'a> {
    url: &'a str,
    part: &'a Path,
    tile: &'a TileInfo,
}

/// The bytes the partial file `part` already holds of `tile` (0 for none); a file longer than
/// the tile is removed and counts as none.
///
/// Errors: the removal ([`Error::Io`], not transient).
async fn partial_prefix(part: &Path, tile: &TileInfo) -> std::result::Result<u64, Attempt> {
    match tokio::fs::symlink_metadata(part).await {
        Ok(m) if m.len() <= tile.bytes => Ok(m.len()),
        Ok(_) => {
            tokio::fs::remove_file(part)
                .await
                .map_err(|e| permanent(Error::io(part, e)))?;
            boundary("fetch.partial:remove_oversized");
            Ok(0)
        }
        Err(_) => Ok(0),
    }
}

/// Opens `to.part` for the body of `resp`: appending after its `have` bytes when the server
/// honoured the `Range` request (206 with the asked `Content-Range`), else created empty for a
/// whole body (2xx). Returns `(file, bytes already in it, resumed)`; `None` for a status that
/// is no success. Never through a link (`O_NOFOLLOW`).
///
/// Errors: a 206 with another `Content-Range` (the file is removed; transient: starting over),
/// opening the file ([`Error::Io`]).
async fn open_partial(
    resp: &reqwest::Response,
    to: &TileFetch<'_>,
    have: u64,
) -> std::result::Result<Option<(tokio::fs::File, u64, bool)>, Attempt> {
    let (url, part) = (to.url, to.part);
    let io = |e: std::io::Error| permanent(Error::io(part, e));
    let status = resp.status();
    if status == reqwest::StatusCode::PARTIAL_CONTENT && have > 0 {
        let cr = resp
            .headers()
            .get(reqwest::header::CONTENT_RANGE)
            .and_then(|v| v.to_str().ok())
            .unwrap_or("");
        if !cr.starts_with(&format!("bytes {have}-")) {
            return Err(transient(Error::network(
                url,
                format!("asked for bytes {have}- but got Content-Range {cr:?}; starting over"),
            )))
            .inspect_err(|_| {
                let _ = std::fs::remove_file(part);
            });
        }
        // Never through a link (set aside above; O_NOFOLLOW closes the gap since).
        let f = tokio::fs::OpenOptions::new()
            .append(true)
            .custom_flags(libc::O_NOFOLLOW)
            .open(part)
            .await
            .map_err(io)?;
        Ok(Some((f, have, true)))
    } else if status.is_success() {
        let f = tokio::fs::OpenOptions::new()
            .write(true)
            .create(true)
            .truncate(true)
            .custom_flags(libc::O_NOFOLLOW)
            .open(part)
            .await
            .map_err(io)?;
        boundary("fetch.partial:create");
        Ok(Some((f, 0, false)))
    } else {
        Ok(None)
    }
}
