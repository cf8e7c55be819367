//! SLAG "Vector Database and Partitioning": per-Gaussian embeddings cut into spatial shards that a
//! robot downloads by location.
//!
//! - [`format`]: the versioned, checksummed shard byte layout ([`encode_shard`], [`decode_shard`]);
//! - [`tiles`]: ground frame, [`Manifest`], [`TileInfo`] and the `rstar` [`TileIndex`] for
//!   [`TileIndex::select_tiles`] (closed-disc radius selection on the ground plane);
//! - [`synthetic`]: deterministic synthetic scenes for tests and scale measurements;
//! - [`GaussianSource`]: what partitioning reads (implemented by
//!   [`Embeddings`](crate::embeddings::Embeddings) and [`synthetic::SyntheticScene`]).

pub mod format;
pub mod synthetic;
pub mod tiles;

pub use format::{
    Aabb, Dtype, SHARD_FORMAT_VERSION, SHARD_MAGIC, Shard, ShardError, ShardHeader, ShardInput,
    StoredShard, StoredVectors, decode_header, decode_shard, decode_shard_stored, encode_shard,
    shard_checksum,
};
pub use tiles::{
    GroundFrame, MANIFEST_FORMAT, MANIFEST_VERSION, Manifest, TileIndex, TileInfo, UpSource,
};

use crate::embeddings::Embeddings;

/// Read access to observed Gaussians for partitioning: ids and means in memory, vectors fetched
/// row by row so a source may generate or stream them (8M × 512 f32 is 16 GB).
pub trait GaussianSource: Sync {
    /// Source-`.ply` indices `[N]`.
    fn ids(&self) -> &[u32];
    /// Centres `[N]`, world frame, scene units.
    fn means(&self) -> &[[f32; 3]];
    /// Embedding width D.
    fn dim(&self) -> usize;
    /// Embedding model id.
    fn model(&self) -> &str;
    /// Writes row `i` (unit norm) into `out` (`out.len() == dim`).
    fn vector_into(&self, i: usize, out: &mut [f32]);
    /// Optional display attributes of row `i`: log-scales and pre-sigmoid opacity (INRIA `.ply`
    /// convention). When `Some` for row 0, partitioning stores them in every shard.
    fn display(&self, _i: usize) -> Option<([f32; 3], f32)> {
        None
    }
}

/// A [`GaussianSource`] plus display attributes taken from the source `.ply` (indexed by
/// Gaussian id), so shards can be rendered without the scene file.
#[derive(Debug, Clone, Copy)]
pub struct WithDisplay<'a, S> {
    /// The embeddings.
    pub inner: &'a S,
    /// Log-scales of every `.ply` Gaussian (`Gaussians::scales`).
    pub scales: &'a [[f32; 3]],
    /// Pre-sigmoid opacities of every `.ply` Gaussian (`Gaussians::opacities`).
    pub opacities: &'a [f32],
}

impl<'a, S: GaussianSource> WithDisplay<'a, S> {
    /// Wraps `inner`; checks every id indexes `scales` and `opacities`.
    ///
    /// Errors: an id out of range (the embeddings come from another `.ply`; [`crate::Error::Invalid`]).
    pub fn new(inner: &'a S, scales: &'a [[f32; 3]], opacities: &'a [f32]) -> crate::Result<Self> {
        let n = scales.len().min(opacities.len());
        if let Some(id) = inner.ids().iter().find(|&&id| id as usize >= n) {
            return Err(crate::Error::Invalid(format!(
                "Gaussian id {id} but the scene has {n}; pass the .ply the embeddings were made from"
            )));
        }
        Ok(WithDisplay {
            inner,
            scales,
            opacities,
        })
    }
}

impl<S: GaussianSource> GaussianSource for WithDisplay<'_, S> {
    fn ids(&self) -> &[u32] {
        self.inner.ids()
    }
    fn means(&self) -> &[[f32; 3]] {
        self.inner.means()
    }
    fn dim(&self) -> usize {
        self.inner.dim()
    }
    fn model(&self) -> &str {
        self.inner.model()
    }
    fn vector_into(&self, i: usize, out: &mut [f32]) {
        self.inner.vector_into(i, out)
    }
    fn display(&self, i: usize) -> Option<([f32; 3], f32)> {
        let id = *self.inner.ids().get(i)? as usize;
        Some((*self.scales.get(id)?, *self.opacities.get(id)?))
    }
}

impl GaussianSource for Embeddings {
    fn ids(&self) -> &[u32] {
        &self.ids
    }
    fn means(&self) -> &[[f32; 3]] {
        &self.means
    }
    fn dim(&self) -> usize {
        self.dim
    }
    fn model(&self) -> &str {
        &self.model
    }
    fn vector_into(&self, i: usize, out: &mut [f32]) {
        out.copy_from_slice(self.vector(i));
    }
}

/// True when `id` is a valid scene id: 1..=64 chars of `[A-Za-z0-9_.-]`, not starting with `.`
/// (safe as a path component and URL segment).
pub fn valid_scene_id(id: &str) -> bool {
    !id.is_empty()
        && id.len() <= 64
        && !id.starts_with('.')
        && id
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-' || b == b'.')
}
