//! A loaded scene, what every query runs against: the manifest of the last completed fetch, the
//! Gaussians of every verified shard in one [`VectorStore`] (the scan kernels' layout), their
//! display columns, and the optional approximate (HNSW) index. [`crate::serve`] swaps a new one in on reload;
//! `slag-edge query`/`bench` and the examples use it directly.

use slag_common::Result;
use slag_common::shards::{Manifest, MixtureShard, StoredShard};

use crate::scan::VectorStore;
use crate::scan::hnsw::{ApproxIndex, HnswBackend, HnswParams};
use crate::store::{EdgeStore, SceneLoad};

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
    /// ([`slag_common::Error::Format`]: fetch again); the index build ([`ApproxIndex::build`]).
    pub fn load_with(edge: &EdgeStore, scene: &str, hnsw: Option<HnswBackend>) -> Result<Engine> {
        if let Some(b) = hnsw {
            b.require()?;
        }
        // The manifest is read once; then one shard file at a time: read, verify, copy its rows
        // into the scan store, drop.
        let manifest = edge.current_manifest(scene)?;
        let mut store = match &manifest.mixture {
            // A mixture scene: its codebook first (verified; missing or corrupt is an error,
            // since no row can be scored without it).
            Some(m) => {
                let cb = edge.codebook(&manifest)?;
                let crc = u32::from_str_radix(&m.codebook_checksum, 16).map_err(|_| {
                    slag_common::Error::format("<manifest>", "codebook checksum is not hex")
                })?;
                VectorStore::new_mixture(cb.dim, m.slots as usize, cb.rows, crc)?
            }
            None => VectorStore::new(manifest.dim as usize, manifest.dtype)?,
        };
        // Room for the rows of every stored shard up front: they land in place (no reallocation,
        // no doubling of the served memory) on transparent huge pages.
        let mut rows = 0u64;
        for tile in &manifest.tiles {
            if edge.has_shard(&manifest.scene_id, tile)? {
                rows += tile.count;
            }
        }
        store.reserve(usize::try_from(rows).unwrap_or(usize::MAX))?;
        let mut display = crate::view::DisplayAttrs::new();
        let load = if store.is_mixture() {
            edge.load_shards(&manifest, |s: MixtureShard| {
                display.push_shard(&s);
                store.push_mixture_shard(s)
            })?
        } else {
            edge.load_shards(&manifest, |s: StoredShard| {
                display.push_shard(&s);
                store.push_shard(s)
            })?
        };
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
                let index = ApproxIndex::build(&store, backend, &params)?;
                tracing::info!(
                    "{backend} HNSW over {} rows built in {:.1} s",
                    store.len(),
                    t.elapsed().as_secs_f64()
                );
                Some(index)
            }
            _ => None,
        };
        Ok(Engine {
            manifest,
            store,
            load,
            hnsw,
            display,
        })
    }
}
