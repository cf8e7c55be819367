//! The `instant-distance` backend of [`super::ApproxIndex`] (always built): an HNSW graph
//! (Malkov & Yashunin 2018) over a [`VectorStore`], built with the `instant-distance` crate.
//!
//! Distance is cosine distance `1 − x·y` on the rows as stored, dequantised to f32, with the
//! scan's explicit SIMD dot at the run-time level (`kernels::dot_f32`; unit rows, so
//! ranking by distance is ranking by cosine). The index holds its own f32 copy of the rows
//! (instant-distance keeps its points by value), so its memory is `N·D·4` bytes plus the graph:
//! see [`HnswIndex::memory_bytes`].

use std::sync::Arc;

use instant_distance::{Builder, Hnsw, Point, Search};
use slag_common::Error;

use super::IndexShape;
use crate::scan::kernels::dot_f32;
use crate::scan::{Hit, VectorStore};

/// Neighbours per node in instant-distance 0.6 (`M`; layer 0 keeps `2·M`).
const HNSW_M: usize = 32;

/// One row as an instant-distance point: a shared matrix and a row index.
#[derive(Clone, Debug)]
struct RowPoint {
    data: Arc<[f32]>,
    row: u32,
    dim: u32,
}

impl RowPoint {
    fn slice(&self) -> &[f32] {
        let d = self.dim as usize;
        let r = self.row as usize;
        self.data.get(r * d..(r + 1) * d).unwrap_or(&[])
    }
}

impl Point for RowPoint {
    fn distance(&self, other: &Self) -> f32 {
        // The scan's explicit SIMD dot at the run-time level (AVX-512F / AVX2 + FMA / NEON).
        1.0 - dot_f32(self.slice(), other.slice())
    }
}

/// An HNSW graph over every row of a store (row indices refer to that store).
pub struct HnswIndex {
    hnsw: Hnsw<RowPoint>,
    data: Arc<[f32]>,
    /// Row width, row count and the beam fixed at build time.
    shape: IndexShape,
}

impl std::fmt::Debug for HnswIndex {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("HnswIndex")
            .field("shape", &self.shape)
            .finish()
    }
}

impl HnswIndex {
    /// Builds the index over all rows of `store` (multi-threaded, rayon) with
    /// `ef_construction` candidates per insertion and a fixed `ef_search` (instant-distance fixes
    /// the search beam at build time; a query returns at most `ef_search` rows). `seed` makes the
    /// layer assignment, and so the graph, reproducible.
    ///
    /// Errors: [`Error::Param`] for `ef_construction == 0`, `ef_search == 0`; [`Error::Invalid`] for more than
    /// `u32::MAX - 1` rows.
    pub fn build(
        store: &VectorStore,
        ef_construction: usize,
        ef_search: usize,
        seed: u64,
    ) -> Result<HnswIndex, Error> {
        if ef_construction == 0 || ef_search == 0 {
            return Err(Error::param(
                if ef_construction == 0 {
                    "ef_construction"
                } else {
                    "ef_search"
                },
                0,
                "at least 1 (typical: 100)",
            ));
        }
        let n = store.len();
        if n >= u32::MAX as usize {
            return Err(Error::Invalid(format!(
                "{n} rows exceed the HNSW index limit of {} rows",
                u32::MAX - 1
            )));
        }
        let dim = store.dim();
        let mut flat = Vec::with_capacity(n * dim);
        for i in 0..n {
            flat.extend(store.row_f32(i).unwrap_or_default());
        }
        let data: Arc<[f32]> = flat.into();
        let points: Vec<RowPoint> = (0..n as u32)
            .map(|row| RowPoint {
                data: Arc::clone(&data),
                row,
                dim: dim as u32,
            })
            .collect();
        let (hnsw, _) = Builder::default()
            .ef_construction(ef_construction)
            .ef_search(ef_search)
            .seed(seed)
            .build_hnsw(points);
        Ok(HnswIndex {
            hnsw,
            data,
            shape: IndexShape {
                dim,
                len: n,
                ef_search,
            },
        })
    }

    /// Row width, row count and the search beam fixed at build time.
    pub fn shape(&self) -> &IndexShape {
        &self.shape
    }

    /// Approximately the `k` rows with the highest cosine to `query` (`[D]`), best first (score
    /// = `query · row`, ties by row). Recall depends on `ef_search` and `ef_construction`.
    ///
    /// Errors: as [`crate::scan::scan`] for a query of the wrong width or with non-finite values;
    /// [`Error::Param`] `top_k` for `k > ef_search` (rebuild with `ef_search >= k`).
    pub fn query(&self, query: &[f32], k: usize) -> Result<Vec<Hit>, Error> {
        self.shape.check_query(query, k, "rebuild with ef_search")?;
        let q = RowPoint {
            data: query.into(),
            row: 0,
            dim: self.shape.dim as u32,
        };
        let mut search = Search::default();
        let mut hits: Vec<Hit> = self
            .hnsw
            .search(&q, &mut search)
            .map(|item| Hit {
                row: item.point.row as usize,
                score: 1.0 - item.distance,
            })
            .collect();
        hits.sort_by(crate::scan::select::rank_cmp);
        hits.truncate(k);
        Ok(hits)
    }

    /// Bytes held by the index: the f32 copy of the rows (`N·D·4`), the point handles, and the
    /// graph as laid out by instant-distance 0.6 (layer 0: `2·M` u32 links per node; each upper
    /// layer `l`: `M` links for every node of layer ≥ `l`; M = 32). Excludes allocator slack.
    pub fn memory_bytes(&self) -> usize {
        let n = self.shape.len;
        let vectors = self.data.len() * 4;
        let handles = n * std::mem::size_of::<RowPoint>();
        let zero = n * 2 * HNSW_M * 4;
        // Same layer sizing as instant-distance's `Hnsw::new` (ml = 1 / ln M).
        let ml = 1.0 / (HNSW_M as f32).ln();
        let mut upper_nodes = 0usize;
        let mut num = n;
        loop {
            let next = (num as f32 * ml) as usize;
            if next < HNSW_M {
                break;
            }
            upper_nodes += next;
            num = next;
        }
        vectors + handles + zero + upper_nodes * HNSW_M * 4
    }
}

#[cfg(test)]
mod tests {
    //! instant-distance on its own; recall and the shared contract: `super::super::tests`.
    use super::*;
    use slag_common::shards::Dtype;

    #[test]
    fn hnsw_rejects_bad_parameters() {
        let store = VectorStore::synthetic(100, 8, Dtype::F16, 3, 1).expect("store");
        assert!(matches!(
            HnswIndex::build(&store, 0, 10, 1),
            Err(Error::Param {
                name: "ef_construction",
                ..
            })
        ));
        let empty = VectorStore::new(8, Dtype::F32).expect("store");
        let e = HnswIndex::build(&empty, 20, 10, 1).expect("index");
        assert!(e.query(&[0.1; 8], 5).expect("query").is_empty());
    }
}
