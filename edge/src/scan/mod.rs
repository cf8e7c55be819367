//! TEMPORARY stand-in for the scan kernels (being written on branch `scan`); same API, naive code.
#![allow(missing_docs)]

use slag_common::shards::{Dtype, StoredShard, StoredVectors};
use slag_common::{Error, Result};

pub struct VectorStore {
    dim: usize,
    dtype: Dtype,
    ids: Vec<u32>,
    means: Vec<[f32; 3]>,
    vectors: Vec<f32>,
}

impl VectorStore {
    pub fn new(dim: usize, dtype: Dtype) -> Self {
        VectorStore {
            dim,
            dtype,
            ids: vec![],
            means: vec![],
            vectors: vec![],
        }
    }
    pub fn push_shard(&mut self, s: StoredShard) -> Result<()> {
        if s.header.dim as usize != self.dim || s.vectors.dtype() != self.dtype {
            return Err(Error::Invalid("dim/dtype mismatch".into()));
        }
        self.vectors.extend(s.vectors.to_f32(self.dim));
        self.ids.extend(s.ids);
        self.means.extend(s.means);
        let _ = StoredVectors::F32(vec![]);
        Ok(())
    }
    pub fn dim(&self) -> usize {
        self.dim
    }
    pub fn dtype(&self) -> Dtype {
        self.dtype
    }
    pub fn len(&self) -> usize {
        self.ids.len()
    }
    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }
    pub fn ids(&self) -> &[u32] {
        &self.ids
    }
    pub fn means(&self) -> &[[f32; 3]] {
        &self.means
    }
    pub fn memory_bytes(&self) -> usize {
        self.vectors.len() * 4 + self.ids.len() * 16
    }
}

pub struct ScanRequest<'a> {
    pub queries: &'a [&'a [f32]],
    pub top_k: Option<usize>,
    pub threshold: Option<f32>,
    pub bbox: Option<([f32; 3], [f32; 3])>,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    pub row: usize,
    pub score: f32,
}

pub fn scan(
    store: &VectorStore,
    req: &ScanRequest<'_>,
    combine: fn(&[f32]) -> f32,
) -> Result<Vec<Hit>> {
    let d = store.dim;
    let mut hits = Vec::new();
    let mut dots = vec![0f32; req.queries.len()];
    for i in 0..store.len() {
        if let Some((lo, hi)) = req.bbox {
            let m = store.means[i];
            if !(0..3).all(|a| m[a] >= lo[a] && m[a] <= hi[a]) {
                continue;
            }
        }
        let row = &store.vectors[i * d..(i + 1) * d];
        for (q, o) in req.queries.iter().zip(dots.iter_mut()) {
            *o = row.iter().zip(q.iter()).map(|(a, b)| a * b).sum();
        }
        let s = combine(&dots);
        if req.threshold.is_none_or(|t| s >= t) {
            hits.push(Hit { row: i, score: s });
        }
    }
    hits.sort_by(|a, b| b.score.total_cmp(&a.score).then(a.row.cmp(&b.row)));
    if let Some(k) = req.top_k {
        hits.truncate(k);
    }
    Ok(hits)
}

pub struct HnswIndex;
impl HnswIndex {
    pub fn build(_store: &VectorStore) -> Result<Self> {
        Ok(HnswIndex)
    }
    pub fn search(&self, store: &VectorStore, q: &[f32], k: usize) -> Result<Vec<Hit>> {
        let qs = [q];
        scan(
            store,
            &ScanRequest {
                queries: &qs,
                top_k: Some(k),
                threshold: None,
                bbox: None,
            },
            |d| d[0],
        )
    }
    pub fn memory_bytes(&self) -> usize {
        0
    }
}
