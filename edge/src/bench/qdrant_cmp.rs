//! Qdrant Edge 0.9.0 side by side with slag's scans in `slag-edge bench --qdrant` (cargo feature
//! `qdrant-edge`, off by default; the crate needs Rust >= 1.96).
//!
//! The same rows (the bench's synthetic unit vectors, D = `--dim`) go into an in-process
//! `qdrant_edge::EdgeShard` with `Distance::Dot` (unit rows: dot = cosine, as slag scores):
//!
//! - `f32`: `Float32` storage, exact search (`SearchParams::exact`);
//! - `f16`: `Float16` storage of the f16 values slag stores (read back from slag's f16 store, so
//!   both hold bit-identical halves), exact search;
//! - `int8`: `Float32` storage plus Qdrant's scalar int8 quantization (`ScalarType::Int8`, kept in
//!   RAM), searched through the quantized vectors with rescoring on the originals
//!   (`rescore = true`, `--qdrant-oversampling`), and once without rescoring; the graph is
//!   disabled (`m = 0`), so this is Qdrant's quantized full scan.
//!
//! Qdrant Edge's HNSW is not built here: the bench's HNSW table builds it through the edge's own
//! approximate-index type (`slag_edge::scan::hnsw::ApproxIndex`, backend `qdrant-edge`).
//!
//! The exact shards are built as two optimised segments of N/2 points each (Qdrant searches
//! segments in parallel on its `max_search_threads` pool, which is set to the bench's thread
//! count), so both engines use the same number of cores. Each query is answered by slag and by
//! Qdrant alternately; the report gives both medians, their ratio and each side's top-k IoU
//! against slag's exact f32 answer on the same rows.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use qdrant_edge::{
    Distance, EdgeShard, EdgeVectorParams, Memory, PointId, QuantizationConfig,
    QuantizationSearchParams, ScalarQuantizationConfig, ScalarType, SearchParams,
    VectorStorageDatatype,
};

use slag_edge::scan::VectorStore;
use slag_edge::scan::hnsw::qdrant;

/// How a Qdrant Edge shard stores and searches the rows.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum Kind {
    /// `Float32` storage, exact search.
    F32,
    /// `Float16` storage, exact search.
    F16,
    /// `Float32` + scalar int8 quantization, quantized full scan (`m = 0`), rescoring on or off.
    Int8 { rescore: bool },
}

impl Kind {
    /// Row label in the report.
    pub(super) fn label(self, oversampling: f64) -> String {
        match self {
            Kind::F32 => "Qdrant Edge f32, exact".into(),
            Kind::F16 => "Qdrant Edge f16, exact".into(),
            Kind::Int8 { rescore: true } => {
                format!("Qdrant Edge scalar int8 + rescoring (oversampling {oversampling})")
            }
            Kind::Int8 { rescore: false } => "Qdrant Edge scalar int8, no rescoring".into(),
        }
    }
}

/// One built Qdrant Edge shard and how to search it.
pub(super) struct Shard {
    /// `None` only while dropping: the shard is closed (and flushed) before its folder goes.
    shard: Option<EdgeShard>,
    dir: PathBuf,
    params: SearchParams,
    /// Seconds to upsert and optimise.
    pub build_s: f64,
}

impl Drop for Shard {
    fn drop(&mut self) {
        // Close the shard first (its drop flushes into the folder), then remove the folder:
        // best effort, the files are only scratch data of the benchmark; the scratch base folder
        // goes too once it is empty.
        drop(self.shard.take());
        let _ = std::fs::remove_dir_all(&self.dir);
        if let Some(base) = self.dir.parent() {
            let _ = std::fs::remove_dir(base);
        }
    }
}

/// Fresh scratch folder `base/name` (removed first if present).
fn scratch(base: &Path, name: &str) -> anyhow::Result<PathBuf> {
    let dir = base.join(name);
    if dir.exists() {
        std::fs::remove_dir_all(&dir)
            .with_context(|| format!("removing old Qdrant Edge shard {}", dir.display()))?;
    }
    Ok(dir)
}

/// Builds a shard of `kind` over every row of `rows` in `base/<name>`: `segments` optimised
/// segments of equal size, `threads` search threads, no graph (`m = 0`: exact or quantized full
/// scans).
pub(super) fn build(
    base: &Path,
    name: &str,
    rows: &VectorStore,
    kind: Kind,
    segments: usize,
    threads: usize,
    oversampling: f64,
) -> anyhow::Result<Shard> {
    let dir = scratch(base, name)?;
    let n = rows.len();
    let dim = rows.dim();
    let t = Instant::now();
    // No graph (`m = 0`); `ef_construct` unused without one (Qdrant's default).
    let hnsw = qdrant::pinned_hnsw_config(0, 100, threads);
    let mut vp = EdgeVectorParams::builder(dim, Distance::Dot).hnsw_config(hnsw);
    vp = match kind {
        Kind::F32 => vp.datatype(VectorStorageDatatype::Float32),
        Kind::F16 => vp.datatype(VectorStorageDatatype::Float16),
        Kind::Int8 { .. } => {
            #[allow(deprecated)]
            let sq = ScalarQuantizationConfig {
                r#type: ScalarType::Int8,
                quantile: None,
                always_ram: None,
                memory: Some(Memory::Pinned),
            };
            vp.datatype(VectorStorageDatatype::Float32)
                .quantization_config(QuantizationConfig::from(sq))
        }
    };
    let bytes_per_row = match kind {
        Kind::F16 => 2 * dim,
        _ => 4 * dim,
    };
    let per_segment = n.div_ceil(segments.max(1));
    // Large enough for one segment, too small for two: the merge optimiser leaves them apart.
    let max_segment_kb = (per_segment * bytes_per_row).div_ceil(1024) * 3 / 2 + 1;
    let config = qdrant::shard_config(vp.build(), hnsw, segments.max(1), max_segment_kb, threads);
    let shard = EdgeShard::new(&dir, config)
        .map_err(|e| anyhow::anyhow!("creating Qdrant Edge shard {}: {e}", dir.display()))?;
    let mut start = 0;
    while start < n {
        let end = (start + per_segment).min(n);
        qdrant::upsert(&shard, &dir, rows, start..end)?;
        shard
            .optimize()
            .map_err(|e| anyhow::anyhow!("Qdrant Edge optimize: {e}"))?;
        start = end;
    }
    let build_s = t.elapsed().as_secs_f64();
    let params = SearchParams {
        exact: matches!(kind, Kind::F32 | Kind::F16),
        quantization: match kind {
            Kind::Int8 { rescore } => Some(QuantizationSearchParams {
                ignore: false,
                rescore: Some(rescore),
                oversampling: Some(oversampling),
            }),
            _ => None,
        },
        ..SearchParams::default()
    };
    Ok(Shard {
        shard: Some(shard),
        dir,
        params,
        build_s,
    })
}

impl Shard {
    /// Searches through the int8 quantization with (`true`) or without rescoring on the
    /// originals, `oversampling` × k candidates.
    pub(super) fn set_rescore(&mut self, rescore: bool, oversampling: f64) {
        self.params.quantization = Some(QuantizationSearchParams {
            ignore: false,
            rescore: Some(rescore),
            oversampling: Some(oversampling),
        });
    }

    /// Number of segments the shard ended with.
    pub(super) fn segments(&self) -> usize {
        self.shard.as_ref().map_or(0, qdrant::segment_count)
    }

    /// Top-`k` rows for `q` (ids are row indices).
    pub(super) fn search(&self, q: &[f32], k: usize) -> anyhow::Result<Vec<usize>> {
        let req = qdrant::nearest_request(q, k, self.params.clone());
        let shard = self
            .shard
            .as_ref()
            .ok_or_else(|| anyhow::anyhow!("Qdrant Edge shard already closed"))?;
        let hits = shard
            .search(req)
            .map_err(|e| anyhow::anyhow!("Qdrant Edge search: {e}"))?;
        hits.iter()
            .map(|h| match h.id {
                PointId::NumId(i) => Ok(i as usize),
                PointId::Uuid(u) => Err(anyhow::anyhow!("unexpected point id {u}")),
            })
            .collect()
    }
}
