//! Loading a scene's stored shards: each file read, verified (and hashed against a signed
//! manifest), decoded and handed to the caller in manifest tile order.

use slag_common::shards::{Manifest, StoredShard, TileInfo};
use slag_common::{Error, Result};

use super::{Committed, EdgeStore, LoadableShard, WholeFile, signed};

/// Which of the manifest's tiles are present, for [`EdgeStore::load_scene`] and `/stats`.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct SceneLoad {
    /// Tiles loaded (verified).
    pub loaded_tiles: Vec<u64>,
    /// Tiles of the manifest that are not stored (outside the fetched radius, or never fetched).
    pub absent_tiles: usize,
    /// Stored tiles that failed verification (corrupted on disk, or bytes other than the signed
    /// manifest's); not served.
    pub rejected: Vec<String>,
    /// Of the loaded tiles, those whose bytes were hashed at this load and match the signed
    /// manifest's SHA-256 (a load with trusted keys of a signed generation,
    /// [`crate::engine::Engine::load_trusting`]; 0 otherwise).
    pub hashed: usize,
    /// Stored tiles of the generation waiting for their SHA-256 check, which a server with
    /// trusted keys runs in the background after it starts
    /// ([`crate::engine::Engine::pending`]): none of their rows is loaded, so none is served
    /// until the check passes. 0 for a load that checked every tile itself.
    pub pending_verification: usize,
}

impl EdgeStore {
    /// Decodes every stored shard of the scene's current manifest, verifying each again
    /// ([`verify_shard`](super::verify_shard)); corrupted shards are reported in
    /// [`SceneLoad::rejected`] and skipped. Holds every decoded shard at once: servers use
    /// [`Self::load_shards`].
    ///
    /// Errors: no completed fetch of `scene` ([`Error::Param`] `scene`), store I/O.
    pub fn load_scene(&self, scene: &str) -> Result<(Manifest, Vec<StoredShard>, SceneLoad)> {
        let manifest = self.current_manifest(scene)?;
        let mut shards = Vec::new();
        let load = self.load_shards(&manifest, |s| {
            shards.push(s);
            Ok(())
        })?;
        Ok((manifest, shards, load))
    }

    /// Reads the stored shards of `manifest`, handing them to `f` in manifest tile order: each
    /// file is read, verified ([`LoadableShard::verify`]: [`verify_shard`](super::verify_shard)
    /// for a dense manifest's [`StoredShard`]s,
    /// [`verify_mixture_shard`](super::verify_mixture_shard) for a mixture manifest's
    /// [`MixtureShard`](slag_common::shards::MixtureShard)s) and its bytes freed on the rayon
    /// pool, [`load_window`] files at a time, while `f` takes the shards already decoded. A
    /// caller that copies the rows elsewhere holds at most three windows of decoded shards (and
    /// one window of file bytes) besides its own copy. Tiles without a file count as absent;
    /// corrupted ones and files that cannot be read are logged, listed in
    /// [`SceneLoad::rejected`] and skipped.
    ///
    /// Errors: the first error `f` returns (the files being read then are dropped).
    pub fn load_shards<S: LoadableShard>(
        &self,
        manifest: &Manifest,
        f: impl FnMut(S) -> Result<()>,
    ) -> Result<SceneLoad> {
        let tiles: Vec<&TileInfo> = manifest.tiles.iter().collect();
        let mut f = f;
        self.load_tiles(manifest, &tiles, false, |s, _| s.map_or(Ok(()), &mut f))
    }

    /// [`Self::load_shards`] for the tiles of one committed generation ([`Committed::tiles`]):
    /// the manifest's other tiles count as absent, whatever files are there. With `hashes` (a
    /// signed generation whose signature the caller verified), each file's SHA-256 is also
    /// compared with the manifest's, before its decoding; a file that differs is rejected like a
    /// corrupted one ([`SceneLoad::rejected`], an [`Error::Untrusted`] message).
    ///
    /// Errors: the first error `f` returns.
    pub fn load_committed<S: LoadableShard>(
        &self,
        committed: &Committed,
        hashes: bool,
        mut f: impl FnMut(S) -> Result<()>,
    ) -> Result<SceneLoad> {
        self.load_committed_each(committed, hashes, |s, _| s.map_or(Ok(()), &mut f))
    }

    /// [`Self::load_committed`], calling `f` once per listed tile in order, whatever became of
    /// it: with `Some(shard)` for a tile that passed (verified, hashed with `hashes`, decoded)
    /// and `None` for one without a file or rejected; with the [`SceneLoad`] of the tiles
    /// handed so far, this one included. A server that serves tiles as they pass
    /// ([`crate::engine::QueryEngine::new`]) publishes what `f` has taken after each call.
    ///
    /// Errors: the first error `f` returns.
    pub fn load_committed_each<S: LoadableShard>(
        &self,
        committed: &Committed,
        hashes: bool,
        f: impl FnMut(Option<S>, &SceneLoad) -> Result<()>,
    ) -> Result<SceneLoad> {
        let tiles = committed.tiles();
        let mut load = self.load_tiles(&committed.manifest, &tiles, hashes, f)?;
        load.absent_tiles += committed.manifest.tiles.len() - tiles.len();
        Ok(load)
    }

    /// Reads `tiles` of `manifest` as [`Self::load_shards`] describes; hashes each too with
    /// `hashes` ([`Self::load_committed`]). A thread of its own reads and checks the files, a
    /// window at a time on the rayon pool, and sends them in order to this one, which hands
    /// each tile's outcome to `f` ([`Self::load_committed_each`]): checking the next files
    /// overlaps with `f` copying the rows of the last ones.
    ///
    /// Errors: the first error `f` returns; [`Error::Internal`] when the reading thread cannot
    /// be started (the system is out of threads or memory).
    fn load_tiles<S: LoadableShard>(
        &self,
        manifest: &Manifest,
        tiles: &[&TileInfo],
        hashes: bool,
        mut f: impl FnMut(Option<S>, &SceneLoad) -> Result<()>,
    ) -> Result<SceneLoad> {
        use rayon::prelude::*;
        let window = load_window();
        let mut load = SceneLoad::default();
        std::thread::scope(|scope| {
            let (tx, rx) = std::sync::mpsc::sync_channel::<Checked<S>>(window);
            let reader = std::thread::Builder::new().name("slag-load".into());
            reader
                .spawn_scoped(scope, move || {
                    for w in tiles.chunks(window) {
                        let checked: Vec<Checked<S>> = w
                            .par_iter()
                            .map(|t| self.check_tile(manifest, t, hashes))
                            .collect();
                        for c in checked {
                            if tx.send(c).is_err() {
                                // `f` failed: the load is over.
                                return;
                            }
                        }
                    }
                })
                .map_err(|e| {
                    Error::internal(format!("the store's loading thread did not start: {e}"))
                })?;
            for (tile, checked) in tiles.iter().zip(rx) {
                let shard = match checked {
                    Checked::Loaded(s) => {
                        load.loaded_tiles.push(tile.id);
                        load.hashed += hashes as usize;
                        Some(s)
                    }
                    Checked::Absent => {
                        load.absent_tiles += 1;
                        None
                    }
                    Checked::Rejected(why) => {
                        load.rejected.push(why);
                        None
                    }
                };
                f(shard, &load)?;
            }
            Ok(load)
        })
    }

    /// Reads and checks one stored tile for [`Self::load_tiles`] (with `hashes`, its SHA-256
    /// against the signed manifest first), logging a tile that is not served.
    fn check_tile<S: LoadableShard>(
        &self,
        manifest: &Manifest,
        tile: &TileInfo,
        hashes: bool,
    ) -> Checked<S> {
        let bytes = match self.shard_bytes(&manifest.scene_id, tile) {
            Ok(Some(b)) => b,
            Ok(None) => return Checked::Absent,
            // A checksum the store cannot name, or a file that cannot be read (a folder in its
            // place, a bad block): reported like a corrupted shard, and the rest of the scene is
            // served.
            Err(e) => {
                tracing::error!("not serving shard {}: {e}", tile.id);
                return Checked::Rejected(format!(
                    "shard {} of scene {}: {e}",
                    tile.id, manifest.scene_id
                ));
            }
        };
        // Under a signed manifest the SHA-256 comes first, and the whole-file CRC-32 adds
        // nothing to it.
        let checked = if hashes {
            signed::check_download(manifest, tile, &bytes)
                .and_then(|()| S::verify(manifest, tile, &bytes, WholeFile::Hashed))
        } else {
            S::verify(manifest, tile, &bytes, WholeFile::Crc32)
        };
        match checked {
            Ok(s) => Checked::Loaded(s),
            Err(e) => {
                tracing::error!("not serving a corrupted shard: {e}");
                Checked::Rejected(e.to_string())
            }
        }
    }
}

/// Most files a load reads and checks at once ([`EdgeStore::load_shards`]).
pub const MAX_LOAD_WINDOW: usize = 4;

/// Files [`EdgeStore::load_shards`] reads and checks at once: one per thread of the rayon pool,
/// at most [`MAX_LOAD_WINDOW`] (with 16 MiB shards, three windows of decoded shards stay under
/// 200 MB beside the rows already copied).
pub fn load_window() -> usize {
    rayon::current_num_threads().clamp(1, MAX_LOAD_WINDOW)
}

/// One stored tile, read and checked ([`EdgeStore::load_tiles`]).
enum Checked<S> {
    /// Verified (and hashed, when asked) and decoded: served.
    Loaded(S),
    /// No file: not part of the store.
    Absent,
    /// Not served: why (the message of its error).
    Rejected(String),
}
