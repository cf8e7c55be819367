//! The robot's shard store: what `slag-edge fetch` downloaded, what `serve` scans.
//!
//! Layout of a store directory `DIR`:
//! - `DIR/shards/<scene-hex>/codebook-<checksum:08x>.codebook`: the codebook of a mixture scene
//!   (its manifest's [`slag_common::shards::MixtureInfo`]), verified and written like a shard;
//! - `DIR/shards/<scene-hex>/<tile:016x>-<checksum:08x>.shard`: one plain file per verified shard
//!   (scene id hex-encoded, so no id reaches the file system as a path). Shards are
//!   content-addressed by their manifest checksum, so two partition generations can coexist and a
//!   new generation never overwrites the one being served. A file gets its final name only by a
//!   `rename` after its bytes are complete, synced and verified (and the folder is synced after the
//!   rename), so a shard file is never half written;
//! - `DIR/db/`: a small sled database with trees
//!   - `manifests`: key `scene` → the manifest JSON of the last *completed* fetch (the switch to a
//!     new generation happens in one write, after all its selected shard files are in place);
//!   - `fetches`: key `scene` → [`FetchRecord`] JSON (server, centre, radius of that fetch);
//! - `DIR/partial/`: `<scene>-<tile>-<checksum>.part` files of interrupted downloads (resumed with
//!   an HTTP `Range` request). A download is renamed into `DIR/shards/` only after its full bytes
//!   match the manifest checksum and decode (both CRCs, header scene/tile/model/dim/dtype) — a
//!   reader never sees a partial shard;
//!   - `signatures`: key `scene` → the signature file of that manifest, for a fetch with a
//!     trusted key (module `signed`: the manifest is then kept as the exact bytes served);
//! - `DIR/shards/<scene-hex>/manifest.json` and `fetch.json` (and `manifest.sig` when signed):
//!   copies of the scene's current manifest and [`FetchRecord`] (and signature), written (atomically) with every completed fetch, from which a
//!   damaged database is rebuilt ([`EdgeStore::open`]: when sled reports its files damaged, the
//!   database is set aside and a new one refilled; a database that opens holding no scene, as
//!   sled leaves one whose data file was garbage, is refilled too);
//! - `DIR/quarantine/`: what the store set aside instead of deleting ([`EdgeStore::set_aside`]):
//!   stored shard files that no longer match their manifest entry (flipped bytes, truncated,
//!   appended to, another tile's or scene's bytes), directories or other non-files where a shard
//!   or a partial download belongs, and a database sled can no longer read. Each is renamed there
//!   with a warning in the log naming it and why; nothing there is read again, and the operator
//!   may inspect or delete it.
//!
//! # Verification
//!
//! "Already stored" means verified: before a fetch skips a tile, [`EdgeStore::check_stored`]
//! compares the file's length with the manifest's, reads it once to compute its CRC-32 against
//! the manifest checksum, and compares its header (scene, tile, model, width, dtype, count,
//! format version) with the manifest. No (length, mtime) cache stands in for the CRC: bit rot and
//! a bad flash block change bytes without changing either. The cost is one sequential read of
//! the selected shards per fetch (CRC-32 runs at several GB/s; the read is the cost). Loading for
//! `serve`, `query` and `check` decodes every shard in full on top ([`verify_shard`]).
//!
//! Shard bytes live in files, not in sled, because sled 0.34 kept the ~65 MB values it had read in
//! its page cache well past its configured capacity: loading 1M × 512 f16 Gaussians (16 shards)
//! left ~1 GB of shard values resident beside the 1 GB scan copy (measured with
//! `cargo run --example store_rss`). Loading reads a few files at a time ([`load_window`])
//! and frees each once decoded.
//!
//! A store written by an older slag-edge (shards inside sled, tree `shards`) is refused at
//! [`EdgeStore::open`] with [`Error::Unsupported`] telling the user to fetch again.
//!
//! One process opens a store at a time (sled holds a lock on `DIR/db`); a second one gets
//! [`slag_common::Error::Invalid`] telling the user to stop the other (`serve` can fetch through
//! `POST /fetch` instead).

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};

use slag_common::fault::{boundary, boundary_in};
use slag_common::io::sync_dir;
use slag_common::shards::{
    CODEBOOK_TILE, Codebook, Dtype, MAX_MANIFEST_BYTES, Manifest, SHARD_FORMAT_VERSION, TileInfo,
    decode_header, valid_scene_id,
};
use slag_common::{Error, Result};

mod load;
mod regular;
mod signed;
mod verify;
pub use load::{MAX_LOAD_WINDOW, SceneLoad, load_window};
pub(crate) use regular::hex_digest;
pub use regular::read_regular;
use regular::{Opened, db_not_regular, open_regular};
pub use signed::{SignatureCheck, SignedManifest};
pub use verify::{
    CODEBOOK_EXTENSION, LoadableShard, WholeFile, codebook_tile, verify_codebook,
    verify_mixture_shard, verify_shard,
};
use verify::{header_disagreement, verify_any_shard};

/// sled page-cache size of the edge store (bytes). sled holds only manifests and fetch records.
pub const SLED_CACHE_BYTES: u64 = 8 * 1024 * 1024;

/// File-name extension of a stored shard.
pub const SHARD_EXTENSION: &str = "shard";

/// Where and how a scene was last fetched (stored beside the manifest).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FetchRecord {
    /// Shard server base URL.
    pub server: String,
    /// Centre of the fetched disc, ground coordinates `(g0, g1)` of the manifest's ground frame.
    pub center: [f64; 2],
    /// Radius of the disc on the ground plane, scene units (a fetch in the map frame records
    /// its radius in metres divided by the transform's scale).
    pub radius: f64,
    /// Seconds since the Unix epoch when the fetch completed.
    pub completed_unix_s: u64,
    /// Ids of the manifest's tiles this generation holds, ascending: the disc's, plus those
    /// outside it that were stored and kept (no pruning). A load reads exactly these shards, so
    /// what it serves is the committed set whatever files a running fetch adds or evicts.
    /// `None` in a record of an older slag-edge: a load then reads every stored shard of the
    /// manifest.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tiles: Option<Vec<u64>>,
    /// A fetch with a trusted key: what became of the tiles the store already held (their
    /// SHA-256 checked against the signed manifest). `None` for an unsigned fetch.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub kept: Option<KeptTiles>,
}

/// What a fetch with a trusted key did with the tiles of the new generation that the store
/// already held (a tile's stored file is hashed and compared with the signed manifest's SHA-256
/// and length before it joins the generation; a codebook is checked the same way but not counted).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct KeptTiles {
    /// Stored tiles (inside the disc and outside it) whose bytes match the signed manifest:
    /// kept.
    pub verified: usize,
    /// Stored tiles inside the disc that did not match: set aside and downloaded again.
    pub refetched: usize,
    /// Stored tiles outside the disc that did not match: set aside, not part of the new
    /// generation (a fetch never downloads outside its disc), so never served.
    pub dropped: usize,
}

/// The store: shard files, a sled database of manifests, and the partial-download folder.
///
/// Clones share one generation lock ([`EdgeStore::lock_generation`]) and commit counter.
#[derive(Debug, Clone)]
pub struct EdgeStore {
    root: PathBuf,
    db: sled::Db,
    manifests: sled::Tree,
    fetches: sled::Tree,
    generation: Arc<Mutex<()>>,
    commits: Arc<AtomicU64>,
    fetching: Arc<tokio::sync::Mutex<()>>,
}

/// The scene's last committed generation, as [`EdgeStore::committed`] read it under the
/// generation lock: its manifest, its fetch record (`None` for a store rebuilt without one),
/// and the store's commit count at the time (orders two loads of one process).
#[derive(Debug, Clone)]
pub struct Committed {
    /// Manifest of the last completed fetch.
    pub manifest: Manifest,
    /// Record of that fetch, with the tiles the generation holds ([`FetchRecord::tiles`]).
    pub record: Option<FetchRecord>,
    /// Generations this process committed into the store before the read (0 for the one found
    /// at start-up); a load of a larger count holds a later generation.
    pub seq: u64,
}

impl Committed {
    /// The tiles a load reads: those of [`FetchRecord::tiles`], or every tile of the manifest
    /// for a record without the list (an older store) or no record.
    pub fn tiles(&self) -> Vec<&TileInfo> {
        match self.record.as_ref().and_then(|r| r.tiles.as_ref()) {
            Some(ids) => self
                .manifest
                .tiles
                .iter()
                .filter(|t| ids.binary_search(&t.id).is_ok())
                .collect(),
            None => self.manifest.tiles.iter().collect(),
        }
    }
}

fn db_err(root: &Path, e: sled::Error) -> Error {
    if db_damaged(&e) {
        return Error::format(
            root.join("db"),
            format!(
                "the store's database is damaged ({e}); stop every slag-edge using this store and \
                 run `slag-edge fetch` again: opening the store sets the database aside and \
                 rebuilds it from the manifest copies beside the verified shard files"
            ),
        );
    }
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

/// True for a sled error that means its files are damaged (not a lock held by another process
/// nor an I/O error of the disk itself).
fn db_damaged(e: &sled::Error) -> bool {
    match e {
        // `Unsupported` at open: its config file does not read as sled's (garbage there).
        sled::Error::Corruption { .. }
        | sled::Error::ReportableBug(_)
        | sled::Error::Unsupported(_) => true,
        sled::Error::Io(io) => matches!(
            io.kind(),
            std::io::ErrorKind::InvalidData | std::io::ErrorKind::UnexpectedEof
        ),
        _ => false,
    }
}

/// Opens the sled database of the store in `root`.
fn open_db(root: &Path) -> std::result::Result<sled::Db, sled::Error> {
    sled::Config::new()
        .path(root.join("db"))
        .cache_capacity(SLED_CACHE_BYTES)
        .open()
}

/// Name of the manifest copy in a scene's shard folder (module doc).
const MANIFEST_COPY: &str = "manifest.json";
/// Name of the fetch-record copy in a scene's shard folder (module doc).
const FETCH_COPY: &str = "fetch.json";

/// Writes `bytes` to `path` atomically: a `.tmp` file beside it, synced, renamed, folder synced;
/// `site` names its durability boundaries ([`write_durably`]).
fn write_atomic(path: &Path, site: &str, bytes: &[u8]) -> Result<()> {
    write_durably(path, &path.with_extension("json.tmp"), site, bytes)
}

/// Writes `bytes` to `tmp` (a path in `path`'s folder), syncs it, renames it to `path` and syncs
/// the folder. On a write error `tmp` is removed; a crash leaves at most `tmp`. Each step is a
/// durability boundary named `site:` + `remove_stale_tmp`, `write`, `fsync`, `rename`,
/// `dir_sync` ([`slag_common::fault`]).
fn write_durably(path: &Path, tmp: &Path, site: &str, bytes: &[u8]) -> Result<()> {
    let write = || -> std::io::Result<()> {
        use std::os::unix::fs::OpenOptionsExt;
        // A new file: whatever is at `tmp` (a leftover, or a link planted there) is removed, not
        // written through.
        match std::fs::remove_file(tmp) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => return Err(e),
            Err(_) => {}
            Ok(()) => boundary_in(site, "remove_stale_tmp"),
        }
        let mut f = std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .custom_flags(libc::O_NOFOLLOW)
            .open(tmp)?;
        f.write_all(bytes)?;
        boundary_in(site, "write");
        f.sync_all()?;
        boundary_in(site, "fsync");
        Ok(())
    };
    write().map_err(|e| {
        let _ = std::fs::remove_file(tmp);
        Error::io(tmp, e)
    })?;
    std::fs::rename(tmp, path).map_err(|e| Error::io(path, e))?;
    boundary_in(site, "rename");
    if let Some(dir) = path.parent() {
        sync_dir(dir)?;
        boundary_in(site, "dir_sync");
    }
    Ok(())
}

/// Bytes of the file header kept while a stored file is checksummed: the header decoder reads
/// no further for the ids and models slag writes (its fixed part is 80 bytes).
const HEAD_BYTES: usize = 64 * 1024;

/// What [`EdgeStore::check_stored`] found for one tile.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Stored {
    /// The file matches its manifest entry: length, CRC-32 and header.
    Verified,
    /// Nothing at the tile's path.
    Missing,
    /// Something at the tile's path that is not its verified file (`why` says what differs): a
    /// fetch sets it aside ([`EdgeStore::set_aside`]) and downloads the tile again.
    Damaged {
        /// The file (or folder) found.
        path: PathBuf,
        /// What differs from the manifest.
        why: String,
    },
}

/// [`EdgeStore::set_aside`] without the log line (also used before the store is open).
fn set_aside_in(root: &Path, path: &Path, why: &str) -> Result<PathBuf> {
    let q = root.join("quarantine");
    std::fs::create_dir_all(&q).map_err(|e| Error::io(&q, e))?;
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or(0);
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "unnamed".into());
    let to = q.join(format!("{nanos}-{name}"));
    std::fs::rename(path, &to).map_err(|e| {
        Error::io(
            path,
            std::io::Error::new(e.kind(), format!("setting it aside ({why}) failed: {e}")),
        )
    })?;
    boundary("store.set_aside:rename");
    sync_dir(&q)?;
    boundary("store.set_aside:quarantine_dir_sync");
    if let Some(parent) = path.parent() {
        sync_dir(parent)?;
        boundary("store.set_aside:dir_sync");
    }
    Ok(to)
}

/// A complete partial download (`part`, at most `max` bytes are read: [`read_regular`]).
///
/// Errors: [`Error::Io`] when it is gone or cannot be read, [`Error::Format`] when it is not a
/// regular file or longer than `max`.
fn read_partial(part: &Path, max: u64) -> Result<Vec<u8>> {
    read_regular(part, max, "partial download")?.ok_or_else(|| {
        Error::io(
            part,
            std::io::Error::new(std::io::ErrorKind::NotFound, "partial download vanished"),
        )
    })
}

/// A download received whole in one response, as the fetch kept it for
/// [`EdgeStore::commit_partial_received`]: its bytes, exactly as written to the partial file,
/// and their SHA-256 (64 lowercase hex digits).
pub struct Received {
    /// The body, in order.
    pub bytes: Vec<u8>,
    /// SHA-256 of `bytes`.
    pub sha256: String,
}

/// Bytes of the files under `p` (0 for what cannot be read).
fn dir_bytes(p: &Path) -> u64 {
    let Ok(rd) = std::fs::read_dir(p) else {
        return 0;
    };
    rd.flatten()
        .map(|e| match e.metadata() {
            Ok(m) if m.is_dir() => dir_bytes(&e.path()),
            Ok(m) => m.len(),
            Err(_) => 0,
        })
        .sum()
}

/// Lower-case hex of `bytes`.
fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// `tile:016x-checksum:08x.shard` → `(tile, checksum)`.
fn parse_shard_name(name: &str) -> Option<(u64, u32)> {
    let stem = name.strip_suffix(SHARD_EXTENSION)?.strip_suffix('.')?;
    let (t, c) = stem.split_once('-')?;
    if t.len() != 16 || c.len() != 8 {
        return None;
    }
    Some((
        u64::from_str_radix(t, 16).ok()?,
        u32::from_str_radix(c, 16).ok()?,
    ))
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

impl EdgeStore {
    /// Opens the store in `root` for reading (`slag-edge query`, `serve`, `check`): unlike
    /// [`Self::open`], a folder that holds no store is an error and nothing is created.
    ///
    /// Errors: [`Error::Param`] `store` when `root` or its database does not exist (a fetch
    /// into it comes first); as [`Self::open`] otherwise.
    pub fn open_existing(root: &Path) -> Result<EdgeStore> {
        if !root.join("db").is_dir() {
            return Err(Error::param(
                "store",
                root.display(),
                format!(
                    "a slag-edge store written by a fetch; there is no slag-edge store there ({})",
                    if root.exists() {
                        "the folder holds no store database"
                    } else {
                        "no such folder"
                    }
                ),
            ));
        }
        EdgeStore::open(root)
    }

    /// Opens (creating if needed) the store in `root`.
    ///
    /// Errors: [`Error::Io`] when the folders cannot be created, [`Error::Invalid`] when another
    /// process holds the store, [`Error::Unsupported`] for a store of an older slag-edge that kept
    /// shards inside sled (delete it or pick another folder and fetch again).
    pub fn open(root: &Path) -> Result<EdgeStore> {
        for sub in ["partial", "shards"] {
            std::fs::create_dir_all(root.join(sub)).map_err(|e| Error::io(root, e))?;
        }
        // sled opens and reads its files by path: a link, FIFO or device among them would be
        // followed or block. Such a database is set aside like a damaged one.
        let not_regular = db_not_regular(&root.join("db"));
        if let Some(why) = &not_regular {
            let aside = set_aside_in(root, &root.join("db"), why)?;
            tracing::warn!(
                "store {}: the database folder holds what is not a regular file ({why}); set \
                 aside as {}, rebuilding it from the manifest copies",
                root.display(),
                aside.display()
            );
        }
        let (db, rebuild) = match open_db(root) {
            Ok(db) => (db, not_regular.is_some()),
            // Damaged files (not a lock, not a disk error): set the database aside and start a
            // new one, refilled below from the manifest copies beside the shard files.
            Err(e) if db_damaged(&e) => {
                let aside = set_aside_in(root, &root.join("db"), &format!("sled: {e}"))?;
                tracing::warn!(
                    "store {}: the database was damaged ({e}); set aside as {}, rebuilding it \
                     from the manifest copies beside the verified shard files",
                    root.display(),
                    aside.display()
                );
                (open_db(root).map_err(|e| db_err(root, e))?, true)
            }
            Err(e) => return Err(db_err(root, e)),
        };
        if db.tree_names().iter().any(|n| n.as_ref() == b"shards") {
            let legacy = db.open_tree("shards").map_err(|e| db_err(root, e))?;
            if !legacy.is_empty() {
                return Err(Error::Unsupported {
                    path: root.to_path_buf(),
                    message:
                        "this store was written by an older slag-edge that kept shards inside \
                              its sled database; this version keeps them in files. Delete the \
                              folder (or use another store folder) and run `slag-edge fetch` again"
                            .into(),
                });
            }
            drop(legacy);
            db.drop_tree("shards").map_err(|e| db_err(root, e))?;
        }
        let tree = |name: &str| db.open_tree(name).map_err(|e| db_err(root, e));
        let store = EdgeStore {
            root: root.to_path_buf(),
            manifests: tree("manifests")?,
            fetches: tree("fetches")?,
            db,
            generation: Arc::new(Mutex::new(())),
            commits: Arc::new(AtomicU64::new(0)),
            fetching: Arc::new(tokio::sync::Mutex::new(())),
        };
        // sled recovers a log whose data is garbage by dropping it, and opens empty: a database
        // without any scene beside manifest copies is refilled as well.
        if rebuild || store.manifests.is_empty() {
            let scenes = store.rebuild_db()?;
            if rebuild || !scenes.is_empty() {
                tracing::warn!(
                    "store {}: database rebuilt with {} scene(s) ({}) from the manifest copies; \
                     shards are verified again when loaded and fetched",
                    root.display(),
                    scenes.len(),
                    scenes.join(", ")
                );
            }
        }
        Ok(store)
    }

    /// Refills the database from the manifest and fetch-record copies in each scene's shard
    /// folder, for scenes it does not hold; returns the scenes restored. A copy that does not parse, or names
    /// another scene than its folder, is skipped with a warning (a fetch of that scene writes it
    /// again).
    fn rebuild_db(&self) -> Result<Vec<String>> {
        let dir = self.root.join("shards");
        let rd = std::fs::read_dir(&dir).map_err(|e| Error::io(&dir, e))?;
        let mut scenes = Vec::new();
        for e in rd.flatten() {
            let folder = e.path();
            let copy = folder.join(MANIFEST_COPY);
            let bytes = match read_regular(&copy, MAX_MANIFEST_BYTES, "manifest copy") {
                Ok(Some(b)) => b,
                Ok(None) => continue,
                Err(e) => {
                    tracing::warn!("not restored: {e}");
                    continue;
                }
            };
            let m = match Manifest::from_json(&bytes, &copy.display().to_string()) {
                Ok(m) if self.scene_dir(&m.scene_id) == folder => m,
                Ok(m) => {
                    tracing::warn!(
                        "{}: scene {} in another scene's folder; skipped",
                        copy.display(),
                        m.scene_id
                    );
                    continue;
                }
                Err(err) => {
                    tracing::warn!("not restored: {err}");
                    continue;
                }
            };
            let key = m.scene_id.as_bytes();
            if self.manifests.contains_key(key).map_err(|e| self.err(e))? {
                continue;
            }
            self.manifests.insert(key, bytes).map_err(|e| self.err(e))?;
            boundary("store.rebuild:insert_manifest");
            self.restore_signature(&folder, key)?;
            if let Ok(Some(r)) = read_regular(
                &folder.join(FETCH_COPY),
                MAX_MANIFEST_BYTES,
                "fetch record copy",
            ) && serde_json::from_slice::<FetchRecord>(&r).is_ok()
            {
                self.fetches.insert(key, r).map_err(|e| self.err(e))?;
                boundary("store.rebuild:insert_fetch_record");
            }
            scenes.push(m.scene_id);
        }
        self.db.flush().map_err(|e| self.err(e))?;
        boundary("store.rebuild:flush");
        scenes.sort();
        Ok(scenes)
    }

    /// Moves `path` (a file, or a folder where a file belongs) into `DIR/quarantine/` under a new
    /// name (the time, then its own name), logs a warning with `why`, and returns the new path:
    /// what the store sets aside is kept for inspection, never deleted (module doc).
    ///
    /// Errors: [`Error::Io`] when the quarantine folder cannot be made or the rename fails.
    pub fn set_aside(&self, path: &Path, why: &str) -> Result<PathBuf> {
        let to = set_aside_in(&self.root, path, why)?;
        tracing::warn!(
            "set aside {} ({why}) as {}; it is fetched again",
            path.display(),
            to.display()
        );
        Ok(to)
    }

    /// Files and folders in `DIR/quarantine/` and their bytes ([`Self::set_aside`]).
    pub fn quarantine_usage(&self) -> (usize, u64) {
        let dir = self.root.join("quarantine");
        let Ok(rd) = std::fs::read_dir(&dir) else {
            return (0, 0);
        };
        (rd.flatten().count(), dir_bytes(&dir))
    }

    /// Checks the stored file of `tile` (a shard, or a mixture scene's codebook as its
    /// [`codebook_tile`]) against `manifest` without decoding its payload: that it is a regular
    /// file, its length, the CRC-32 of all its bytes (read once, 1 MiB at a time), and its header
    /// (format version, scene, tile, model, width, dtype, count). See the module doc.
    ///
    /// Errors: [`Error::Format`] for a checksum that is not 8 hex digits; [`Error::Io`] when the
    /// file exists but cannot be read.
    pub fn check_stored(&self, manifest: &Manifest, tile: &TileInfo) -> Result<Stored> {
        self.check_stored_read(manifest, tile, None)
    }

    /// [`Self::check_stored`], feeding every byte it reads to `sha256` as well when given (the
    /// digest is of the whole file when the check reports [`Stored::Verified`]).
    ///
    /// Errors: as [`Self::check_stored`].
    pub(crate) fn check_stored_read(
        &self,
        manifest: &Manifest,
        tile: &TileInfo,
        sha256: Option<&mut sha2::Sha256>,
    ) -> Result<Stored> {
        let path = self.stored_path(manifest, tile)?;
        let damaged = |why: String| {
            Ok(Stored::Damaged {
                path: path.clone(),
                why,
            })
        };
        let (f, len) = match open_regular(&path).map_err(|e| Error::io(&path, e))? {
            Opened::File(f, len) => (f, len),
            Opened::Missing => return Ok(Stored::Missing),
            Opened::NotRegular("a folder") => {
                return damaged("a folder where a shard file belongs".into());
            }
            Opened::NotRegular(kind) => {
                return damaged(format!("{kind}, not a regular file"));
            }
        };
        if len != tile.bytes {
            let longer = if len > tile.bytes {
                "longer"
            } else {
                "shorter"
            };
            return damaged(format!(
                "{len} bytes, {longer} than the {} bytes the manifest says",
                tile.bytes
            ));
        }
        // Never past the stated length, whatever the file does meanwhile.
        let (got, head, total) = regular::crc_and_head(f, tile.bytes, HEAD_BYTES, sha256)
            .map_err(|e| Error::io(&path, e))?;
        if total != tile.bytes {
            return damaged(format!(
                "{total} bytes read, the manifest says {}",
                tile.bytes
            ));
        }
        let want = parse_checksum(tile)?;
        if got != want {
            return damaged(format!("checksum {got:08x}, the manifest says {want:08x}"));
        }
        let h = match decode_header(&head) {
            Ok(h) => h,
            Err(e) => return damaged(format!("header: {e}")),
        };
        let codebook = manifest
            .mixture
            .as_ref()
            .filter(|_| tile.id == CODEBOOK_TILE);
        // Shards are of the manifest's format version (1 or 3 dense, 2 or 4 mixture; the
        // manifest's own check keeps it to those), the codebook always version 1.
        let (version, dtype) = match (&manifest.mixture, codebook) {
            (Some(_), None) => (manifest.shard_format_version, Dtype::F16),
            (Some(_), Some(_)) => (SHARD_FORMAT_VERSION, Dtype::F16),
            (None, _) => (manifest.shard_format_version, manifest.dtype),
        };
        if let Some(m) = header_disagreement(&h, manifest, tile, Some(version), dtype) {
            return damaged(m);
        }
        Ok(Stored::Verified)
    }

    /// Where the verified file of `tile` lives: [`Self::codebook_path`] for a mixture scene's
    /// codebook pseudo tile, [`Self::shard_path`] otherwise.
    ///
    /// Errors: [`Error::Format`] for a checksum that is not 8 hex digits.
    pub fn stored_path(&self, manifest: &Manifest, tile: &TileInfo) -> Result<PathBuf> {
        if manifest.mixture.is_some()
            && tile.id == CODEBOOK_TILE
            && let Some(p) = self.codebook_path(manifest)?
        {
            return Ok(p);
        }
        self.shard_path(&manifest.scene_id, tile)
    }

    /// Tiles of `manifest` inside the disc of the scene's last completed fetch
    /// ([`FetchRecord`]) that have no stored file: what `check` reports as missing. Empty when
    /// the scene has no fetch record.
    ///
    /// Errors: store I/O, a checksum that is not 8 hex digits ([`Error::Format`]).
    pub fn missing_tiles(&self, manifest: &Manifest) -> Result<Vec<u64>> {
        let Some(r) = self.fetch_record(&manifest.scene_id)? else {
            return Ok(Vec::new());
        };
        let mut missing = Vec::new();
        for id in manifest.tile_index().select_tiles(r.center, r.radius) {
            if let Some(t) = manifest.tiles.iter().find(|t| t.id == id)
                && std::fs::symlink_metadata(self.shard_path(&manifest.scene_id, t)?).is_err()
            {
                missing.push(id);
            }
        }
        Ok(missing)
    }

    /// Bytes free for this store's downloads: `statvfs` of `DIR/partial` (blocks available to an
    /// unprivileged user times the fragment size).
    ///
    /// Errors: [`Error::Io`] when the file system cannot be asked.
    pub fn free_bytes(&self) -> Result<u64> {
        let dir = self.root.join("partial");
        let st = rustix::fs::statvfs(&dir).map_err(|e| Error::io(&dir, e.into()))?;
        Ok(st.f_bavail.saturating_mul(st.f_frsize))
    }

    /// The store folder.
    pub fn root(&self) -> &Path {
        &self.root
    }

    fn err(&self, e: sled::Error) -> Error {
        db_err(&self.root, e)
    }

    /// Folder of `scene`'s shard files: `DIR/shards/<hex of the scene id>`.
    pub fn scene_dir(&self, scene: &str) -> PathBuf {
        self.root.join("shards").join(hex(scene.as_bytes()))
    }

    /// Path of the stored shard of `tile` (module doc); it exists only once the shard is verified.
    ///
    /// Errors: [`Error::Format`] when the manifest checksum is not 8 hex digits.
    pub fn shard_path(&self, scene: &str, tile: &TileInfo) -> Result<PathBuf> {
        let checksum = parse_checksum(tile)?;
        Ok(self
            .scene_dir(scene)
            .join(format!("{:016x}-{checksum:08x}.{SHARD_EXTENSION}", tile.id)))
    }

    /// Path of the stored codebook of a mixture manifest (`None` for a dense one); it exists
    /// only once verified.
    ///
    /// Errors: [`Error::Format`] when the manifest checksum is not 8 hex digits.
    pub fn codebook_path(&self, manifest: &Manifest) -> Result<Option<PathBuf>> {
        let Some(t) = codebook_tile(manifest) else {
            return Ok(None);
        };
        let checksum = parse_checksum(&t)?;
        Ok(Some(self.scene_dir(&manifest.scene_id).join(format!(
            "codebook-{checksum:08x}.{CODEBOOK_EXTENSION}"
        ))))
    }

    /// Verifies a complete partial download of a mixture manifest's codebook
    /// ([`verify_codebook`]) and renames it into place (then syncs the folders), like
    /// [`Self::commit_partial`] for a shard.
    ///
    /// Errors: verification ([`Error::Format`]; `part` is left for the caller to discard), file
    /// I/O.
    pub fn commit_codebook_partial(&self, manifest: &Manifest, part: &Path) -> Result<()> {
        self.commit_codebook_partial_checked(manifest, part, false)
    }

    /// [`Self::commit_codebook_partial`], first checking the codebook's SHA-256 against a
    /// signed manifest when `signed`.
    ///
    /// Errors: as [`Self::commit_codebook_partial`]; [`Error::Untrusted`] for another SHA-256.
    pub fn commit_codebook_partial_checked(
        &self,
        manifest: &Manifest,
        part: &Path,
        signed: bool,
    ) -> Result<()> {
        let max = manifest.mixture.as_ref().map_or(0, |m| m.codebook_bytes);
        let bytes = read_partial(part, max)?;
        if signed && let Some(t) = codebook_tile(manifest) {
            signed::check_download(manifest, &t, &bytes)?;
        }
        verify_codebook(manifest, &bytes)?;
        drop(bytes);
        let Some(path) = self.codebook_path(manifest)? else {
            return Err(Error::internal("commit_codebook_partial: a dense manifest"));
        };
        self.move_into_place(&manifest.scene_id, part, &path, "store.commit_codebook")
    }

    /// Renames the verified partial download `part` to `path` in the scene's folder, then syncs
    /// both folders; `site` names the durability boundaries (`rename`, `dir_sync`,
    /// `partial_dir_sync`).
    fn move_into_place(&self, scene: &str, part: &Path, path: &Path, site: &str) -> Result<()> {
        let dir = self.ensure_scene_dir(scene)?;
        std::fs::rename(part, path).map_err(|e| Error::io(path, e))?;
        boundary_in(site, "rename");
        sync_dir(&dir)?;
        boundary_in(site, "dir_sync");
        sync_dir(&self.root.join("partial"))?;
        boundary_in(site, "partial_dir_sync");
        Ok(())
    }

    /// Reads and verifies the stored codebook of a mixture manifest ([`verify_codebook`]).
    ///
    /// Errors: [`Error::Format`] when it is missing (naming `slag-edge fetch`), truncated or
    /// corrupted on disk, or belongs to another scene; [`Error::Io`] when it cannot be read.
    pub fn codebook(&self, manifest: &Manifest) -> Result<Codebook> {
        self.codebook_checked(manifest, false)
    }

    /// [`Self::codebook`], and with `hashes` (a signed generation whose signature the caller
    /// verified) the file's SHA-256 compared with the manifest's too.
    ///
    /// Errors: as [`Self::codebook`]; [`Error::Untrusted`] for another SHA-256.
    pub fn codebook_checked(&self, manifest: &Manifest, hashes: bool) -> Result<Codebook> {
        let Some(path) = self.codebook_path(manifest)? else {
            return verify_codebook(manifest, &[]);
        };
        let max = manifest.mixture.as_ref().map_or(0, |m| m.codebook_bytes);
        let Some(bytes) = read_regular(&path, max, "the mixture scene's codebook")? else {
            return Err(Error::format(
                &path,
                "the mixture scene's codebook is not stored; run `slag-edge fetch` again",
            ));
        };
        if hashes && let Some(t) = codebook_tile(manifest) {
            signed::check_download(manifest, &t, &bytes)?;
        }
        verify_codebook(manifest, &bytes)
    }

    /// Removes codebook files of `scene` other than `keep` (a file name from
    /// [`Self::codebook_path`]); returns how many were removed.
    ///
    /// Errors: [`Error::Io`] when a file exists but cannot be removed.
    pub fn remove_other_codebooks(&self, scene: &str, keep: Option<&Path>) -> Result<usize> {
        let Ok(rd) = std::fs::read_dir(self.scene_dir(scene)) else {
            return Ok(0);
        };
        let mut removed = 0;
        for e in rd.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            let ours = name.starts_with("codebook-")
                && name.ends_with(&format!(".{CODEBOOK_EXTENSION}"))
                && keep.and_then(|k| k.file_name()) != Some(e.file_name().as_os_str());
            if ours {
                std::fs::remove_file(e.path()).map_err(|err| Error::io(e.path(), err))?;
                boundary("store.evict_codebook:remove");
                removed += 1;
            }
        }
        Ok(removed)
    }

    /// Path of the partial download of `tile` (its checksum names the content it resumes):
    /// `DIR/partial/<scene>-<tile>-<checksum>.part`, always a plain file name inside
    /// `DIR/partial`: a scene id failing [`valid_scene_id`] or a checksum that is not 8 hex digits
    /// (both come from outside: the command line and the server's manifest) is written as hex of
    /// its bytes (prefixed `x`), so no `/`, `..` or NUL can reach the file system.
    pub fn partial_path(&self, scene: &str, tile: &TileInfo) -> PathBuf {
        let x = |s: &str| format!("x{}", hex(&s.as_bytes()[..s.len().min(64)]));
        let scene = if valid_scene_id(scene) {
            scene.to_string()
        } else {
            x(scene)
        };
        let checksum = match parse_checksum(tile) {
            Ok(c) => format!("{c:08x}"),
            Err(_) => x(&tile.checksum),
        };
        self.root
            .join("partial")
            .join(format!("{scene}-{}-{checksum}.part", tile.id))
    }

    /// Removes the partial downloads of `scene` except those in `keep` (file names from
    /// [`EdgeStore::partial_path`]), and temporary files of interrupted shard writes in the
    /// scene's shard folder; returns how many were removed. Called after a completed fetch:
    /// partials of stored shards and of older generations can never be resumed into anything
    /// useful.
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
                boundary("store.clean_partials:remove_partial");
                removed += 1;
            }
        }
        if let Ok(rd) = std::fs::read_dir(self.scene_dir(scene)) {
            for e in rd.flatten() {
                if e.file_name().to_string_lossy().ends_with(".tmp")
                    && std::fs::remove_file(e.path()).is_ok()
                {
                    boundary("store.clean_partials:remove_tmp");
                    removed += 1;
                }
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

    /// Like [`Self::manifest`], but a scene never fetched is an error.
    ///
    /// Errors: [`Error::Param`] `scene` when there is no completed fetch of `scene` (a fetch of
    /// it comes first); as [`Self::manifest`] otherwise.
    pub fn current_manifest(&self, scene: &str) -> Result<Manifest> {
        self.manifest(scene)?.ok_or_else(|| {
            Error::param(
                "scene",
                format!("{scene:?}"),
                format!(
                    "a scene fetched into store {}, which has no completed fetch of it",
                    self.root.display()
                ),
            )
        })
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
    ///
    /// Errors: [`Error::Format`] for a checksum that is not 8 hex digits.
    pub fn has_shard(&self, scene: &str, tile: &TileInfo) -> Result<bool> {
        Ok(std::fs::symlink_metadata(self.shard_path(scene, tile)?).is_ok_and(|m| m.is_file()))
    }

    /// Raw bytes of a stored shard (as downloaded; the caller decodes and verifies), `None` when
    /// it is not stored. Only a regular file is read, and at most the manifest's length
    /// ([`read_regular`]).
    ///
    /// Errors: [`Error::Format`] for a symbolic link, FIFO, device, socket or folder in the
    /// shard's place, or a file longer than the manifest says; [`Error::Io`] when the file
    /// exists but cannot be read.
    pub fn shard_bytes(&self, scene: &str, tile: &TileInfo) -> Result<Option<Vec<u8>>> {
        let path = self.shard_path(scene, tile)?;
        read_regular(
            &path,
            tile.bytes,
            &format!("shard {} of scene {scene}", tile.id),
        )
    }

    /// Creates the scene's shard folder (synced into its parent the first time).
    fn ensure_scene_dir(&self, scene: &str) -> Result<PathBuf> {
        let dir = self.scene_dir(scene);
        if !dir.is_dir() {
            std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
            boundary("store.scene_dir:create");
            sync_dir(&self.root.join("shards"))?;
            boundary("store.scene_dir:dir_sync");
        }
        Ok(dir)
    }

    /// Verifies `bytes` ([`verify_shard`]) and stores them durably: written to a temporary file in
    /// the scene's folder, synced, renamed to [`Self::shard_path`], folder synced.
    ///
    /// Errors: verification ([`Error::Format`] / [`Error::Unsupported`]; nothing is stored) or
    /// file I/O ([`Error::Io`]; at most a `.tmp` file is left, removed by the next fetch).
    pub fn commit_shard(&self, manifest: &Manifest, tile: &TileInfo, bytes: &[u8]) -> Result<()> {
        verify_any_shard(manifest, tile, bytes, WholeFile::Crc32)?;
        let path = self.shard_path(&manifest.scene_id, tile)?;
        self.ensure_scene_dir(&manifest.scene_id)?;
        let tmp = path.with_extension(format!("{SHARD_EXTENSION}.tmp"));
        write_durably(&path, &tmp, "store.write_shard", bytes)
    }

    /// Verifies a complete, synced partial download `part` ([`verify_shard`]) and moves it into
    /// place with one `rename` (same file system), then syncs the folder. Nothing is copied: the
    /// bytes are read once to verify them and freed.
    ///
    /// Errors: verification ([`Error::Format`] / [`Error::Unsupported`]; `part` is left for the
    /// caller to discard) or file I/O ([`Error::Io`]).
    pub fn commit_partial(&self, manifest: &Manifest, tile: &TileInfo, part: &Path) -> Result<()> {
        self.commit_partial_checked(manifest, tile, part, false)
    }

    /// [`Self::commit_partial`], also checking the shard's SHA-256 against a signed manifest
    /// when `signed`, beside its verification; a file failing both is refused for its SHA-256,
    /// so that any other bytes are named as such.
    ///
    /// Errors: as [`Self::commit_partial`]; [`Error::Untrusted`] for another SHA-256.
    pub fn commit_partial_checked(
        &self,
        manifest: &Manifest,
        tile: &TileInfo,
        part: &Path,
        signed: bool,
    ) -> Result<()> {
        let bytes = read_partial(part, tile.bytes)?;
        // The hash runs beside the verification, on the rayon pool; the SHA-256's error first.
        let (hashed, verified) = rayon::join(
            || match signed {
                true => signed::check_download(manifest, tile, &bytes),
                false => Ok(()),
            },
            || verify_any_shard(manifest, tile, &bytes, WholeFile::Crc32),
        );
        hashed.and(verified)?;
        drop(bytes);
        let path = self.shard_path(&manifest.scene_id, tile)?;
        self.move_into_place(&manifest.scene_id, part, &path, "store.commit_shard")
    }

    /// [`Self::commit_partial_checked`] of a signed download received whole in this run, from
    /// what the fetch kept of it ([`Received`]): the bytes it wrote to `part` (synced) and
    /// their SHA-256, hashed on another thread while they arrived. The digest is compared with
    /// the signed manifest's and the same bytes are verified (length, CRC-32s, decode); the
    /// file is neither read back nor hashed again. A file changed in `partial/` by another
    /// process between its write and this rename would go unseen here, as a stored file
    /// changed after its commit does: a server with the key hashes every tile again on load.
    ///
    /// Errors: as [`Self::commit_partial_checked`].
    pub fn commit_partial_received(
        &self,
        manifest: &Manifest,
        tile: &TileInfo,
        part: &Path,
        received: &Received,
    ) -> Result<()> {
        signed::compare_download(manifest, tile, &received.sha256)?;
        verify_any_shard(manifest, tile, &received.bytes, WholeFile::Crc32)?;
        let path = self.shard_path(&manifest.scene_id, tile)?;
        self.move_into_place(&manifest.scene_id, part, &path, "store.commit_shard")
    }

    /// Holds the scene's committed generation still: while the guard lives, no other holder
    /// commits a generation or evicts shards, and a load ([`Self::committed`] and the shard
    /// reads after it) sees one committed generation whole. `fetch` holds it for its commit and
    /// evictions, `Engine::load_with` for its reads; downloads run without it (a new shard file
    /// is no part of any committed generation until the commit lists it). Shared by clones.
    pub fn lock_generation(&self) -> MutexGuard<'_, ()> {
        // A holder that panicked left nothing half done that the lock protects (the commit is
        // one sled transaction): carry on.
        self.generation
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Serialises fetches into this store (shared by clones): `fetch` holds it from its start to
    /// its end, so a fetch started while another runs waits for it instead of evicting the
    /// shards the other one is about to commit.
    pub async fn lock_fetching(&self) -> tokio::sync::MutexGuard<'_, ()> {
        self.fetching.lock().await
    }

    /// The scene's last committed generation: manifest, fetch record and commit count. Call it
    /// with [`Self::lock_generation`] held, and keep holding it while reading the shards.
    ///
    /// Errors: as [`Self::current_manifest`] and [`Self::fetch_record`].
    pub fn committed(&self, scene: &str) -> Result<Committed> {
        let seq = self.commits.load(Ordering::SeqCst);
        Ok(Committed {
            manifest: self.current_manifest(scene)?,
            record: self.fetch_record(scene)?,
            seq,
        })
    }

    /// Makes `manifest` the scene's current one and records the fetch, in one transaction, then
    /// flushes. Called after every selected shard is committed (their files and folders synced),
    /// with [`Self::lock_generation`] held. Copies of both are written first beside the scene's
    /// shard files (module doc), for a rebuild of the database: they describe shards that are all
    /// in place already.
    ///
    /// Errors: store I/O, an aborted transaction ([`Error::Internal`]).
    pub fn commit_fetch(&self, manifest: &Manifest, record: &FetchRecord) -> Result<()> {
        self.commit_fetch_signed(manifest, None, record)
    }

    /// Stored shards of `scene` as `(tile id, checksum, bytes on disk)`, in no particular order.
    ///
    /// Errors: the scene's shard folder exists but cannot be listed ([`Error::Io`]).
    pub fn stored_shards(&self, scene: &str) -> Result<Vec<(u64, u32, u64)>> {
        let dir = self.scene_dir(scene);
        let rd = match std::fs::read_dir(&dir) {
            Ok(rd) => rd,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(Error::io(&dir, e)),
        };
        let mut out = Vec::new();
        for e in rd.flatten() {
            if let Some((tile, checksum)) = parse_shard_name(&e.file_name().to_string_lossy()) {
                let len = e.metadata().map(|m| m.len()).unwrap_or(0);
                out.push((tile, checksum, len));
            }
        }
        Ok(out)
    }

    /// Removes one stored shard (by tile id and checksum); returns whether it existed.
    ///
    /// Errors: [`Error::Io`] when the file exists but cannot be removed.
    pub fn remove_shard(&self, scene: &str, tile: u64, checksum: u32) -> Result<bool> {
        let path = self
            .scene_dir(scene)
            .join(format!("{tile:016x}-{checksum:08x}.{SHARD_EXTENSION}"));
        match std::fs::remove_file(&path) {
            Ok(()) => {
                boundary("store.evict_shard:remove");
                Ok(true)
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(false),
            Err(e) => Err(Error::io(path, e)),
        }
    }

    /// Flushes the sled database (manifests, fetch records) and syncs the scene folders.
    ///
    /// Errors: store I/O.
    pub fn flush(&self) -> Result<()> {
        self.db.flush().map_err(|e| self.err(e))?;
        boundary("store.flush:db");
        sync_dir(&self.root.join("shards"))?;
        boundary("store.flush:dir_sync");
        Ok(())
    }

    /// Bytes the store uses on disk (shard files, sled files, partial downloads, quarantine).
    pub fn disk_bytes(&self) -> u64 {
        dir_bytes(&self.root)
    }
}

#[cfg(test)]
mod tests {
    use super::parse_shard_name;

    #[test]
    fn shard_file_names_round_trip_and_others_are_ignored() {
        let name = format!("{:016x}-{:08x}.shard", 0x1234u64, 0xdeadbeefu32);
        assert_eq!(parse_shard_name(&name), Some((0x1234, 0xdeadbeef)));
        for other in [
            "0000000000001234-deadbeef.shard.tmp",
            "1234-deadbeef.shard",
            "0000000000001234-deadbeef.part",
            "000000000000123g-deadbeef.shard",
        ] {
            assert_eq!(parse_shard_name(other), None, "{other}");
        }
    }
}
