//! The `qdrant-edge` backend of [`super::ApproxIndex`] (cargo feature `qdrant-edge`): Qdrant Edge
//! 0.9.0's HNSW over a [`VectorStore`], in an in-process `EdgeShard` in a scratch folder.
//!
//! The shard holds one vector per row: the row as f32 ([`VectorStore::row_f32`]: f32 rows as
//! stored, f16 rows widened exactly, int8 rows as `q·scale`), `Float32` storage, `Distance::Dot`
//! (Qdrant normalises nothing for Dot, so a hit's score is `query · row` on those f32 values, as
//! slag's exact scan scores), point id = row index. One optimised segment with an HNSW graph of
//! `m` links per node (`2m` on layer 0), `ef_construct` = [`HnswParams::ef_construction`],
//! `full_scan_threshold` 1 KB (the graph is always used), vectors and graph kept in RAM
//! (`Memory::Pinned`), no WAL. The scratch folder (a fresh `slag-edge-hnsw-<pid>-<n>` under
//! [`HnswParams::scratch_dir`] or the system temp folder) is removed when the index is dropped.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use qdrant_edge::external::serde_json::Value as JsonValue;
use qdrant_edge::{
    DEFAULT_VECTOR_NAME, Distance, EdgeConfig, EdgeOptimizersConfig, EdgeShard, EdgeVectorParams,
    HnswIndexConfig, Memory, NamedQuery, PointId, PointInsertOperations, PointOperations,
    PointStruct, QueryEnum, SearchParams, SearchRequest, SearchRequestBuilder, UpdateOperation,
    VectorStorageDatatype, WithPayloadInterface, WithVector,
};
use slag_common::Error;

use super::{HnswParams, IndexShape};
use crate::scan::{Hit, VectorStore};

/// Rows per upsert call.
const UPSERT_BATCH: usize = 1000;

/// Distinguishes the scratch folders of several indexes in one process.
static SCRATCH_SEQ: AtomicUsize = AtomicUsize::new(0);

/// A Qdrant Edge failure on the shard in `dir`, as an [`Error::Io`] naming the folder (its
/// errors are storage errors or bugs; the message says which step failed).
fn qdrant_err(dir: &Path, step: &str, e: impl std::fmt::Display) -> Error {
    Error::io(
        dir,
        std::io::Error::other(format!(
            "Qdrant Edge could not {step}: {e}; check that the folder is writable and has room \
             for N·D·4 bytes plus the graph, or use the instant-distance backend"
        )),
    )
}

/// Upserts rows `range` of `rows` into `shard` (as f32, point id = row index), in batches of
/// [`UPSERT_BATCH`]. Shared with the exact Qdrant Edge shards of `slag-edge bench --qdrant`.
///
/// Errors: [`Error::Internal`] for a row index past the store (a caller bug); [`Error::Io`] when
/// Qdrant Edge refuses the batch.
pub fn upsert(
    shard: &EdgeShard,
    dir: &Path,
    rows: &VectorStore,
    range: std::ops::Range<usize>,
) -> Result<(), Error> {
    let mut i = range.start;
    while i < range.end {
        let end = (i + UPSERT_BATCH).min(range.end);
        let mut batch = Vec::with_capacity(end - i);
        for r in i..end {
            let v = rows.row_f32(r).ok_or_else(|| {
                Error::internal(format!("row {r} of a store of {} rows", rows.len()))
            })?;
            // An empty payload object (`PointStruct::new` panics on anything but an object).
            let payload = JsonValue::Object(Default::default());
            batch.push(PointStruct::new(r as u64, v, payload).into());
        }
        shard
            .update(UpdateOperation::PointOperation(
                PointOperations::UpsertPoints(PointInsertOperations::PointsList(batch)),
            ))
            .map_err(|e| qdrant_err(dir, "insert rows", e))?;
        i = end;
    }
    Ok(())
}

/// Bytes the files under `dir` occupy (`du`: allocated blocks on Unix, where Qdrant's sparse
/// preallocated chunks count only as far as written; apparent sizes elsewhere; 0 for what cannot
/// be read).
fn folder_bytes(dir: &Path) -> u64 {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    entries
        .flatten()
        .map(|e| match e.metadata() {
            Ok(m) if m.is_dir() => folder_bytes(&e.path()),
            #[cfg(unix)]
            Ok(m) => std::os::unix::fs::MetadataExt::blocks(&m) * 512,
            #[cfg(not(unix))]
            Ok(m) => m.len(),
            Err(_) => 0,
        })
        .sum()
}

/// The graph settings of a shard held in RAM (`Memory::Pinned`) whose graph is always used
/// (`full_scan_threshold` 1 KB): `m` links per node (0: no graph, full scans), `ef_construct`,
/// `threads` indexing threads. Shared with the exact shards of `slag-edge bench --qdrant`.
#[allow(deprecated)] // `on_disk` has no replacement field to leave unset but this one
pub fn pinned_hnsw_config(m: usize, ef_construct: usize, threads: usize) -> HnswIndexConfig {
    HnswIndexConfig {
        m,
        ef_construct,
        full_scan_threshold: 1,
        max_indexing_threads: threads,
        on_disk: None,
        memory: Some(Memory::Pinned),
        payload_m: None,
        inline_storage: None,
    }
}

/// The configuration of a shard of one unnamed vector `vectors` with the graph `hnsw`, no WAL,
/// `threads` search threads, and an optimiser that keeps `segments` segments of at most
/// `max_segment_kb` KiB apart (it starts `segments + 2` appendable ones and indexes from the
/// first point). Shared with the exact shards of `slag-edge bench --qdrant`.
pub fn shard_config(
    vectors: EdgeVectorParams,
    hnsw: HnswIndexConfig,
    segments: usize,
    max_segment_kb: usize,
    threads: usize,
) -> EdgeConfig {
    EdgeConfig::builder()
        .vector(DEFAULT_VECTOR_NAME, vectors)
        .hnsw_config(hnsw)
        .optimizers(EdgeOptimizersConfig {
            default_segment_number: Some(segments + 2),
            max_segment_size: Some(max_segment_kb),
            indexing_threshold: Some(1),
            ..EdgeOptimizersConfig::default()
        })
        .wal_enabled(false)
        .max_search_threads(threads.max(1))
        .build()
}

/// The search for the `k` points nearest to `query` (`[D]`, by the shard's distance) under
/// `params`, ids and scores only (no payload, no vectors). Shared with `slag-edge bench
/// --qdrant`.
pub fn nearest_request(query: &[f32], k: usize, params: SearchParams) -> SearchRequest {
    SearchRequestBuilder::new(
        QueryEnum::Nearest(NamedQuery {
            query: query.to_vec().into(),
            using: None,
        }),
        k,
    )
    .params(params)
    .with_payload(WithPayloadInterface::Bool(false))
    .with_vector(WithVector::Bool(false))
    .build()
}

/// Segments of `shard` now (0 when Qdrant Edge cannot say).
pub fn segment_count(shard: &EdgeShard) -> usize {
    shard.info().map_or(0, |i| i.segments_count)
}

/// Qdrant Edge's HNSW over every row of one store (module doc).
pub struct QdrantHnsw {
    /// `None` only while dropping: the shard is closed before its folder is removed.
    shard: Option<EdgeShard>,
    dir: PathBuf,
    /// Row width, row count and the beam of queries (`hnsw_ef`).
    shape: IndexShape,
    /// Size of the shard's files after the build.
    bytes: usize,
}

impl Drop for QdrantHnsw {
    fn drop(&mut self) {
        // Close (and flush) the shard, then remove its scratch folder: best effort, nothing in
        // it is needed again.
        drop(self.shard.take());
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

impl QdrantHnsw {
    /// Builds the shard and its graph over all rows of `store` (module doc); `params` are
    /// checked by the caller ([`super::ApproxIndex::build`]).
    ///
    /// Errors: [`Error::Io`] when the scratch folder cannot be made or Qdrant Edge fails to
    /// write or optimise the shard.
    pub fn build(store: &VectorStore, params: &HnswParams) -> Result<QdrantHnsw, Error> {
        let base = params
            .scratch_dir
            .clone()
            .unwrap_or_else(std::env::temp_dir);
        let dir = base.join(format!(
            "slag-edge-hnsw-{}-{}",
            std::process::id(),
            SCRATCH_SEQ.fetch_add(1, Ordering::Relaxed)
        ));
        if dir.exists() {
            std::fs::remove_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
        }
        let threads = match params.threads {
            0 => rayon::current_num_threads(),
            t => t,
        };
        let n = store.len();
        let dim = store.dim();
        let hnsw = pinned_hnsw_config(params.m, params.ef_construction.max(4), threads);
        let vectors = EdgeVectorParams::builder(dim, Distance::Dot)
            .hnsw_config(hnsw)
            .datatype(VectorStorageDatatype::Float32)
            .build();
        // One segment: large enough for every row (1.5× margin), so the optimiser never splits
        // or merges.
        let max_segment_kb = (n * 4 * dim).div_ceil(1024) * 3 / 2 + 1;
        let config = shard_config(vectors, hnsw, 1, max_segment_kb, threads);
        let shard = EdgeShard::new(&dir, config).map_err(|e| qdrant_err(&dir, "create", e))?;
        // From here on the folder is ours: dropping `index` on an error removes it.
        let mut index = QdrantHnsw {
            shard: Some(shard),
            dir,
            shape: IndexShape {
                dim,
                len: n,
                ef_search: params.ef_search,
            },
            bytes: 0,
        };
        let shard = index.shard()?;
        upsert(shard, &index.dir, store, 0..n)?;
        shard
            .optimize()
            .map_err(|e| qdrant_err(&index.dir, "build the HNSW graph", e))?;
        index.bytes = usize::try_from(folder_bytes(&index.dir)).unwrap_or(usize::MAX);
        Ok(index)
    }

    fn shard(&self) -> Result<&EdgeShard, Error> {
        self.shard
            .as_ref()
            .ok_or_else(|| Error::internal("Qdrant Edge shard used after it was closed"))
    }

    /// Row width, row count and the search beam (`hnsw_ef`) of queries, also the largest `k`
    /// answered.
    pub fn shape(&self) -> &IndexShape {
        &self.shape
    }

    /// Sets the search beam of later queries (≥ 1, checked by the caller).
    pub fn set_ef_search(&mut self, ef: usize) {
        self.shape.ef_search = ef.max(1);
    }

    /// Segments of the shard (1 after a build; for the bench's report).
    pub fn segments(&self) -> usize {
        self.shard.as_ref().map_or(0, segment_count)
    }

    /// Bytes the shard's files occupy after the build (`du`): the indexed segment's f32 vectors
    /// and graph links, and the chunks Qdrant preallocates for its empty appendable segment;
    /// the vectors and graph are held in RAM (`Memory::Pinned`).
    pub fn memory_bytes(&self) -> usize {
        self.bytes
    }

    /// Approximately the `k` best rows for `query` (`[D]`), best first (score desc, row asc),
    /// searched with `hnsw_ef` = the shape's [`IndexShape::ef_search`].
    ///
    /// Errors: as [`super::ApproxIndex::query`].
    pub fn query(&self, query: &[f32], k: usize) -> Result<Vec<Hit>, Error> {
        self.shape.check_query(query, k, "raise ef_search to")?;
        if k == 0 || self.shape.is_empty() {
            return Ok(Vec::new());
        }
        let params = SearchParams {
            hnsw_ef: Some(self.shape.ef_search),
            exact: false,
            ..SearchParams::default()
        };
        let req = nearest_request(query, k, params);
        let found = self
            .shard()?
            .search(req)
            .map_err(|e| qdrant_err(&self.dir, "search", e))?;
        let mut hits = found
            .iter()
            .map(|p| match p.id {
                PointId::NumId(i) if (i as usize) < self.shape.len => Ok(Hit {
                    row: i as usize,
                    score: p.score,
                }),
                other => Err(Error::internal(format!(
                    "Qdrant Edge returned point id {other} outside the {} rows it was given",
                    self.shape.len
                ))),
            })
            .collect::<Result<Vec<Hit>, Error>>()?;
        hits.sort_by(crate::scan::select::rank_cmp);
        Ok(hits)
    }
}
