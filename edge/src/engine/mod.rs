//! The query engine of the edge.
//!
//! - [`Engine`]: a loaded scene, what every query runs against: the manifest of the last
//!   completed fetch, the Gaussians of every verified shard in one [`VectorStore`] (the scan
//!   kernels' layout), their display columns, and the optional approximate (HNSW) index;
//!   [`Engine::answer`] answers one validated query over it. `slag-edge query`/`bench` and the
//!   examples use it directly.
//! - [`QueryEngine`] ([`queries`]): the one call both interfaces make, [`QueryEngine::query`]:
//!   admission ([`admission`]), scan, objects and answer frame against the generation served
//!   now; [`QueryEngine::reload`] swaps a new generation in. The HTTP server
//!   ([`crate::serve`]) and the ROS 2 node ([`crate::ros2`]) stand beside each other on it.
//!
//! An engine holds exactly one committed generation of the store: it is loaded under the
//! store's generation lock ([`EdgeStore::lock_generation`]), from the tiles that generation
//! lists ([`crate::store::Committed::tiles`]), and is immutable once built; a server swaps a
//! whole new `Arc<Engine>` in, so a query that took one keeps it to the end.

pub mod admission;
pub mod queries;

pub use admission::{Admission, Busy};
pub use queries::{
    DEFAULT_MAX_MATCHES, DEFAULT_MAX_SCANS, DEFAULT_SCAN_QUEUE, EngineOptions, QueryEngine,
    Verification, VerifyGate, check_matches, compact_answer,
};

use slag_common::Result;
use slag_common::shards::signature::TrustedKeys;
use slag_common::shards::{Manifest, MixtureShard, StoredShard};

use crate::query::{IndexKind, QueryAnswer, QueryContext, QueryParams, TextEmbedder};
use crate::scan::VectorStore;
use crate::scan::hnsw::{ApproxIndex, HnswBackend, HnswParams};
use crate::store::{EdgeStore, FetchRecord, SceneLoad};

/// HNSW build effort (`ef_construction`, both backends).
pub const HNSW_EF_CONSTRUCTION: usize = 100;
/// HNSW search breadth; also the largest `top_k` the index answers.
pub const HNSW_EF_SEARCH: usize = 1000;
/// Links per node of the Qdrant Edge graph (`m`; instant-distance fixes M = 32).
pub const HNSW_M: usize = 16;
/// Seed of instant-distance's layer assignment.
const HNSW_SEED: u64 = 0x51A6;

/// A loaded scene: the manifest, every verified shard's Gaussians in one [`VectorStore`], and the
/// optional approximate index.
pub struct Engine {
    /// Manifest of the last completed fetch.
    pub manifest: Manifest,
    /// All stored Gaussians of the scene.
    pub store: VectorStore,
    /// Which tiles were loaded / absent / rejected.
    pub load: SceneLoad,
    /// Approximate index, when enabled (`index=hnsw` queries).
    pub hnsw: Option<ApproxIndex>,
    /// Display columns of the same Gaussians, same row order (for `GET /query.ply`).
    pub display: crate::view::DisplayAttrs,
    /// Record of the fetch that committed this generation (`None` for a store rebuilt without
    /// one).
    pub record: Option<FetchRecord>,
    /// The store's commit count when this generation was read ([`crate::store::Committed::seq`]):
    /// of two engines of one process, the one with the larger count holds the later generation.
    pub seq: u64,
}

impl Engine {
    /// Loads `scene` from the store (verifying every shard) and builds the instant-distance HNSW
    /// index if `hnsw`: [`Engine::load_with`].
    ///
    /// A mixture scene ([`slag_common::shards::MixtureInfo`]) loads its codebook first and its
    /// shards into a mixture [`VectorStore`]; no HNSW index is built over mixture rows.
    ///
    /// Errors: as [`Engine::load_with`].
    pub fn load(edge: &EdgeStore, scene: &str, hnsw: bool) -> Result<Engine> {
        Engine::load_with(edge, scene, hnsw.then_some(HnswBackend::InstantDistance))
    }

    /// Loads `scene` from the store (verifying every shard) and, with `Some(backend)`, builds
    /// that backend's approximate index over every loaded row ([`ApproxIndex::build`] with
    /// [`HNSW_EF_CONSTRUCTION`], [`HNSW_EF_SEARCH`], [`HNSW_M`]; none for an empty scene). The
    /// build runs here, before the engine exists: `serve` does it at start-up and, on reload,
    /// on a blocking task while the previous engine keeps answering.
    ///
    /// Errors: [`slag_common::Error::Param`] `hnsw_backend` at once (before reading the store)
    /// for a backend this binary lacks; no completed fetch, store I/O, shards of another width
    /// or type than the manifest; a mixture scene's codebook missing, truncated or corrupted
    /// ([`slag_common::Error::Format`]: fetch again); a Gaussian id in two shards
    /// ([`slag_common::shards::ShardError::ManifestNotASet`]); the index build
    /// ([`ApproxIndex::build`]).
    pub fn load_with(edge: &EdgeStore, scene: &str, hnsw: Option<HnswBackend>) -> Result<Engine> {
        Engine::load_trusting(edge, scene, hnsw, None)
    }

    /// [`Engine::load_with`], and with `trusted` (the publisher's keys, as `serve` holds them)
    /// for a signed generation: the stored signature is verified over the stored manifest bytes
    /// and every tile's bytes are hashed as they are read, before their decoding
    /// ([`EdgeStore::load_committed`]); a tile whose SHA-256 or length differs from the signed
    /// manifest (a file rewritten on disk with its CRC-32s kept) is not served
    /// ([`SceneLoad::rejected`]), and [`SceneLoad::hashed`] counts those that match. An
    /// unsigned generation loads on its CRC-32s alone, with a warning.
    ///
    /// Errors: as [`Engine::load_with`]; [`slag_common::Error::Untrusted`] when the stored
    /// signature is by none of `trusted` or does not hold over the stored manifest, or the
    /// manifest lacks a SHA-256; a mixture scene's codebook whose SHA-256 differs.
    pub fn load_trusting(
        edge: &EdgeStore,
        scene: &str,
        hnsw: Option<HnswBackend>,
        trusted: Option<&TrustedKeys>,
    ) -> Result<Engine> {
        Engine::load_observed(edge, scene, hnsw, trusted, &mut |_| Ok(()))
    }

    /// [`Engine::load_trusting`], handing `observe` the rows loaded so far after each tile of
    /// the generation ([`LoadProgress`]; in manifest tile order, whether the tile passed, was
    /// rejected or had no file): a server that verifies in the background serves the tiles
    /// verified so far from it ([`QueryEngine::new`]). The check that no Gaussian id is in
    /// two shards and the approximate index come after the last tile.
    ///
    /// Errors: as [`Engine::load_trusting`]; the first error `observe` returns (the load
    /// stops there).
    pub fn load_observed(
        edge: &EdgeStore,
        scene: &str,
        hnsw: Option<HnswBackend>,
        trusted: Option<&TrustedKeys>,
        observe: &mut dyn FnMut(&LoadProgress<'_>) -> Result<()>,
    ) -> Result<Engine> {
        if let Some(b) = hnsw {
            b.require()?;
        }
        let loaded = {
            // One committed generation, read whole while no fetch commits or evicts.
            let _generation = edge.lock_generation();
            load_generation(edge, scene, trusted, observe)?
        };
        let (manifest, store, load, display, record, seq) = loaded;
        let hnsw = build_index(&store, scene, hnsw)?;
        Ok(Engine {
            manifest,
            store,
            load,
            hnsw,
            display,
            record,
            seq,
        })
    }

    /// The engine a server with the publisher's keys `trusted` answers from while the tiles of
    /// `scene`'s signed generation are hashed in the background ([`QueryEngine::new`]): the
    /// committed generation's manifest, fetch record and commit count, with **no rows** (and
    /// no approximate index), and [`SceneLoad::pending_verification`] counting its stored tiles.
    /// Its signature is verified here, over the stored manifest bytes, and a mixture scene's
    /// codebook is hashed and decoded (every row needs it). A served engine thus only ever
    /// holds rows decoded from bytes whose SHA-256 matched: this one none, the one the
    /// background load builds ([`Engine::load_trusting`]) every tile that passed.
    ///
    /// `None` without `trusted` or for an unsigned generation: the caller loads at once
    /// ([`Engine::load_trusting`], CRC-32s only).
    ///
    /// Errors: as [`Engine::load_trusting`] for the signature, the manifest and the codebook;
    /// store I/O.
    pub fn pending(
        edge: &EdgeStore,
        scene: &str,
        trusted: Option<&TrustedKeys>,
    ) -> Result<Option<Engine>> {
        if trusted.is_none() {
            return Ok(None);
        }
        let _generation = edge.lock_generation();
        let committed = edge.committed(scene)?;
        if edge.signature(scene)?.is_none() {
            return Ok(None);
        }
        let manifest = &committed.manifest;
        let hashes = signed_generation(edge, scene, manifest, trusted)?;
        let store = empty_store(edge, manifest, hashes)?;
        let mut pending = 0;
        for tile in committed.tiles() {
            pending += edge.has_shard(&manifest.scene_id, tile)? as usize;
        }
        let load = SceneLoad {
            absent_tiles: manifest.tiles.len() - pending,
            pending_verification: pending,
            ..SceneLoad::default()
        };
        Ok(Some(Engine {
            store,
            load,
            hnsw: None,
            display: crate::view::DisplayAttrs::new(),
            manifest: committed.manifest,
            record: committed.record,
            seq: committed.seq,
        }))
    }

    /// The engine a background verification serves after some of the tiles of this one (the
    /// engine of [`Engine::pending`]) passed: a copy of the rows in `progress` (those of the
    /// tiles verified so far, never of a pending or rejected one), with this generation's
    /// manifest, fetch record and commit count, no approximate index, and
    /// [`SceneLoad::pending_verification`] counting the stored tiles not yet handed.
    pub fn verified_so_far(&self, progress: &LoadProgress<'_>) -> Engine {
        let p = progress.load;
        let handed = p.loaded_tiles.len() + p.rejected.len();
        Engine {
            manifest: self.manifest.clone(),
            store: progress.store.clone(),
            load: SceneLoad {
                loaded_tiles: p.loaded_tiles.clone(),
                absent_tiles: self.load.absent_tiles,
                rejected: p.rejected.clone(),
                hashed: p.hashed,
                pending_verification: self.load.pending_verification.saturating_sub(handed),
            },
            hnsw: None,
            display: progress.display.clone(),
            record: self.record.clone(),
            seq: self.seq,
        }
    }

    /// What a query over this generation runs against: its rows, embedding model, scene-to-map
    /// transform, approximate index and display columns, with the prompt side (`text`, and
    /// `negatives`: the embeddings of [`crate::query::CANONICAL_NEGATIVES`], `[4][D]`).
    pub fn context<'a>(
        &'a self,
        text: &'a dyn TextEmbedder,
        negatives: &'a [Vec<f32>],
    ) -> QueryContext<'a> {
        QueryContext {
            store: &self.store,
            embedding_model: &self.manifest.model,
            to_map: self.manifest.frames.scene_to_map.as_ref(),
            text,
            negatives,
            hnsw: self.hnsw.as_ref(),
            display: Some(&self.display),
        }
    }

    /// Answers the validated query `q` over this generation ([`Self::context`]): scan, objects,
    /// and every coordinate in the answer's frame (the map frame when the manifest has a
    /// scene-to-map transform, unless `q.frame` is scene). While tiles are pending verification
    /// ([`Engine::pending`]) the answer says so ([`QueryAnswer::partial`]).
    ///
    /// Errors: as [`crate::query::run_query_framed`].
    pub fn answer(
        &self,
        text: &dyn TextEmbedder,
        negatives: &[Vec<f32>],
        q: &QueryParams,
    ) -> Result<QueryAnswer> {
        let pending = self.load.pending_verification;
        let mut a = if pending > 0 && q.index == IndexKind::Hnsw && !self.store.is_mixture() {
            // No row is served yet, so no index is built: the exact scan of no rows gives the
            // same (empty) answer.
            let exact = QueryParams {
                index: IndexKind::Exact,
                ..q.clone()
            };
            let mut a = crate::query::run_query_framed(&self.context(text, negatives), &exact)?;
            a.index = IndexKind::Hnsw;
            a
        } else {
            crate::query::run_query_framed(&self.context(text, negatives), q)?
        };
        a.tiles_pending_verification = pending;
        a.partial = pending > 0;
        Ok(a)
    }
}

/// What `slag-edge check` finds in the store for one scene (everything it checks but the text
/// model): the scene loaded as [`Engine::load`] loads it, and the problems that make the check
/// fail, each naming what is wrong: a stored shard that fails verification (corrupt, not
/// served), a tile of the last fetch's disc missing from the store, a scene without a Gaussian.
pub struct StoreCheck {
    /// The committed generation, loaded (no approximate index).
    pub engine: Engine,
    /// Tiles of the last fetch's disc without a stored file ([`EdgeStore::missing_tiles`]).
    pub missing: Vec<u64>,
    /// Entries in the store's `quarantine/` and their bytes ([`EdgeStore::quarantine_usage`]).
    pub set_aside: (usize, u64),
    /// One line per problem; empty when the committed generation is complete and valid.
    pub problems: Vec<String>,
}

impl StoreCheck {
    /// Loads `scene` from `edge` and lists its problems (type doc).
    ///
    /// Errors: as [`Engine::load`] (no completed fetch, store I/O, a bad stored manifest, a
    /// mixture scene's codebook missing or corrupt): the caller reports them as a problem too.
    pub fn run(edge: &EdgeStore, scene: &str) -> Result<StoreCheck> {
        let engine = Engine::load(edge, scene, false)?;
        let missing = edge.missing_tiles(&engine.manifest)?;
        let m = &engine.manifest;
        let mut problems: Vec<String> = engine
            .load
            .rejected
            .iter()
            .map(|r| format!("corrupt shard, not served: {r}"))
            .collect();
        for id in &missing {
            problems.push(format!(
                "shard {id} of the fetched disc is missing from the store"
            ));
        }
        if engine.store.is_empty() {
            problems.push(format!(
                "scene {} has no Gaussians to serve ({} of its {} tiles stored)",
                m.scene_id,
                engine.load.loaded_tiles.len(),
                m.tiles.len()
            ));
        }
        Ok(StoreCheck {
            set_aside: edge.quarantine_usage(),
            engine,
            missing,
            problems,
        })
    }
}

/// The engine a server answers from: one immutable [`Engine`] behind an `Arc`, swapped whole.
/// A query takes the `Arc` ([`Self::current`]) and keeps that one generation to its end,
/// whatever is swapped in meanwhile; of two engines offered out of order (two reloads that
/// finish in the other order), the later generation ([`Engine::seq`]) stays.
pub struct ServedEngine(std::sync::RwLock<std::sync::Arc<Engine>>);

impl ServedEngine {
    /// Serves `engine`.
    pub fn new(engine: Engine) -> Self {
        ServedEngine(std::sync::RwLock::new(std::sync::Arc::new(engine)))
    }

    /// The engine served now.
    pub fn current(&self) -> std::sync::Arc<Engine> {
        self.0
            .read()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone()
    }

    /// Serves `next` if `expected` is the engine served now (the same `Arc`); returns whether
    /// it was swapped in. A background verification publishes its progress this way, so that
    /// it never replaces an engine a reload swapped in meanwhile.
    pub fn swap_if(&self, expected: &std::sync::Arc<Engine>, next: std::sync::Arc<Engine>) -> bool {
        let mut g = self
            .0
            .write()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let swap = std::sync::Arc::ptr_eq(&g, expected);
        if swap {
            *g = next;
        }
        swap
    }

    /// Serves `engine` unless the one served now holds a later generation (a larger
    /// [`Engine::seq`]); returns whether it was swapped in.
    pub fn offer(&self, engine: Engine) -> bool {
        let mut g = self
            .0
            .write()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if engine.seq >= g.seq {
            *g = std::sync::Arc::new(engine);
            true
        } else {
            false
        }
    }
}

/// The rows of a generation loaded so far ([`Engine::load_observed`]): every row of the tiles
/// that passed, in tile order, their display columns, and what became of each tile handed so
/// far.
pub struct LoadProgress<'a> {
    /// The rows of every tile that passed so far.
    pub store: &'a VectorStore,
    /// Their display columns, same row order.
    pub display: &'a crate::view::DisplayAttrs,
    /// The tiles handed so far: loaded (and hashed), rejected, without a file.
    pub load: &'a SceneLoad,
}

/// A decoded shard a scene's rows are made of: dense ([`StoredShard`]) or mixture
/// ([`MixtureShard`]), for [`load_generation`].
trait ServedShard: crate::store::LoadableShard + crate::view::ShardDisplay {
    /// Gaussian ids of its rows.
    fn row_ids(&self) -> &[u32];
    /// Its tile.
    fn tile(&self) -> u64;
    /// Moves its rows into `store` (errors: as [`VectorStore::push_shard`]).
    fn push_into(self, store: &mut VectorStore) -> Result<()>;
}

impl ServedShard for StoredShard {
    fn row_ids(&self) -> &[u32] {
        &self.ids
    }
    fn tile(&self) -> u64 {
        self.header.tile_id
    }
    fn push_into(self, store: &mut VectorStore) -> Result<()> {
        store.push_shard(self)
    }
}

impl ServedShard for MixtureShard {
    fn row_ids(&self) -> &[u32] {
        &self.ids
    }
    fn tile(&self) -> u64 {
        self.header.tile_id
    }
    fn push_into(self, store: &mut VectorStore) -> Result<()> {
        store.push_mixture_shard(self)
    }
}

/// What [`load_generation`] read: manifest, rows, load report, display columns, fetch record,
/// commit count.
type Generation = (
    Manifest,
    VectorStore,
    SceneLoad,
    crate::view::DisplayAttrs,
    Option<FetchRecord>,
    u64,
);

/// Reads the scene's committed generation (call with the generation lock held): the manifest
/// once, then the listed shard files a few at a time (read, verified and decoded on the rayon
/// pool, then their rows copied into the scan store in tile order and the decoded shard
/// dropped), then the check that no Gaussian id is in two shards.
///
/// Errors: as [`Engine::load_with`].
fn load_generation(
    edge: &EdgeStore,
    scene: &str,
    trusted: Option<&TrustedKeys>,
    observe: &mut dyn FnMut(&LoadProgress<'_>) -> Result<()>,
) -> Result<Generation> {
    let committed = edge.committed(scene)?;
    let manifest = &committed.manifest;
    let hashes = signed_generation(edge, scene, manifest, trusted)?;
    let mut store = empty_store(edge, manifest, hashes)?;
    // Room for the rows of every stored shard up front: they land in place (no reallocation,
    // no doubling of the served memory) on transparent huge pages.
    let mut rows = 0u64;
    for tile in committed.tiles() {
        if edge.has_shard(&manifest.scene_id, tile)? {
            rows += tile.count;
        }
    }
    store.reserve(usize::try_from(rows).unwrap_or(usize::MAX))?;
    let mut display = crate::view::DisplayAttrs::new();
    // (Gaussian id, shard in load order) of every row and the tile of each shard, for the
    // check that no id is in two shards.
    let (mut ids, mut tiles) = (Vec::<(u32, u32)>::new(), Vec::<u64>::new());
    let mut note = |ids_of: &[u32], tile: u64| {
        let k = tiles.len() as u32;
        tiles.push(tile);
        ids.extend(ids_of.iter().map(|&i| (i, k)));
    };
    let rows = Rows {
        store: &mut store,
        display: &mut display,
        note: &mut note,
    };
    let load = if rows.store.is_mixture() {
        rows.load::<MixtureShard>(edge, &committed, hashes, observe)?
    } else {
        rows.load::<StoredShard>(edge, &committed, hashes, observe)?
    };
    refuse_shared_ids(ids, &tiles, scene)?;
    Ok((
        committed.manifest,
        store,
        load,
        display,
        committed.record,
        committed.seq,
    ))
}

/// Where [`load_generation`] puts the rows of each tile that passes: the scan store, the
/// display columns, and `note` (its Gaussian ids and tile, for [`refuse_shared_ids`]).
struct Rows<'a> {
    store: &'a mut VectorStore,
    display: &'a mut crate::view::DisplayAttrs,
    note: &'a mut dyn FnMut(&[u32], u64),
}

impl Rows<'_> {
    /// Loads the committed generation's tiles as `S` shards ([`EdgeStore::load_committed_each`]),
    /// pushing the rows of each that passes and handing `observe` the rows so far after every
    /// tile.
    ///
    /// Errors: as [`EdgeStore::load_committed_each`]; the first error of a push or `observe`.
    fn load<S: ServedShard>(
        self,
        edge: &EdgeStore,
        committed: &crate::store::Committed,
        hashes: bool,
        observe: &mut dyn FnMut(&LoadProgress<'_>) -> Result<()>,
    ) -> Result<SceneLoad> {
        let Rows {
            store,
            display,
            note,
        } = self;
        edge.load_committed_each(committed, hashes, |s: Option<S>, load| {
            if let Some(s) = s {
                note(s.row_ids(), s.tile());
                display.push_shard(&s);
                s.push_into(store)?;
            }
            observe(&LoadProgress {
                store,
                display,
                load,
            })
        })
    }
}

/// The scan store of `manifest`'s generation before any shard is pushed: a mixture scene's
/// codebook read and verified first (hashed too with `hashes`; missing or corrupt is an error,
/// since no row can be scored without it), an empty dense store of the manifest's width and
/// dtype otherwise.
///
/// Errors: as [`EdgeStore::codebook_checked`]; a codebook checksum that is not hex.
fn empty_store(edge: &EdgeStore, manifest: &Manifest, hashes: bool) -> Result<VectorStore> {
    match &manifest.mixture {
        Some(m) => {
            let cb = edge.codebook_checked(manifest, hashes)?;
            let crc = u32::from_str_radix(&m.codebook_checksum, 16).map_err(|_| {
                slag_common::Error::format("<manifest>", "codebook checksum is not hex")
            })?;
            VectorStore::new_mixture(cb.dim, m.slots as usize, cb.rows, crc)
        }
        None => VectorStore::new(manifest.dim as usize, manifest.dtype),
    }
}

/// Whether a load with the publisher's keys `trusted` hashes the committed generation's tiles
/// ([`Engine::load_trusting`]): true once the stored signature of `scene` is verified over the
/// stored manifest bytes (`manifest` parsed from them) and the manifest names every SHA-256;
/// false without keys, or for an unsigned generation (logged). Call with the generation lock
/// held.
///
/// Errors: [`slag_common::Error::Untrusted`] (module `signature`); store I/O.
fn signed_generation(
    edge: &EdgeStore,
    scene: &str,
    manifest: &Manifest,
    trusted: Option<&TrustedKeys>,
) -> Result<bool> {
    let Some(keys) = trusted else {
        return Ok(false);
    };
    let Some(sig) = edge.signature(scene)? else {
        tracing::warn!(
            "scene {scene}: the stored generation is unsigned, so its tiles are checked by their \
             CRC-32s only; fetch it with the trusted key to have them hashed"
        );
        return Ok(false);
    };
    let origin = format!("the store's manifest of scene {scene}");
    let bytes = edge.manifest_bytes(scene)?.unwrap_or_default();
    keys.verify(&bytes, &sig, &origin)?;
    slag_common::shards::signature::check_hashes(manifest, &origin)?;
    Ok(true)
}

/// Refuses rows of one Gaussian id in two shards: the manifest's tiles must partition the
/// scene's Gaussians, or every answer counts some twice.
///
/// Errors: [`slag_common::shards::ShardError::ManifestNotASet`] naming the id and both tiles.
fn refuse_shared_ids(mut ids: Vec<(u32, u32)>, tiles: &[u64], scene: &str) -> Result<()> {
    ids.sort_unstable();
    match ids.windows(2).find(|w| w[0].0 == w[1].0) {
        Some(w) => Err(slag_common::Error::Shard(
            slag_common::shards::ShardError::ManifestNotASet(format!(
                "scene {scene}: Gaussian id {} is in the shards of tiles {} and {}",
                w[0].0, tiles[w[0].1 as usize], tiles[w[1].1 as usize]
            )),
        )),
        None => Ok(()),
    }
}

/// Builds the approximate index of `hnsw`'s backend over `store` (none for an empty or mixture
/// scene): [`Engine::load_with`].
///
/// Errors: the index build ([`ApproxIndex::build`]).
fn build_index(
    store: &VectorStore,
    scene: &str,
    hnsw: Option<HnswBackend>,
) -> Result<Option<ApproxIndex>> {
    if hnsw.is_some() && store.is_mixture() {
        tracing::warn!(
            "scene {scene} holds codebook mixtures: no HNSW index is built over them \
                 (index=hnsw is refused; the exact mixture scan answers)"
        );
    }
    let hnsw = match hnsw {
        Some(backend) if !store.is_empty() && !store.is_mixture() => {
            let params = HnswParams {
                ef_construction: HNSW_EF_CONSTRUCTION,
                ef_search: HNSW_EF_SEARCH,
                m: HNSW_M,
                seed: HNSW_SEED,
                ..HnswParams::default()
            };
            let t = std::time::Instant::now();
            let index = ApproxIndex::build(store, backend, &params)?;
            tracing::info!(
                "{backend} HNSW over {} rows built in {:.1} s",
                store.len(),
                t.elapsed().as_secs_f64()
            );
            Some(index)
        }
        _ => None,
    };
    Ok(hnsw)
}

#[cfg(test)]
mod tests {
    use super::refuse_shared_ids;

    #[test]
    fn a_gaussian_id_in_two_shards_is_refused_naming_both_tiles() {
        assert!(refuse_shared_ids(vec![(3, 0), (1, 0), (2, 1), (7, 1)], &[10, 11], "s").is_ok());
        let e = refuse_shared_ids(vec![(3, 0), (1, 0), (2, 1), (3, 1)], &[10, 11], "s")
            .expect_err("id 3 twice");
        assert!(
            matches!(
                &e,
                slag_common::Error::Shard(slag_common::shards::ShardError::ManifestNotASet(_))
            ),
            "{e}"
        );
        let m = e.to_string();
        assert!(
            m.contains("Gaussian id 3") && m.contains("tiles 10 and 11"),
            "{m}"
        );
    }
}
