//! Step 4 of a fetch: the downloads, [`super::FetchParams::jobs`] at a time, each retried after a
//! transient failure, verified and committed into the store.

use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use futures_util::{StreamExt, TryStreamExt};
use indicatif::ProgressBar;
use slag_common::fault::boundary;
use slag_common::shards::{CODEBOOK_TILE, Manifest, TileInfo};
use slag_common::{Error, Result};
use tokio::io::AsyncWriteExt;

use super::client::{Attempt, Pace, net_error, permanent, status_error, transient, url_join};
use super::resume::{TileFetch, open_partial, partial_prefix, write_chunk};
use super::signed::refusal;
use super::{FetchParams, FetchSummary};
use crate::store::{EdgeStore, Received};

/// Bytes of one tile: received over the network in this run, and shown in the progress bar.
#[derive(Default)]
pub(super) struct Counts {
    received: u64,
    shown: u64,
}

/// What every download of one fetch shares: the HTTP client, the store, the manifest, the
/// fetch's parameters (server, token, retries, jobs, trusted key) and the progress bar.
pub(super) struct Downloads<'a> {
    pub(super) client: &'a reqwest::Client,
    pub(super) store: &'a EdgeStore,
    pub(super) manifest: Arc<Manifest>,
    pub(super) p: &'a FetchParams,
    pub(super) pb: ProgressBar,
}

impl Downloads<'_> {
    /// Step 4 of the module doc: the codebook first (when `codebook` is due), then the shards of
    /// `todo`, [`FetchParams::jobs`] at a time; counts what was downloaded in `summary`. On a
    /// failure every download still finishes, the store is flushed and the first error returned.
    ///
    /// Errors: as [`Self::tile`]; store I/O.
    pub(super) async fn run(
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
                Ok((r, received)) => {
                    resumed |= r;
                    match self.commit(tile, &part, received).await? {
                        Ok(()) => return Ok((resumed, counts.received)),
                        // Under a trusted key the SHA-256 matched first: the same bytes would
                        // fail again, and any failed check is a refusal.
                        Err(e @ Error::Format { .. }) if self.p.trusted_keys.is_some() => {
                            let _ = tokio::fs::remove_file(&part).await;
                            return Err(refusal(e, &format!("tile {}", tile.id)));
                        }
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
                        "{} (retry {attempt}/{} in {:.1} s)",
                        a.error,
                        self.p.retries,
                        wait.as_secs_f64()
                    );
                    tokio::time::sleep(wait).await;
                }
                Err(a) => return Err(a.error),
            }
        }
    }

    /// Whether `tile` is the codebook of a mixture scene, which travels as a pseudo tile
    /// ([`crate::store::codebook_tile`]): its own URL and verification.
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
    /// blocking pool; hashes too with a trusted key: from `received`, the body kept and hashed
    /// as it came in, when this run received it whole, else the file read back). The outer
    /// error is a failed task, the inner one the commit's ([`Error::Format`] for a file that
    /// fails verification).
    ///
    /// Errors: [`Error::Internal`] when the task fails.
    async fn commit(
        &self,
        tile: &TileInfo,
        part: &Path,
        received: Option<Received>,
    ) -> Result<Result<()>> {
        let is_codebook = self.is_codebook(tile);
        let signed = self.p.trusted_keys.is_some();
        let (store, manifest, tile, part) = (
            self.store.clone(),
            self.manifest.clone(),
            tile.clone(),
            part.to_path_buf(),
        );
        tokio::task::spawn_blocking(move || match received {
            _ if is_codebook => store.commit_codebook_partial_checked(&manifest, &part, signed),
            Some(r) => store.commit_partial_received(&manifest, &tile, &part, &r),
            None => store.commit_partial_checked(&manifest, &tile, &part, signed),
        })
        .await
        .map_err(|e| Error::internal(format!("store task failed: {e}")))
    }

    /// One HTTP attempt: continues `to.part` if it holds a prefix, otherwise starts over. On
    /// success the file holds exactly `to.tile.bytes` bytes (synced). Returns whether a `Range`
    /// request was honoured, and with a trusted key the body kept and hashed when this attempt
    /// received the whole tile ([`Self::receive`]).
    async fn try_download(
        &self,
        to: &TileFetch<'_>,
        counts: &mut Counts,
    ) -> std::result::Result<(bool, Option<Received>), Attempt> {
        let tile = to.tile;
        let have = partial_prefix(to.part, tile).await?;
        if have == tile.bytes && have > 0 {
            return Ok((false, None));
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
        let pace = Pace::new(self.p.timeout, self.p.min_rate);
        let resp = pace
            .within(to.url, 0, req.send())
            .await?
            .map_err(|e| net_error(to.url, e))?;
        let Some((file, start, resumed)) = open_partial(&resp, to, have).await? else {
            let status = resp.status();
            let answered = slag_common::auth::redact_url(resp.url().as_str()).into_owned();
            let body = pace.within(&answered, 0, resp.text()).await?;
            return Err(status_error(&answered, status, &body.unwrap_or_default()));
        };
        // Keep the bar at "bytes of this tile on disk" across resumes and restarts.
        if start >= counts.shown {
            self.pb.inc(start - counts.shown);
        } else {
            self.pb
                .set_position(self.pb.position().saturating_sub(counts.shown - start));
        }
        counts.shown = start;
        let received = self.receive(resp, file, to, (start, pace), counts).await?;
        Ok((resumed, received))
    }

    /// Appends the body of `resp` to `file` (holding `start` bytes of `to.part`) at `pace`,
    /// then flushes and syncs it. With a trusted key, a body received whole (`start` 0; not
    /// the codebook) is also kept in memory and hashed on a thread of its own as it arrives
    /// ([`BodyHash`]), so that the commit neither reads the file back nor waits for a hash of
    /// it: returned as [`Received`]. Past the manifest's size the file is removed and the attempt
    /// starts over (with a trusted key: refused); a write that fails (disk full) removes it too,
    /// never left to fill the disk further; a body cut short, or slower than `pace`, keeps what
    /// arrived for the next attempt to resume.
    async fn receive(
        &self,
        resp: reqwest::Response,
        mut file: tokio::fs::File,
        to: &TileFetch<'_>,
        (start, pace): (u64, Pace),
        counts: &mut Counts,
    ) -> std::result::Result<Option<Received>, Attempt> {
        let (part, tile) = (to.part, to.tile);
        let url = &slag_common::auth::redact_url(resp.url().as_str()).into_owned();
        let io = |e: std::io::Error| permanent(Error::io(part, e));
        let mut written = start;
        let mut stream = resp.bytes_stream().map_err(|e| net_error(url, e));
        let whole = self.p.trusted_keys.is_some() && start == 0 && !self.is_codebook(tile);
        let mut body = whole.then(|| BodyHash::new(tile.bytes));
        loop {
            let next = pace.within(url, written - start, stream.next()).await;
            let chunk = match next {
                Ok(None) => break,
                Ok(Some(Ok(c))) => c,
                Ok(Some(Err(a))) | Err(a) => {
                    let _ = file.flush().await;
                    let _ = file.sync_data().await;
                    return Err(a);
                }
            };
            written += chunk.len() as u64;
            if written > tile.bytes {
                drop(file);
                let _ = tokio::fs::remove_file(part).await;
                return Err(self.too_long(url, tile));
            }
            if let Err(e) = write_chunk(&mut file, &chunk).await {
                // The disk is full or failing: the partial file is removed (with those of the
                // rest of the scene, by `fetch`), never left to fill the disk further.
                drop(file);
                let _ = tokio::fs::remove_file(part).await;
                return Err(io(e));
            }
            boundary("fetch.partial:write");
            if let Some(b) = body.as_mut() {
                b.push(&chunk);
            }
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
        match body {
            Some(b) => Ok(Some(b.finish().await.map_err(permanent)?)),
            None => Ok(None),
        }
    }
}

impl Downloads<'_> {
    /// The failed attempt of a body longer than the manifest gives `tile` (from `url`): with
    /// a trusted key a refusal (its length is signed, so a longer body is not the publisher's
    /// file), else a transient failure that starts over.
    fn too_long(&self, url: &str, tile: &TileInfo) -> Attempt {
        if self.p.trusted_keys.is_some() {
            return permanent(Error::untrusted(
                slag_common::Untrusted::Malformed,
                url,
                format!(
                    "the server sent more than the {} bytes the signed manifest gives tile {}: \
                     not the publisher's file",
                    tile.bytes, tile.id
                ),
            ));
        }
        transient(Error::network(
            url,
            format!(
                "more than the manifest's {} bytes; starting over",
                tile.bytes
            ),
        ))
    }
}

/// Most bytes [`BodyHash::new`] reserves before the body arrives (a larger tile grows its
/// buffer as it comes).
const MAX_BODY_RESERVE: u64 = 64 << 20;

/// A body kept in memory and hashed on a blocking thread as its chunks arrive
/// ([`Downloads::receive`]): each chunk is appended to the kept bytes and handed (shared, not
/// copied) to the hashing thread, so the SHA-256 overlaps with the network and the writes.
struct BodyHash<C> {
    bytes: Vec<u8>,
    chunks: std::sync::mpsc::Sender<C>,
    digest: tokio::task::JoinHandle<String>,
}

impl<C: AsRef<[u8]> + Clone + Send + 'static> BodyHash<C> {
    /// Room for `len` bytes (at most [`MAX_BODY_RESERVE`] up front), and the hashing thread
    /// started (on the blocking pool).
    fn new(len: u64) -> Self {
        let (chunks, rx) = std::sync::mpsc::channel::<C>();
        let digest = tokio::task::spawn_blocking(move || {
            use sha2::Digest;
            let mut h = sha2::Sha256::new();
            for c in rx {
                h.update(c.as_ref());
            }
            crate::store::hex_digest(&h.finalize())
        });
        BodyHash {
            bytes: Vec::with_capacity(len.min(MAX_BODY_RESERVE) as usize),
            chunks,
            digest,
        }
    }

    /// Keeps and hashes the next chunk.
    fn push(&mut self, chunk: &C) {
        self.bytes.extend_from_slice(chunk.as_ref());
        // The thread only ends once `chunks` is dropped, so the send cannot fail.
        let _ = self.chunks.send(chunk.clone());
    }

    /// The kept bytes and their SHA-256, once the thread has hashed every chunk.
    ///
    /// Errors: [`Error::Internal`] when the hashing task failed.
    async fn finish(self) -> Result<Received> {
        drop(self.chunks);
        let sha256 = self
            .digest
            .await
            .map_err(|e| Error::internal(format!("the hashing task failed: {e}")))?;
        Ok(Received {
            bytes: self.bytes,
            sha256,
        })
    }
}
