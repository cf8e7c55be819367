//! `slag-edge fetch`: download the shards around the robot into the [`EdgeStore`].
//!
//! 1. `GET {server}/v1/scenes/{scene}/manifest` (the shard server of `slag-encoder serve`);
//! 2. tiles whose footprint meets the closed disc (centre, radius) on the manifest's ground plane
//!    ([`select_tiles`] → [`slag_common::shards::TileIndex::select_tiles`], an `rstar` R-tree);
//!    centre and radius are in the robot's map frame (metres) when the manifest has a
//!    scene-to-map transform, converted by [`selection_disc`];
//!    The manifest is read as a stream and refused past
//!    [`slag_common::shards::MAX_MANIFEST_BYTES`]; its declared sizes must be ones the shard
//!    format allows ([`slag_common::shards::Manifest::check_sizes`]), so a manifest declaring
//!    a 10^12-byte tile is refused before anything is written;
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
//! With [`FetchParams::trusted_keys`] the manifest must come with the publisher's signature
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
//!
//! # Modules
//!
//! - `disc`: the disc on the manifest's ground plane and the tiles it selects;
//! - `client`: the HTTP client (rustls, a private CA), requests and their errors, the manifest;
//! - `signed`: the manifest with its signature, under a trusted key;
//! - `space`: the free-space check before anything is downloaded;
//! - `download`: the downloads of one fetch, each verified and committed;
//! - `resume`: partial files, continued with `Range` requests;
//! - `commit`: the stored files checked before the downloads, and the new generation's
//!   commit and evictions after them.

mod client;
mod commit;
mod disc;
mod download;
mod resume;
mod signed;
mod space;

use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use slag_common::shards::{MAP_FRAME, TileInfo, valid_scene_id};
use slag_common::{Error, Result};

use crate::query::FrameChoice;
use crate::store::{EdgeStore, FetchRecord, KeptTiles, codebook_tile};
use slag_common::shards::signature::TrustedKeys;

pub use client::{client, client_trusting, fetch_manifest, fetch_manifest_bytes};
pub use disc::{Center, select_tiles, selection_disc};
pub use signed::fetch_trusted_manifest;

use commit::{
    check_kept_outside, check_stored_tiles, commit_and_evict, plan_downloads, tidy_after_commit,
};
use download::Downloads;
use space::check_free_space;

/// Default [`FetchParams::min_rate`]: 16 KiB/s (131 kbit/s), a few percent of what a slow LTE
/// link carries, so only a stalled or dripping transfer falls below it.
pub const DEFAULT_MIN_RATE: u64 = 16 * 1024;

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
    /// Connect and read (idle) timeout per request; also the grace before [`Self::min_rate`]
    /// counts.
    pub timeout: Duration,
    /// Least mean rate of every transfer (manifest, signature, each tile), bytes per second:
    /// after [`Self::timeout`], a file must keep arriving at this rate or its request is cut
    /// off (a deadline per file that grows with its size, so a server that sends a byte now and
    /// then, never idle long enough for the timeout, cannot hold a fetch). A tile cut off keeps
    /// what arrived for the retry to resume. 0: no deadline. [`DEFAULT_MIN_RATE`] by default.
    pub min_rate: u64,
    /// Bearer token for the shard server, if it requires one.
    pub token: Option<String>,
    /// Draw a progress bar on stderr (when it is a terminal).
    pub progress: bool,
    /// The publisher's public keys (one, or two while it rotates): only a manifest one of them
    /// signed, and files matching that manifest's SHA-256s, are accepted (module doc, "Signed manifests"). `None`: unsigned
    /// manifests are accepted as they are.
    pub trusted_keys: Option<TrustedKeys>,
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
    /// With a trusted key: the stored tiles the new generation would keep, hashed against the
    /// signed manifest (verified, re-fetched inside the disc, dropped outside it); all 0 for an
    /// unsigned fetch.
    pub kept: KeptTiles,
}

impl std::fmt::Display for FetchSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "scene {} generation {} ({} frame{}): {} shards in the radius ({} downloaded, {} \
             resumed, {} already stored and verified, {} damaged set aside), {} Gaussians, {:.1} \
             MB of shards, {:.1} MB received; {} outside the radius kept, {} evicted; store {:.1} \
             MB on disk{}{}",
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
            },
            match self.kept {
                KeptTiles {
                    verified: 0,
                    refetched: 0,
                    dropped: 0,
                } => String::new(),
                k => format!(
                    "; stored tiles hashed against the signed manifest: {} verified, {} \
                     re-fetched, {} dropped",
                    k.verified, k.refetched, k.dropped
                ),
            }
        )
    }
}

/// Runs a fetch (steps in the module doc). Fetches into one store run one at a time; steps 5
/// and 6 hold the store's generation lock, so a concurrent load sees one committed generation.
///
/// Errors: bad parameters ([`Error::Param`]; `server` for a URL with a user name or password,
/// [`slag_common::auth::refuse_credentials_in_url`]), the server ([`Error::Network`]), a manifest too
/// large or whose sizes the shard format does not allow ([`Error::Limit`], [`Error::Format`]),
/// not enough free disk space for what is to be downloaded ([`Error::Limit`]
/// [`slag_common::Resource::DiskSpace`], naming the folder), a shard that fails verification
/// twice ([`Error::Format`]), with [`FetchParams::trusted_keys`] a manifest or file the key does
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
    let (todo, codebook_todo) = plan_downloads(checked, codebook.as_ref(), hashed, &mut summary);
    let manifest = if hashed && !p.prune {
        check_kept_outside(store, manifest, &selected, &mut summary.kept).await?
    } else {
        manifest
    };
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
        kept: hashed.then_some(summary.kept),
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
