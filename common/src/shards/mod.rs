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
    decode_header, decode_shard, encode_shard, shard_checksum,
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
