//! The cloud shard store (`sled` 0.34): manifests, tile index and shards of many scenes.
//!
//! Trees (keys are `scene id ++ 0x00 ++ generation u64 BE [++ tile id u64 BE]`):
//! - `current`: scene id → committed generation (u64 BE), the *current pointer*;
//! - `manifests`: scene/generation → manifest JSON;
//! - `tiles`: scene/generation/tile → [`TileInfo`] JSON (the tile index);
//! - `shards`: scene/generation/tile → shard bytes;
//! - `codebooks`: scene/generation → codebook file bytes (mixture scenes only,
//!   [`slag_common::shards::mixture`]);
//! - `signatures`: scene/generation → the detached signature of that generation's manifest
//!   bytes ([`slag_common::shards::signature`]), for generations committed with a signing key
//!   ([`SceneWriter::commit_signed`]).
//!
//! Writes are versioned: a [`SceneWriter`] puts shards under a fresh generation nobody reads,
//! then [`SceneWriter::commit`] inserts the manifest, the tile index, the signature (when signed)
//! and the current pointer in one sled transaction over four trees and flushes. A crash before that transaction leaves the
//! previous generation current and intact; leftovers of the unfinished generation are removed by
//! the next writer of that scene. One writer per scene at a time (sled locks the folder against
//! other processes).
//!
//! Every sled step that changes the store is a durability boundary of [`slag_common::fault`]
//! (crash tests): `shards.writer:remove_leftover` (each key of an unfinished generation removed),
//! `shards.put_shard:insert`, `shards.put_codebook:insert`, `shards.commit:flush_shards`,
//! `shards.commit:flush_codebooks`, `shards.commit:transaction`, `shards.commit:flush`,
//! `shards.commit:remove_old` (each key of an older generation removed) and
//! `shards.commit:flush_removals`.

use std::path::Path;

use slag_common::fault::boundary;
use slag_common::mixture::MixtureEmbeddings;
use slag_common::shards::signature::SigningKey;
use slag_common::shards::{GaussianSource, Manifest, TileInfo, shard_checksum, valid_scene_id};
use slag_common::{Error, Result};
use sled::Transactional;
use sled::transaction::{ConflictableTransactionError, TransactionError};

use crate::partition::{PartitionParams, partition_mixture_with, partition_with};

/// Handle on a sled shard store folder. Cheap to clone (sled handles are reference counted).
#[derive(Clone)]
pub struct ShardStore {
    db: sled::Db,
    current: sled::Tree,
    manifests: sled::Tree,
    tiles: sled::Tree,
    shards: sled::Tree,
    codebooks: sled::Tree,
    signatures: sled::Tree,
    /// The least generation [`ShardStore::writer`] gives a scene ([`ShardStore::starting_at`]).
    start_generation: u64,
}

/// The current manifest of a scene as stored: its exact JSON bytes (what is served and signed),
/// its generation, and its signature file when the generation was signed.
#[derive(Debug, Clone)]
pub struct StoredManifest {
    /// Committed generation.
    pub generation: u64,
    /// The manifest JSON exactly as stored, served and signed.
    pub bytes: sled::IVec,
    /// The signature file of `bytes` ([`slag_common::shards::signature::ManifestSignature`]),
    /// `None` for a generation committed unsigned.
    pub signature: Option<sled::IVec>,
}

impl std::fmt::Debug for ShardStore {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ShardStore").finish_non_exhaustive()
    }
}

fn prefix(scene: &str, generation: u64) -> Vec<u8> {
    let mut k = Vec::with_capacity(scene.len() + 9);
    k.extend_from_slice(scene.as_bytes());
    k.push(0);
    k.extend_from_slice(&generation.to_be_bytes());
    k
}

fn tile_key(scene: &str, generation: u64, tile: u64) -> Vec<u8> {
    let mut k = prefix(scene, generation);
    k.extend_from_slice(&tile.to_be_bytes());
    k
}

fn be_u64(v: &[u8]) -> Option<u64> {
    Some(u64::from_be_bytes(v.try_into().ok()?))
}

fn check_scene(scene: &str) -> Result<()> {
    if valid_scene_id(scene) {
        Ok(())
    } else {
        Err(Error::param(
            "scene_id",
            format!("{scene:?}"),
            "1-64 characters of A-Z a-z 0-9 _ - .",
        ))
    }
}

impl ShardStore {
    /// Opens (creating if needed) the store folder `path`.
    ///
    /// Errors: another process holds it ([`Error::Invalid`], after waiting up to 2 s for a
    /// store just closed in this process to let go of its lock); the folder cannot be opened
    /// ([`Error::Io`] / [`Error::Format`]).
    pub fn open(path: &Path) -> Result<ShardStore> {
        let db = open_db(path)?;
        let tree = |name: &str| db.open_tree(name).map_err(|e| sled_err(path, e));
        Ok(ShardStore {
            current: tree("current")?,
            manifests: tree("manifests")?,
            tiles: tree("tiles")?,
            shards: tree("shards")?,
            codebooks: tree("codebooks")?,
            signatures: tree("signatures")?,
            start_generation: 1,
            db,
        })
    }

    /// This store, whose next generation of a scene is at least `start` (≥ 1): a publisher that
    /// re-creates its store (a lost disk, a new machine) carries on above the generation its
    /// robots hold, which they would otherwise refuse as a replay. A scene whose committed
    /// generation is `start` or more carries on from it as usual.
    ///
    /// Errors: [`Error::Param`] `start_generation` for 0.
    pub fn starting_at(mut self, start: u64) -> Result<ShardStore> {
        if start == 0 {
            return Err(Error::param(
                "start_generation",
                0,
                "a generation ≥ 1 (above the one the robots hold)",
            ));
        }
        self.start_generation = start;
        Ok(self)
    }

    /// Committed generation of `scene`, if any.
    pub fn current_generation(&self, scene: &str) -> Result<Option<u64>> {
        Ok(self
            .current
            .get(scene.as_bytes())
            .map_err(db_err)?
            .and_then(|v| be_u64(&v)))
    }

    /// Scene ids with a committed generation, ascending.
    pub fn scenes(&self) -> Result<Vec<String>> {
        self.current
            .iter()
            .keys()
            .map(|k| {
                k.map(|k| String::from_utf8_lossy(&k).into_owned())
                    .map_err(db_err)
            })
            .collect()
    }

    /// The current manifest of `scene`; `None` for an unknown scene.
    ///
    /// Errors: invalid scene id, storage errors, a corrupted manifest ([`Error::Format`]).
    pub fn manifest(&self, scene: &str) -> Result<Option<Manifest>> {
        check_scene(scene)?;
        let Some(g) = self.current_generation(scene)? else {
            return Ok(None);
        };
        match self.manifests.get(prefix(scene, g)).map_err(db_err)? {
            Some(b) => Manifest::from_json(&b, &format!("store manifest {scene}@{g}")).map(Some),
            None => Err(Error::format(
                "<store>",
                format!("scene {scene} generation {g} has no manifest"),
            )),
        }
    }

    /// The current manifest of `scene` as stored ([`StoredManifest`]: exact bytes, checked to
    /// parse, and signature); `None` for an unknown scene.
    ///
    /// Errors: as [`Self::manifest`].
    pub fn stored_manifest(&self, scene: &str) -> Result<Option<StoredManifest>> {
        check_scene(scene)?;
        let Some(g) = self.current_generation(scene)? else {
            return Ok(None);
        };
        let Some(bytes) = self.manifests.get(prefix(scene, g)).map_err(db_err)? else {
            return Err(Error::format(
                "<store>",
                format!("scene {scene} generation {g} has no manifest"),
            ));
        };
        Manifest::from_json(&bytes, &format!("store manifest {scene}@{g}"))?;
        let signature = self.signatures.get(prefix(scene, g)).map_err(db_err)?;
        Ok(Some(StoredManifest {
            generation: g,
            bytes,
            signature,
        }))
    }

    /// Raw bytes of shard `tile` in the current generation of `scene`; `None` if unknown.
    ///
    /// Errors: invalid scene id, storage errors.
    pub fn shard(&self, scene: &str, tile: u64) -> Result<Option<sled::IVec>> {
        check_scene(scene)?;
        let Some(g) = self.current_generation(scene)? else {
            return Ok(None);
        };
        self.shards.get(tile_key(scene, g, tile)).map_err(db_err)
    }

    /// Raw bytes of the codebook of the current generation of `scene`; `None` for an unknown
    /// scene or a dense one (no codebook).
    ///
    /// Errors: invalid scene id, storage errors.
    pub fn codebook(&self, scene: &str) -> Result<Option<sled::IVec>> {
        check_scene(scene)?;
        let Some(g) = self.current_generation(scene)? else {
            return Ok(None);
        };
        self.codebooks.get(prefix(scene, g)).map_err(db_err)
    }

    /// Total bytes of the stored shards of the current generation of `scene` (each tile of
    /// its manifest, as read back from the store, plus the codebook of a mixture scene); `None`
    /// for an unknown scene.
    ///
    /// Errors: invalid scene id, storage errors, a manifest tile without a stored shard
    /// ([`Error::Format`]: the store is damaged, re-run partition).
    pub fn scene_bytes(&self, scene: &str) -> Result<Option<u64>> {
        let Some(m) = self.manifest(scene)? else {
            return Ok(None);
        };
        let mut total = 0u64;
        for t in &m.tiles {
            let b = self.shard(scene, t.id)?.ok_or_else(|| {
                Error::format(
                    "<store>",
                    format!(
                        "scene {scene} lists tile {} but has no shard for it; re-run partition",
                        t.id
                    ),
                )
            })?;
            total += b.len() as u64;
        }
        if m.mixture.is_some() {
            let b = self.codebook(scene)?.ok_or_else(|| {
                Error::format(
                    "<store>",
                    format!("mixture scene {scene} has no codebook; re-run partition"),
                )
            })?;
            total += b.len() as u64;
        }
        Ok(Some(total))
    }

    /// Tile info of `tile` in the current generation (from the tile index tree).
    ///
    /// Errors: invalid scene id, storage errors, corrupted entries.
    pub fn tile(&self, scene: &str, tile: u64) -> Result<Option<TileInfo>> {
        check_scene(scene)?;
        let Some(g) = self.current_generation(scene)? else {
            return Ok(None);
        };
        match self.tiles.get(tile_key(scene, g, tile)).map_err(db_err)? {
            Some(b) => serde_json::from_slice(&b)
                .map(Some)
                .map_err(|e| Error::format("<store>", format!("tile index entry: {e}"))),
            None => Ok(None),
        }
    }

    /// Every generation of `scene` with stored data (committed or left over by an interrupted
    /// writer), ascending. Diagnostics; readers only ever see [`ShardStore::current_generation`].
    ///
    /// Errors: invalid scene id, storage errors.
    pub fn stored_generations(&self, scene: &str) -> Result<Vec<u64>> {
        check_scene(scene)?;
        let mut p = scene.as_bytes().to_vec();
        p.push(0);
        let mut gens = std::collections::BTreeSet::new();
        for tree in self.generation_trees() {
            for kv in tree.scan_prefix(&p) {
                let (k, _) = kv.map_err(db_err)?;
                if let Some(g) = k.get(p.len()..p.len() + 8).and_then(be_u64) {
                    gens.insert(g);
                }
            }
        }
        Ok(gens.into_iter().collect())
    }

    /// The trees whose keys are `scene \0 generation …`: every per-generation record of a scene.
    fn generation_trees(&self) -> [&sled::Tree; 5] {
        [
            &self.shards,
            &self.tiles,
            &self.manifests,
            &self.codebooks,
            &self.signatures,
        ]
    }

    /// Starts writing a new generation of `scene`, first removing leftovers of generations that
    /// were never committed.
    ///
    /// Errors: invalid scene id, storage errors.
    pub fn writer(&self, scene: &str) -> Result<SceneWriter<'_>> {
        check_scene(scene)?;
        let current = self.current_generation(scene)?;
        self.remove_generations(scene, "shards.writer:remove_leftover", |g| {
            Some(g) != current
        })?;
        Ok(SceneWriter {
            store: self,
            scene: scene.to_string(),
            generation: current.map_or(1, |g| g + 1).max(self.start_generation),
        })
    }

    /// Deletes every stored generation of `scene` for which `drop(generation)` is true; `name`
    /// names the durability boundary after each removal.
    fn remove_generations(
        &self,
        scene: &str,
        name: &str,
        drop: impl Fn(u64) -> bool,
    ) -> Result<()> {
        let mut p = scene.as_bytes().to_vec();
        p.push(0);
        for tree in self.generation_trees() {
            for kv in tree.scan_prefix(&p) {
                let (k, _) = kv.map_err(db_err)?;
                let g = k.get(p.len()..p.len() + 8).and_then(be_u64);
                if g.is_some_and(&drop) {
                    tree.remove(k).map_err(db_err)?;
                    boundary(name);
                }
            }
        }
        Ok(())
    }

    /// Flushes all trees to disk.
    ///
    /// Errors: storage errors.
    pub fn flush(&self) -> Result<()> {
        self.db.flush().map(|_| ()).map_err(db_err)
    }
}

/// Writes one new generation of a scene; invisible to readers until [`SceneWriter::commit`].
/// Dropping it without committing leaves the previous generation current.
#[derive(Debug)]
pub struct SceneWriter<'a> {
    store: &'a ShardStore,
    scene: String,
    generation: u64,
}

impl SceneWriter<'_> {
    /// Generation this writer will commit.
    pub fn generation(&self) -> u64 {
        self.generation
    }

    /// Stores the bytes of shard `tile` (not yet visible).
    ///
    /// Errors: storage errors.
    pub fn put_shard(&mut self, tile: u64, bytes: &[u8]) -> Result<()> {
        self.store
            .shards
            .insert(tile_key(&self.scene, self.generation, tile), bytes)
            .map_err(db_err)?;
        boundary("shards.put_shard:insert");
        Ok(())
    }

    /// Stores the codebook of a mixture generation (not yet visible).
    ///
    /// Errors: storage errors.
    pub fn put_codebook(&mut self, bytes: &[u8]) -> Result<()> {
        self.store
            .codebooks
            .insert(prefix(&self.scene, self.generation), bytes)
            .map_err(db_err)?;
        boundary("shards.put_codebook:insert");
        Ok(())
    }

    /// Checks that every manifest tile has a stored shard with the listed size and checksum
    /// (and a mixture manifest's codebook likewise),
    /// then atomically publishes manifest + tile index + current pointer, flushes, and deletes
    /// older generations. Returns the manifest with `generation` set.
    ///
    /// Errors: scene mismatch or missing/mismatching shards ([`Error::Internal`]: the writer's
    /// contract), storage errors.
    pub fn commit(self, manifest: Manifest) -> Result<Manifest> {
        self.commit_signed(manifest, None)
    }

    /// [`Self::commit`], signing the manifest's exact JSON bytes (generation set) with `key` when
    /// given; the signature is stored in the same transaction as the manifest and the current
    /// pointer, so a signed generation is never visible without its signature.
    ///
    /// Errors: as [`Self::commit`].
    pub fn commit_signed(
        self,
        mut manifest: Manifest,
        key: Option<&SigningKey>,
    ) -> Result<Manifest> {
        self.check_stored(&manifest)?;
        manifest.generation = self.generation;
        let json = manifest.to_json();
        let signature = key.map(|k| k.sign(&json).to_json());
        let tile_entries: Vec<(Vec<u8>, Vec<u8>)> = manifest
            .tiles
            .iter()
            .map(|t| {
                (
                    tile_key(&self.scene, self.generation, t.id),
                    serde_json::to_vec(t).unwrap_or_default(),
                )
            })
            .collect();
        let s = self.store;
        // Shards and codebook must be durable before the pointer flip can be.
        s.shards.flush().map_err(db_err)?;
        boundary("shards.commit:flush_shards");
        s.codebooks.flush().map_err(db_err)?;
        boundary("shards.commit:flush_codebooks");
        let g = self.generation;
        (&s.manifests, &s.tiles, &s.current, &s.signatures)
            .transaction(|(m, t, c, sig)| {
                m.insert(prefix(&self.scene, g), json.as_slice())?;
                if let Some(signed) = &signature {
                    sig.insert(prefix(&self.scene, g), signed.as_slice())?;
                }
                for (k, v) in &tile_entries {
                    t.insert(k.as_slice(), v.as_slice())?;
                }
                c.insert(self.scene.as_bytes(), &g.to_be_bytes())?;
                Ok::<(), ConflictableTransactionError<()>>(())
            })
            .map_err(|e: TransactionError<()>| match e {
                TransactionError::Storage(e) => db_err(e),
                TransactionError::Abort(()) => Error::internal("store transaction aborted"),
            })?;
        boundary("shards.commit:transaction");
        s.flush()?;
        boundary("shards.commit:flush");
        s.remove_generations(&self.scene, "shards.commit:remove_old", |old| old != g)?;
        s.flush()?;
        boundary("shards.commit:flush_removals");
        Ok(manifest)
    }

    /// Checks that `manifest` is for this writer's scene and that this generation holds every
    /// tile's shard, and a mixture manifest's codebook, with the listed size and checksum.
    ///
    /// Errors: [`Error::Internal`] (the writer's contract) for another scene or a missing or
    /// mismatching shard or codebook; storage errors.
    fn check_stored(&self, manifest: &Manifest) -> Result<()> {
        if manifest.scene_id != self.scene {
            return Err(Error::internal(format!(
                "manifest is for scene {} but writer for {}",
                manifest.scene_id, self.scene
            )));
        }
        let shards = &self.store.shards;
        for t in &manifest.tiles {
            let b = shards
                .get(tile_key(&self.scene, self.generation, t.id))
                .map_err(db_err)?;
            if !stored_as_listed(b, t.bytes, &t.checksum) {
                return Err(Error::internal(format!(
                    "tile {} has no stored shard matching the manifest",
                    t.id
                )));
            }
        }
        if let Some(x) = &manifest.mixture {
            let codebooks = &self.store.codebooks;
            let b = codebooks
                .get(prefix(&self.scene, self.generation))
                .map_err(db_err)?;
            if !stored_as_listed(b, x.codebook_bytes, &x.codebook_checksum) {
                return Err(Error::internal(
                    "the mixture manifest's codebook is not stored with its size and checksum",
                ));
            }
        }
        Ok(())
    }
}

/// Whether `stored` is present with the manifest's length `bytes` and CRC-32 `checksum` (8
/// lower-case hex digits, [`shard_checksum`]).
fn stored_as_listed(stored: Option<sled::IVec>, bytes: u64, checksum: &str) -> bool {
    stored.is_some_and(|b| {
        b.len() as u64 == bytes && format!("{:08x}", shard_checksum(&b)) == checksum
    })
}

/// Partitions `src` straight into `store` as a new generation of `params.scene_id`, committing
/// only after every shard is stored.
///
/// Errors: as [`partition_with`] and [`SceneWriter::commit`].
pub fn partition_into_store(
    store: &ShardStore,
    src: &impl GaussianSource,
    params: &PartitionParams,
) -> Result<Manifest> {
    partition_into_store_signed(store, src, params, None)
}

/// [`partition_into_store`], the manifest signed with `key` when given
/// ([`SceneWriter::commit_signed`]).
///
/// Errors: as [`partition_into_store`].
pub fn partition_into_store_signed(
    store: &ShardStore,
    src: &impl GaussianSource,
    params: &PartitionParams,
    key: Option<&SigningKey>,
) -> Result<Manifest> {
    let mut w = store.writer(&params.scene_id)?;
    let manifest = partition_with(src, params, |info, bytes| w.put_shard(info.id, &bytes))?;
    w.commit_signed(manifest, key)
}

/// Partitions the mixture `mix` (rows, ids and display columns from `src`, see
/// [`partition_mixture_with`]) into `store` as a new generation: shards and codebook stored,
/// then committed together.
///
/// Errors: as [`partition_mixture_with`] and [`SceneWriter::commit`].
pub fn partition_mixture_into_store(
    store: &ShardStore,
    src: &impl GaussianSource,
    mix: &MixtureEmbeddings,
    params: &PartitionParams,
) -> Result<Manifest> {
    partition_mixture_into_store_signed(store, src, mix, params, None)
}

/// [`partition_mixture_into_store`], the manifest signed with `key` when given.
///
/// Errors: as [`partition_mixture_into_store`].
pub fn partition_mixture_into_store_signed(
    store: &ShardStore,
    src: &impl GaussianSource,
    mix: &MixtureEmbeddings,
    params: &PartitionParams,
    key: Option<&SigningKey>,
) -> Result<Manifest> {
    let mut w = store.writer(&params.scene_id)?;
    let (manifest, codebook) =
        partition_mixture_with(src, mix, params, |info, bytes| w.put_shard(info.id, &bytes))?;
    w.put_codebook(&codebook)?;
    w.commit_signed(manifest, key)
}

fn db_err(e: sled::Error) -> Error {
    match e {
        sled::Error::Io(io) => Error::io("<shard store>", io),
        other => Error::format(
            "<shard store>",
            format!("{other}; the store may be corrupted, re-run partition into a new folder"),
        ),
    }
}

/// How long [`open_db`] waits for a lock that a store closed in this process still holds.
const LOCK_WAIT: std::time::Duration = std::time::Duration::from_secs(2);

/// `sled::open(path)`, waiting up to [`LOCK_WAIT`] while its lock is held: a store dropped in
/// this process (a `partition` just done, say) keeps its lock until sled's flusher thread stops,
/// within its flush interval (500 ms). A lock still held after that belongs to another process
/// (or to a store still open in this one), and the error says so.
fn open_db(path: &Path) -> Result<sled::Db> {
    let t0 = std::time::Instant::now();
    loop {
        match sled::open(path) {
            // sled reports the lock as an `Other` I/O error that names it.
            Err(sled::Error::Io(io)) if io.to_string().contains("could not acquire lock") => {
                if t0.elapsed() >= LOCK_WAIT {
                    return Err(Error::Invalid(format!(
                        "shard store {} is in use by another process (a running `slag-shards \
                         serve` or `partition`?): stop it, or partition into another store ({io})",
                        path.display()
                    )));
                }
                std::thread::sleep(std::time::Duration::from_millis(20));
            }
            other => return other.map_err(|e| sled_err(path, e)),
        }
    }
}

fn sled_err(path: &Path, e: sled::Error) -> Error {
    match e {
        sled::Error::Io(io) => Error::io(path, io),
        other => Error::format(path, format!("cannot open shard store: {other}")),
    }
}
