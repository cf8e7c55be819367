//! The edge's approximate nearest-neighbour index: one type, [`ApproxIndex`], over two HNSW
//! backends chosen at run time ([`HnswBackend`]):
//!
//! - `instant-distance` ([`HnswIndex`], `instant.rs`; always built, the default): the
//!   `instant-distance` 0.6 crate, M = 32 (layer 0 keeps 64 links), the search beam `ef_search`
//!   fixed at build time;
//! - `qdrant-edge` (`qdrant.rs`; only with the cargo feature `qdrant-edge`): Qdrant Edge 0.9.0's
//!   HNSW (an in-process `EdgeShard`, one segment, `m` links per node, `Distance::Dot`), the
//!   beam settable per query. A binary built without the feature refuses it with
//!   [`Error::Param`] `hnsw_backend` ([`HnswBackend::require`]).
//!
//! Both index f32 copies of the store's rows: f32 stores as they are, f16 / int8 stores
//! dequantised by [`VectorStore::row_f32`] (f16 → f32 exactly; int8 → `q·scale`), i.e. the same
//! values the exact [`scan`](super::scan) dots. A hit's score is the dot product of the query with
//! that row (the cosine for unit rows and a unit query, as the exact scan scores), and rows are
//! the store's row indices, so `index=hnsw` answers carry the same ids and scores as `index=exact`
//! ones, only possibly missing rows. Memory: `N·D·4` bytes for the copy plus the graph
//! ([`ApproxIndex::memory_bytes`]).

mod instant;
#[cfg(feature = "qdrant-edge")]
pub mod qdrant;

use std::path::PathBuf;

use slag_common::Error;

pub use instant::HnswIndex;

use super::{Hit, VectorStore};

/// Which HNSW implementation an [`ApproxIndex`] uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum HnswBackend {
    /// The `instant-distance` crate (always built).
    #[default]
    InstantDistance,
    /// Qdrant Edge 0.9.0 (cargo feature `qdrant-edge`).
    QdrantEdge,
}

impl HnswBackend {
    /// Every backend, in the order of their names in messages.
    pub const ALL: [HnswBackend; 2] = [HnswBackend::InstantDistance, HnswBackend::QdrantEdge];

    /// The backend's name in the config file, on the command line and in `/stats`:
    /// `instant-distance` or `qdrant-edge`.
    pub fn name(self) -> &'static str {
        match self {
            HnswBackend::InstantDistance => "instant-distance",
            HnswBackend::QdrantEdge => "qdrant-edge",
        }
    }

    /// The backend called `name` ([`HnswBackend::name`]; `instant` and `qdrant` are accepted
    /// too). It may still be unavailable in this binary: see [`HnswBackend::require`].
    ///
    /// Errors: [`Error::Param`] `hnsw_backend` for any other name.
    pub fn from_name(name: &str) -> Result<HnswBackend, Error> {
        match name.trim() {
            "instant-distance" | "instant" => Ok(HnswBackend::InstantDistance),
            "qdrant-edge" | "qdrant" => Ok(HnswBackend::QdrantEdge),
            other => Err(Error::param(
                "hnsw_backend",
                format!("{other:?}"),
                "instant-distance or qdrant-edge",
            )),
        }
    }

    /// `true` when this binary can build the backend (`qdrant-edge` needs the cargo feature of
    /// the same name).
    pub fn available(self) -> bool {
        match self {
            HnswBackend::InstantDistance => true,
            HnswBackend::QdrantEdge => cfg!(feature = "qdrant-edge"),
        }
    }

    /// The backend, if this binary can build it.
    ///
    /// Errors: [`Error::Param`] `hnsw_backend` for `qdrant-edge` in a binary built without the
    /// cargo feature `qdrant-edge`; the message says to rebuild with that feature (a command
    /// line's hint adds the `cargo build` command).
    pub fn require(self) -> Result<HnswBackend, Error> {
        if self.available() {
            return Ok(self);
        }
        Err(Error::param(
            "hnsw_backend",
            self.name(),
            "instant-distance: this slag-edge was built without Qdrant Edge; to use qdrant-edge \
             rebuild slag-edge with the cargo feature `qdrant-edge` (Rust >= 1.96, a C++ \
             compiler)",
        ))
    }
}

impl std::fmt::Display for HnswBackend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// How to build an [`ApproxIndex`].
#[derive(Debug, Clone, PartialEq)]
pub struct HnswParams {
    /// Candidates kept per insertion while building (`ef_construction` / Qdrant's
    /// `ef_construct`), ≥ 1; typical 100.
    pub ef_construction: usize,
    /// Search beam, ≥ 1; also the largest `k` a query may ask ([`ApproxIndex::query`]).
    /// instant-distance fixes it at build time; Qdrant Edge's can be changed afterwards
    /// ([`ApproxIndex::set_ef_search`]).
    pub ef_search: usize,
    /// Links per node (`m`) of the Qdrant Edge graph, ≥ 2 (layer 0 keeps `2m`). instant-distance
    /// fixes M = 32 and ignores this.
    pub m: usize,
    /// Seed of instant-distance's layer assignment (the same seed gives the same graph). Qdrant
    /// Edge's build is not seeded.
    pub seed: u64,
    /// Threads Qdrant Edge builds and searches with (0: rayon's thread count). instant-distance
    /// builds on the rayon pool and answers a query on the calling thread.
    pub threads: usize,
    /// Folder in which Qdrant Edge's scratch shard is made (a fresh sub-folder, removed when the
    /// index is dropped). `None`: the system temp folder. instant-distance uses no files.
    pub scratch_dir: Option<PathBuf>,
}

impl Default for HnswParams {
    /// `ef_construction` 100, `ef_search` 1000, `m` 16, seed `0x51A6`, threads 0, no scratch
    /// folder: what `slag-edge serve --hnsw` builds.
    fn default() -> Self {
        HnswParams {
            ef_construction: 100,
            ef_search: 1000,
            m: 16,
            seed: 0x51A6,
            threads: 0,
            scratch_dir: None,
        }
    }
}

impl HnswParams {
    /// Errors: [`Error::Param`] `ef_construction` / `ef_search` for 0, `m` for less than 2
    /// (Qdrant Edge only: `m = 0` would disable its graph).
    fn check(&self, backend: HnswBackend) -> Result<(), Error> {
        if self.ef_construction == 0 {
            return Err(Error::param(
                "ef_construction",
                0,
                "at least 1 (typical: 100)",
            ));
        }
        if self.ef_search == 0 {
            return Err(Error::param(
                "ef_search",
                0,
                "at least 1 and at least the top_k queries ask",
            ));
        }
        if backend == HnswBackend::QdrantEdge && self.m < 2 {
            return Err(Error::param("m", self.m, "at least 2 (typical: 16)"));
        }
        Ok(())
    }
}

/// An approximate index over every row of one [`VectorStore`] (row indices refer to that store),
/// built by the backend [`ApproxIndex::backend`] (module doc).
pub enum ApproxIndex {
    /// instant-distance's graph.
    InstantDistance(HnswIndex),
    /// Qdrant Edge's graph.
    #[cfg(feature = "qdrant-edge")]
    QdrantEdge(qdrant::QdrantHnsw),
}

impl std::fmt::Debug for ApproxIndex {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ApproxIndex")
            .field("backend", &self.backend())
            .field("len", &self.len())
            .field("ef_search", &self.ef_search())
            .finish()
    }
}

impl ApproxIndex {
    /// Builds `backend`'s index over all rows of `store` (module doc: f32 copies of the rows).
    /// Blocks until the graph is complete: seconds to minutes (100K × 512 on 2 cores:
    /// instant-distance 2–5 min, Qdrant Edge 2.6–3.9× less; docs/results/edge-hnsw.md).
    ///
    /// Errors: [`Error::Param`] `hnsw_backend` for a backend this binary lacks
    /// ([`HnswBackend::require`]), `ef_construction` / `ef_search` / `m` out of range
    /// ([`HnswParams`]); [`Error::Invalid`] for more than `u32::MAX - 1` rows (instant-distance);
    /// [`Error::Io`] when Qdrant Edge cannot create or write its scratch shard (the folder is
    /// named).
    pub fn build(
        store: &VectorStore,
        backend: HnswBackend,
        params: &HnswParams,
    ) -> Result<ApproxIndex, Error> {
        backend.require()?;
        params.check(backend)?;
        match backend {
            HnswBackend::InstantDistance => Ok(ApproxIndex::InstantDistance(HnswIndex::build(
                store,
                params.ef_construction,
                params.ef_search,
                params.seed,
            )?)),
            #[cfg(feature = "qdrant-edge")]
            HnswBackend::QdrantEdge => Ok(ApproxIndex::QdrantEdge(qdrant::QdrantHnsw::build(
                store, params,
            )?)),
            #[cfg(not(feature = "qdrant-edge"))]
            HnswBackend::QdrantEdge => Err(Error::internal(
                "qdrant-edge passed HnswBackend::require in a build without it",
            )),
        }
    }

    /// The backend that built this index.
    pub fn backend(&self) -> HnswBackend {
        match self {
            ApproxIndex::InstantDistance(_) => HnswBackend::InstantDistance,
            #[cfg(feature = "qdrant-edge")]
            ApproxIndex::QdrantEdge(_) => HnswBackend::QdrantEdge,
        }
    }

    /// The index's row width, row count and search beam, from whichever backend built it.
    pub fn shape(&self) -> &IndexShape {
        match self {
            ApproxIndex::InstantDistance(i) => i.shape(),
            #[cfg(feature = "qdrant-edge")]
            ApproxIndex::QdrantEdge(i) => i.shape(),
        }
    }

    /// Number of indexed rows.
    pub fn len(&self) -> usize {
        self.shape().len
    }

    /// `true` when the index holds no row.
    pub fn is_empty(&self) -> bool {
        self.shape().is_empty()
    }

    /// The search beam; also the largest `k` [`ApproxIndex::query`] answers.
    pub fn ef_search(&self) -> usize {
        self.shape().ef_search
    }

    /// Sets the search beam of later queries (a larger beam: higher recall, slower queries).
    ///
    /// Errors: [`Error::Param`] `ef_search` for 0, or for instant-distance any value other than
    /// the one it was built with (its beam is fixed at build time: rebuild with
    /// [`HnswParams::ef_search`]).
    pub fn set_ef_search(&mut self, ef: usize) -> Result<(), Error> {
        if ef == 0 {
            return Err(Error::param("ef_search", 0, "at least 1"));
        }
        let built = self.ef_search();
        match self {
            ApproxIndex::InstantDistance(_) => {
                if ef == built {
                    Ok(())
                } else {
                    Err(Error::param(
                        "ef_search",
                        ef,
                        format!(
                            "{built}: instant-distance fixes the beam at build time; rebuild \
                             the index with this ef_search"
                        ),
                    ))
                }
            }
            #[cfg(feature = "qdrant-edge")]
            ApproxIndex::QdrantEdge(i) => {
                i.set_ef_search(ef);
                Ok(())
            }
        }
    }

    /// Approximately the `k` rows with the highest score `query · row` (module doc), best first
    /// (higher score, then lower row). `query` is `[D]`, used as given (pass a unit vector to get
    /// cosines).
    ///
    /// Errors: [`Error::Mismatch`] for a query of another width than the rows, [`Error::Query`]
    /// `text` for non-finite values (as [`super::scan`]); [`Error::Param`] `top_k` for
    /// `k > ef_search`; [`Error::Io`] when Qdrant Edge fails to read its shard.
    pub fn query(&self, query: &[f32], k: usize) -> Result<Vec<Hit>, Error> {
        match self {
            ApproxIndex::InstantDistance(i) => i.query(query, k),
            #[cfg(feature = "qdrant-edge")]
            ApproxIndex::QdrantEdge(i) => i.query(query, k),
        }
    }

    /// Bytes the index holds beside the store: instant-distance's f32 copy, point handles and
    /// graph as laid out by the crate ([`HnswIndex::memory_bytes`]); for Qdrant Edge the bytes
    /// its shard's files occupy (`du`: f32 vectors, graph links, id tracker, and the chunks it
    /// preallocates for its empty appendable segment), whose vectors and graph it keeps in RAM
    /// (`Memory::Pinned`). Excludes allocator slack: `slag-edge bench` reports the RSS growth
    /// too.
    pub fn memory_bytes(&self) -> usize {
        match self {
            ApproxIndex::InstantDistance(i) => i.memory_bytes(),
            #[cfg(feature = "qdrant-edge")]
            ApproxIndex::QdrantEdge(i) => i.memory_bytes(),
        }
    }
}

/// What every backend's index knows of itself the same way: the width of its rows, how many rows
/// it holds and its search beam. [`ApproxIndex::len`], [`ApproxIndex::is_empty`] and
/// [`ApproxIndex::ef_search`] read it, whichever backend built the index.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct IndexShape {
    /// Values per row and per query (`D`).
    pub dim: usize,
    /// Number of indexed rows.
    pub len: usize,
    /// The search beam (`ef_search`, ≥ 1); also the largest `k` a query answers.
    pub ef_search: usize,
}

impl IndexShape {
    /// `true` when the index holds no row.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The checks of every backend's query before it searches: the query's width and values (as
    /// the exact scan checks them), and `k` at most the beam `ef_search` ([`Error::Param`]
    /// `top_k`, whose remedy reads `"{remedy} >= k"`, e.g. "rebuild with ef_search").
    fn check_query(&self, query: &[f32], k: usize, remedy: &str) -> Result<(), Error> {
        super::check_queries(self.dim, &[query])?;
        if k > self.ef_search {
            return Err(Error::param(
                "top_k",
                k,
                format!(
                    "at most the index's ef_search {} ({remedy} >= {k})",
                    self.ef_search
                ),
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests;
