//! The robot's embedded shard store (`sled`): what `slag-edge fetch` downloaded, what `serve`
//! scans.
//!
//! Layout of a store directory `DIR`:
//! - `DIR/db/`: the sled database with trees
//!   - `shards`: key `scene \0 tile_id(u64 BE) checksum(u32 BE)` → the verified shard bytes.
//!     Shards are content-addressed by their manifest checksum, so two partition generations can
//!     coexist and a new generation never overwrites the one being served;
//!   - `manifests`: key `scene` → the manifest JSON of the last *completed* fetch (the switch to a
//!     new generation happens in one write, after all its selected shards are committed);
//!   - `fetches`: key `scene` → [`FetchRecord`] JSON (server, centre, radius of that fetch);
//! - `DIR/partial/`: `<scene>-<tile>-<checksum>.part` files of interrupted downloads (resumed with
//!   an HTTP `Range` request). A shard enters `shards` only after its full bytes match the
//!   manifest checksum and decode (both CRCs, header scene/tile/model/dim/dtype) — a reader never
//!   sees a partial shard.
//!
//! One process opens a store at a time (sled holds a lock on `DIR/db`); a second one gets
//! [`slag_common::Error::Invalid`] telling the user to stop the other (`serve` can fetch through
//! `POST /fetch` instead).

use std::path::{Path, PathBuf};

use slag_common::shards::{
    Manifest, StoredShard, TileInfo, decode_shard_stored, shard_checksum, valid_scene_id,
};
use slag_common::{Error, Result};

/// sled page-cache size of the edge store (bytes).
pub const SLED_CACHE_BYTES: u64 = 64 * 1024 * 1024;

/// Where and how a scene was last fetched (stored beside the manifest).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FetchRecord {
    /// Shard server base URL.
    pub server: String,
    /// Centre of the fetched disc, ground coordinates `(g0, g1)` of the manifest's ground frame.
    pub center: [f64; 2],
    /// Radius of the disc, scene units (metres for metric scenes).
    pub radius: f64,
    /// Seconds since the Unix epoch when the fetch completed.
    pub completed_unix_s: u64,
}

/// The store: a sled database plus the partial-download folder.
#[derive(Debug, Clone)]
pub struct EdgeStore {
    root: PathBuf,
    db: sled::Db,
    shards: sled::Tree,
    manifests: sled::Tree,
    fetches: sled::Tree,
}

fn db_err(root: &Path, e: sled::Error) -> Error {
    match e {
        sled::Error::Io(io) if io.kind() == std::io::ErrorKind::WouldBlock => {
            Error::Invalid(format!(
                "store {} is in use by another process (a running `slag-edge serve`?); stop it, or ask \
             the running server to fetch with POST /fetch",
                root.display()
            ))
        }
        sled::Error::Io(io) => Error::io(root, io),
        other => Error::format(root, format!("sled store: {other}")),
    }
}

/// Shard key: `scene \0 tile(u64 BE) checksum(u32 BE)`.
fn shard_key(scene: &str, tile: u64, checksum: u32) -> Vec<u8> {
    let mut k = Vec::with_capacity(scene.len() + 13);
    k.extend_from_slice(scene.as_bytes());
    k.push(0);
    k.extend_from_slice(&tile.to_be_bytes());
    k.extend_from_slice(&checksum.to_be_bytes());
    k
}

/// Parses the manifest's 8-hex-digit checksum.
///
/// Errors: [`Error::Format`] when it is not 8 hex digits.
pub fn parse_checksum(tile: &TileInfo) -> Result<u32> {
    if tile.checksum.len() != 8 {
        return Err(Error::format(
            "<manifest>",
            format!(
                "tile {} checksum {:?} is not 8 hex digits",
                tile.id, tile.checksum
            ),
        ));
    }
    u32::from_str_radix(&tile.checksum, 16).map_err(|_| {
        Error::format(
            "<manifest>",
            format!(
                "tile {} checksum {:?} is not 8 hex digits",
                tile.id, tile.checksum
            ),
        )
    })
}

/// Checks downloaded bytes against the manifest entry and the manifest itself: length, whole-shard
/// CRC-32, and a full decode whose header names the same scene, tile, model, dim and dtype.
///
/// Errors: [`Error::Format`] naming the tile and what differs (the caller discards the bytes).
pub fn verify_shard(manifest: &Manifest, tile: &TileInfo, bytes: &[u8]) -> Result<StoredShard> {
    let origin = format!("shard {} of scene {}", tile.id, manifest.scene_id);
    if bytes.len() as u64 != tile.bytes {
        return Err(Error::format(
            &origin,
            format!("{} bytes, the manifest says {}", bytes.len(), tile.bytes),
        ));
    }
    let want = parse_checksum(tile)?;
    let got = shard_checksum(bytes);
    if got != want {
        return Err(Error::format(
            &origin,
            format!("checksum {got:08x}, the manifest says {want:08x}"),
        ));
    }
    let shard = decode_shard_stored(bytes).map_err(|e| match e {
        // Not corruption: a shard from a newer (or older) slag. Typed apart so that fetch does not
        // download it again and the message names the version.
        slag_common::shards::ShardError::UnsupportedVersion(_) => Error::Unsupported {
            path: origin.clone().into(),
            message: e.to_string(),
        },
        e => Error::format(&origin, e.to_string()),
    })?;
    let h = &shard.header;
    if h.scene_id != manifest.scene_id
        || h.tile_id != tile.id
        || h.model != manifest.model
        || h.dim != manifest.dim
        || h.dtype != manifest.dtype
        || h.count as u64 != tile.count
    {
        return Err(Error::format(
            &origin,
            format!(
                "header (scene {}, tile {}, model {}, dim {}, {:?}, {} Gaussians) disagrees with \
                 the manifest (scene {}, tile {}, model {}, dim {}, {:?}, {} Gaussians)",
                h.scene_id,
                h.tile_id,
                h.model,
                h.dim,
                h.dtype,
                h.count,
                manifest.scene_id,
                tile.id,
                manifest.model,
                manifest.dim,
                manifest.dtype,
                tile.count
            ),
        ));
    }
    Ok(shard)
}

impl EdgeStore {
    /// Opens (creating if needed) the store in `root`.
    ///
    /// Errors: [`Error::Io`] when the folder cannot be created, [`Error::Invalid`] when another
    /// process holds the store.
    pub fn open(root: &Path) -> Result<EdgeStore> {
        std::fs::create_dir_all(root.join("partial")).map_err(|e| Error::io(root, e))?;
        // sled's page cache defaults to 1 GB; the scan holds its own copy of the vectors, so the
        // store only needs a small cache (robots have little memory to spare).
        let db = sled::Config::new()
            .path(root.join("db"))
            .cache_capacity(SLED_CACHE_BYTES)
            .open()
            .map_err(|e| db_err(root, e))?;
        let tree = |name: &str| db.open_tree(name).map_err(|e| db_err(root, e));
        Ok(EdgeStore {
            root: root.to_path_buf(),
            shards: tree("shards")?,
            manifests: tree("manifests")?,
            fetches: tree("fetches")?,
            db,
        })
    }

    /// The store folder.
    pub fn root(&self) -> &Path {
        &self.root
    }

    fn err(&self, e: sled::Error) -> Error {
        db_err(&self.root, e)
    }

    /// Path of the partial download of `tile` (its checksum names the content it resumes):
    /// `DIR/partial/<scene>-<tile>-<checksum>.part`, always a plain file name inside
    /// `DIR/partial`: a scene id failing [`valid_scene_id`] or a checksum that is not 8 hex digits
    /// (both come from outside: the command line and the server's manifest) is written as hex of
    /// its bytes (prefixed `x`), so no `/`, `..` or NUL can reach the file system.
    pub fn partial_path(&self, scene: &str, tile: &TileInfo) -> PathBuf {
        fn hex(s: &str) -> String {
            let mut out = String::from("x");
            for b in s.bytes().take(64) {
                out.push_str(&format!("{b:02x}"));
            }
            out
        }
        let scene = if valid_scene_id(scene) {
            scene.to_string()
        } else {
            hex(scene)
        };
        let checksum = match parse_checksum(tile) {
            Ok(c) => format!("{c:08x}"),
            Err(_) => hex(&tile.checksum),
        };
        self.root
            .join("partial")
            .join(format!("{scene}-{}-{checksum}.part", tile.id))
    }

    /// Removes the partial downloads of `scene` except those in `keep` (file names from
    /// [`EdgeStore::partial_path`]); returns how many were removed. Called after a completed
    /// fetch: partials of stored shards (a kill between the commit and the removal) and of older
    /// generations can never be resumed into anything useful.
    ///
    /// Errors: the partial folder cannot be listed ([`Error::Io`]); single removals are best effort.
    pub fn clean_partials(&self, scene: &str, keep: &[PathBuf]) -> Result<usize> {
        let dir = self.root.join("partial");
        let rd = std::fs::read_dir(&dir).map_err(|e| Error::io(&dir, e))?;
        let mut removed = 0;
        for e in rd.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            // `<scene>-<tile>-<checksum>.part`: the scene is what is left of the last two dashes.
            let Some(stem) = name.strip_suffix(".part") else {
                continue;
            };
            let mut parts = stem.rsplitn(3, '-');
            let (_, _, owner) = (parts.next(), parts.next(), parts.next());
            if owner != Some(scene)
                || keep
                    .iter()
                    .any(|k| k.file_name() == Some(e.file_name().as_os_str()))
            {
                continue;
            }
            if std::fs::remove_file(e.path()).is_ok() {
                removed += 1;
            }
        }
        Ok(removed)
    }

    /// The manifest of the last completed fetch of `scene`.
    ///
    /// Errors: store I/O, or a stored manifest that no longer parses ([`Error::Format`]).
    pub fn manifest(&self, scene: &str) -> Result<Option<Manifest>> {
        match self
            .manifests
            .get(scene.as_bytes())
            .map_err(|e| self.err(e))?
        {
            Some(b) => Ok(Some(Manifest::from_json(&b, "stored manifest")?)),
            None => Ok(None),
        }
    }

    /// The record of the last completed fetch of `scene`.
    pub fn fetch_record(&self, scene: &str) -> Result<Option<FetchRecord>> {
        match self
            .fetches
            .get(scene.as_bytes())
            .map_err(|e| self.err(e))?
        {
            Some(b) => serde_json::from_slice(&b)
                .map(Some)
                .map_err(|e| Error::format(&self.root, format!("stored fetch record: {e}"))),
            None => Ok(None),
        }
    }

    /// Scenes with a completed fetch.
    pub fn scenes(&self) -> Result<Vec<String>> {
        self.manifests
            .iter()
            .keys()
            .map(|k| {
                k.map(|k| String::from_utf8_lossy(&k).into_owned())
                    .map_err(|e| self.err(e))
            })
            .collect()
    }

    /// True when the shard of `tile` with the manifest's checksum is stored.
    pub fn has_shard(&self, scene: &str, tile: &TileInfo) -> Result<bool> {
        let key = shard_key(scene, tile.id, parse_checksum(tile)?);
        self.shards.contains_key(key).map_err(|e| self.err(e))
    }

    /// Raw bytes of a stored shard (as downloaded; the caller decodes and verifies).
    pub fn shard_bytes(&self, scene: &str, tile: &TileInfo) -> Result<Option<sled::IVec>> {
        let key = shard_key(scene, tile.id, parse_checksum(tile)?);
        self.shards.get(key).map_err(|e| self.err(e))
    }

    /// Verifies `bytes` ([`verify_shard`]) and stores them durably (flushed before returning).
    ///
    /// Errors: verification ([`Error::Format`]; nothing is stored) or store I/O.
    pub fn commit_shard(&self, manifest: &Manifest, tile: &TileInfo, bytes: &[u8]) -> Result<()> {
        verify_shard(manifest, tile, bytes)?;
        let key = shard_key(&manifest.scene_id, tile.id, parse_checksum(tile)?);
        self.shards.insert(key, bytes).map_err(|e| self.err(e))?;
        self.db.flush().map_err(|e| self.err(e))?;
        Ok(())
    }

    /// Makes `manifest` the scene's current one and records the fetch, in one transaction, then
    /// flushes. Called after every selected shard is committed.
    pub fn commit_fetch(&self, manifest: &Manifest, record: &FetchRecord) -> Result<()> {
        use sled::Transactional;
        let m = manifest.to_json();
        let r = serde_json::to_vec(record).unwrap_or_default();
        let key = manifest.scene_id.as_bytes();
        (&self.manifests, &self.fetches)
            .transaction(|(tm, tf)| {
                tm.insert(key, m.as_slice())?;
                tf.insert(key, r.as_slice())?;
                Ok::<(), sled::transaction::ConflictableTransactionError<()>>(())
            })
            .map_err(|e| match e {
                sled::transaction::TransactionError::Storage(e) => self.err(e),
                sled::transaction::TransactionError::Abort(()) => {
                    Error::Invalid("store transaction aborted".into())
                }
            })?;
        self.db.flush().map_err(|e| self.err(e))?;
        Ok(())
    }

    /// Stored shards of `scene` as `(tile id, checksum, bytes on disk)`.
    pub fn stored_shards(&self, scene: &str) -> Result<Vec<(u64, u32, u64)>> {
        let mut prefix = scene.as_bytes().to_vec();
        prefix.push(0);
        let mut out = Vec::new();
        for kv in self.shards.scan_prefix(&prefix) {
            let (k, v) = kv.map_err(|e| self.err(e))?;
            let rest = &k[prefix.len()..];
            if rest.len() == 12 {
                let mut t = [0u8; 8];
                t.copy_from_slice(&rest[..8]);
                let mut c = [0u8; 4];
                c.copy_from_slice(&rest[8..]);
                out.push((u64::from_be_bytes(t), u32::from_be_bytes(c), v.len() as u64));
            }
        }
        Ok(out)
    }

    /// Removes one stored shard (by tile id and checksum); returns whether it existed.
    pub fn remove_shard(&self, scene: &str, tile: u64, checksum: u32) -> Result<bool> {
        let existed = self
            .shards
            .remove(shard_key(scene, tile, checksum))
            .map_err(|e| self.err(e))?
            .is_some();
        Ok(existed)
    }

    /// Flushes everything to disk.
    pub fn flush(&self) -> Result<()> {
        self.db.flush().map(|_| ()).map_err(|e| self.err(e))
    }

    /// Bytes the store uses on disk (sled files + partial downloads).
    pub fn disk_bytes(&self) -> u64 {
        fn walk(p: &Path) -> u64 {
            let Ok(rd) = std::fs::read_dir(p) else {
                return 0;
            };
            rd.flatten()
                .map(|e| match e.metadata() {
                    Ok(m) if m.is_dir() => walk(&e.path()),
                    Ok(m) => m.len(),
                    Err(_) => 0,
                })
                .sum()
        }
        walk(&self.root)
    }
}

/// Which of the manifest's tiles are present, for [`EdgeStore::load_scene`] and `/stats`.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct SceneLoad {
    /// Tiles loaded (verified).
    pub loaded_tiles: Vec<u64>,
    /// Tiles of the manifest that are not stored (outside the fetched radius, or never fetched).
    pub absent_tiles: usize,
    /// Stored tiles that failed verification (corrupted on disk); not served.
    pub rejected: Vec<String>,
}

impl EdgeStore {
    /// Decodes every stored shard of the scene's current manifest, verifying each again
    /// ([`verify_shard`]); corrupted shards are reported in [`SceneLoad::rejected`] and skipped.
    ///
    /// Errors: no completed fetch of `scene` ([`Error::Invalid`]), store I/O.
    pub fn load_scene(&self, scene: &str) -> Result<(Manifest, Vec<StoredShard>, SceneLoad)> {
        let mut shards = Vec::new();
        let (manifest, load) = self.load_scene_with(scene, |s| {
            shards.push(s);
            Ok(())
        })?;
        Ok((manifest, shards, load))
    }

    /// Like [`Self::load_scene`] but hands each verified shard to `f` as soon as it is decoded,
    /// so a caller that copies the rows elsewhere holds one shard at a time, not the whole scene.
    ///
    /// Errors: as [`Self::load_scene`], plus the first error `f` returns.
    pub fn load_scene_with(
        &self,
        scene: &str,
        mut f: impl FnMut(StoredShard) -> Result<()>,
    ) -> Result<(Manifest, SceneLoad)> {
        let manifest = self.manifest(scene)?.ok_or_else(|| {
            Error::Invalid(format!(
                "store {} has no completed fetch of scene {scene:?}; run `slag-edge fetch --from URL \
                 --scene {scene} --center X,Y --radius R --store {}` first",
                self.root.display(),
                self.root.display()
            ))
        })?;
        let mut load = SceneLoad::default();
        for tile in &manifest.tiles {
            match self.shard_bytes(scene, tile)? {
                None => load.absent_tiles += 1,
                Some(bytes) => match verify_shard(&manifest, tile, &bytes) {
                    Ok(s) => {
                        drop(bytes);
                        load.loaded_tiles.push(tile.id);
                        f(s)?;
                    }
                    Err(e) => {
                        tracing::error!("not serving a corrupted shard: {e}");
                        load.rejected.push(e.to_string());
                    }
                },
            }
        }
        Ok((manifest, load))
    }
}
