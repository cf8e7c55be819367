//! SLAG "Vector Database and Partitioning": per-Gaussian embeddings cut into spatial shards that a
//! robot downloads by location.
//!
//! - [`format`]: the versioned, checksummed shard byte layout ([`encode_shard`], [`decode_shard`]);
//! - [`tiles`]: ground frame, [`Manifest`], [`TileInfo`] and the `rstar` [`TileIndex`] for
//!   [`TileIndex::select_tiles`] (closed-disc radius selection on the ground plane);
//! - [`mixture`]: mixture shards (codebook atom indices and weights per Gaussian, format
//!   version 2) and the scene's codebook file;
//! - [`signature`]: the publisher's Ed25519 key pair, detached manifest signatures and the
//!   SHA-256 of every listed file;
//! - [`frame`]: the scene-to-map similarity transform ([`SceneToMap`]) recorded in the manifest;
//! - [`synthetic`]: deterministic synthetic scenes for tests and scale measurements;
//! - [`GaussianSource`]: what partitioning reads (implemented by
//!   [`Embeddings`](crate::embeddings::Embeddings) and [`synthetic::SyntheticScene`]).

pub(crate) mod eigen;
pub mod format;
pub mod frame;
pub mod mixture;
pub mod signature;
pub mod synthetic;
pub mod tiles;

pub use format::{
    Aabb, DisplaySlices, Dtype, MIXTURE_SEGMENTS_SHARD_FORMAT_VERSION,
    MIXTURE_SHARD_FORMAT_VERSION, NEWEST_SHARD_FORMAT_VERSION, SEGMENTS_SHARD_FORMAT_VERSION,
    SHARD_FORMAT_VERSION, SHARD_MAGIC, Shard, ShardError, ShardHeader, ShardInput, ShardLayout,
    StoredShard, StoredVectors, decode_header, decode_shard, decode_shard_stored, encode_shard,
    has_segments_version, is_mixture_version, shard_checksum,
};
pub use frame::{Frames, MAP_FRAME, MapSource, SCENE_FRAME, SceneToMap};
pub use mixture::{
    CODEBOOK_TILE, Codebook, MixtureLayout, MixtureShard, MixtureShardInput, decode_codebook,
    decode_mixture_shard, encode_codebook, encode_mixture_shard,
};
pub use tiles::{
    GroundFrame, MANIFEST_FORMAT, MANIFEST_VERSION, MAX_MANIFEST_BYTES, MIXTURE_MANIFEST_VERSION,
    Manifest, MixtureInfo, TileIndex, TileInfo, UpSource, manifest_too_large,
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
    /// Optional normalised rotation (w, x, y, z) of row `i`, for display. When `Some` for row 0
    /// (and [`GaussianSource::display`] is too), partitioning stores rotations in every shard.
    fn display_rotation(&self, _i: usize) -> Option<[f32; 4]> {
        None
    }
    /// Optional SH DC colour (`f_dc_0..2`) of row `i`, for display; stored like
    /// [`GaussianSource::display_rotation`].
    fn display_sh_dc(&self, _i: usize) -> Option<[f32; 3]> {
        None
    }
    /// Optional scene-wide geometric segment id of row `i` ([`crate::segments`]). When `Some`
    /// for row 0, partitioning stores segment ids in every shard (format version 3).
    fn segment(&self, _i: usize) -> Option<u32> {
        None
    }
}

/// Display columns of a whole scene in the INRIA `.ply` storage convention (what shards carry),
/// indexed by Gaussian id: see [`DisplayColumns::from_gaussians`] and [`WithDisplay::from_columns`].
#[derive(Debug, Clone, PartialEq, Default)]
pub struct DisplayColumns {
    /// Log-scales `ln(s)` `[N][3]`.
    pub log_scales: Vec<[f32; 3]>,
    /// Pre-sigmoid opacities `logit(o)` `[N]`.
    pub logit_opacities: Vec<f32>,
    /// Normalised rotations (w, x, y, z) `[N][4]`.
    pub rotations: Vec<[f32; 4]>,
    /// SH DC colour `f_dc_0..2` `[N][3]`, when the scene was loaded with colours.
    pub sh_dc: Option<Vec<[f32; 3]>>,
}

impl DisplayColumns {
    /// Inverts the activations of [`crate::scene::load_ply`]: `ln(scale)` and `logit(opacity)`
    /// (both finite: `load_ply` keeps scales positive and opacities inside (0, 1)); rotations
    /// as loaded (normalised); SH DC from `g.sh` when present (load with
    /// `PlyLoadOptions { colours: true }`).
    pub fn from_gaussians(g: &crate::scene::Gaussians) -> DisplayColumns {
        let logit = |o: f32| {
            let o = (o as f64).clamp(f32::MIN_POSITIVE as f64, 1.0 - 1e-7);
            (o / (1.0 - o)).ln() as f32
        };
        DisplayColumns {
            log_scales: g
                .scales
                .iter()
                .map(|s| s.map(|v| (v as f64).max(1e-30).ln() as f32))
                .collect(),
            logit_opacities: g.opacities.iter().map(|&o| logit(o)).collect(),
            rotations: g.rotations.clone(),
            sh_dc: g
                .sh
                .as_ref()
                .map(|sh| (0..g.len()).map(|i| sh.dc(i)).collect()),
        }
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
    /// Optional normalised rotations (w, x, y, z) of every `.ply` Gaussian.
    pub rotations: Option<&'a [[f32; 4]]>,
    /// Optional SH DC colours (`f_dc_0..2`) of every `.ply` Gaussian.
    pub sh_dc: Option<&'a [[f32; 3]]>,
}

impl<'a, S: GaussianSource> WithDisplay<'a, S> {
    /// Wraps `inner`; checks every id indexes `scales` and `opacities`.
    ///
    /// Errors: an id out of range (the embeddings come from another `.ply`;
    /// [`crate::Error::Mismatch`]).
    pub fn new(inner: &'a S, scales: &'a [[f32; 3]], opacities: &'a [f32]) -> crate::Result<Self> {
        let n = scales.len().min(opacities.len());
        if let Some(id) = inner.ids().iter().find(|&&id| id as usize >= n) {
            return Err(crate::Error::mismatch(
                crate::Mismatched::Scene,
                format!(
                    "Gaussian id {id} but the scene has {n}; pass the .ply the embeddings were \
                     made from"
                ),
            ));
        }
        Ok(WithDisplay {
            inner,
            scales,
            opacities,
            rotations: None,
            sh_dc: None,
        })
    }

    /// Wraps `inner` with every column of `cols` (log-scales, logit opacities, rotations and,
    /// when present, SH DC), so shards carry all a splat viewer needs.
    ///
    /// Errors: an id out of range of any column ([`crate::Error::Mismatch`]).
    pub fn from_columns(inner: &'a S, cols: &'a DisplayColumns) -> crate::Result<Self> {
        let w = Self::new(inner, &cols.log_scales, &cols.logit_opacities)?;
        let w = w.with_rotations(&cols.rotations)?;
        match &cols.sh_dc {
            Some(dc) => w.with_sh_dc(dc),
            None => Ok(w),
        }
    }

    fn check_ids(&self, n: usize, what: &str) -> crate::Result<()> {
        match self.inner.ids().iter().find(|&&id| id as usize >= n) {
            Some(id) => Err(crate::Error::mismatch(
                crate::Mismatched::Scene,
                format!(
                    "Gaussian id {id} but the scene has {n} {what}; pass the .ply the embeddings \
                     were made from"
                ),
            )),
            None => Ok(()),
        }
    }

    /// Adds rotations (normalised, w x y z) indexed by Gaussian id.
    ///
    /// Errors: an id out of range ([`crate::Error::Mismatch`]).
    pub fn with_rotations(mut self, rotations: &'a [[f32; 4]]) -> crate::Result<Self> {
        self.check_ids(rotations.len(), "rotations")?;
        self.rotations = Some(rotations);
        Ok(self)
    }

    /// Adds SH DC colours (`f_dc_0..2`) indexed by Gaussian id.
    ///
    /// Errors: an id out of range ([`crate::Error::Mismatch`]).
    pub fn with_sh_dc(mut self, sh_dc: &'a [[f32; 3]]) -> crate::Result<Self> {
        self.check_ids(sh_dc.len(), "colours")?;
        self.sh_dc = Some(sh_dc);
        Ok(self)
    }
}

/// The row methods of [`GaussianSource`] (ids, means, width, model, vectors) forwarded to
/// `self.inner`: a wrapper that only adds columns implements the rest.
macro_rules! forward_rows_to_inner {
    () => {
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
    };
}

impl<S: GaussianSource> GaussianSource for WithDisplay<'_, S> {
    forward_rows_to_inner!();
    fn display(&self, i: usize) -> Option<([f32; 3], f32)> {
        let id = *self.inner.ids().get(i)? as usize;
        Some((*self.scales.get(id)?, *self.opacities.get(id)?))
    }
    fn display_rotation(&self, i: usize) -> Option<[f32; 4]> {
        let id = *self.inner.ids().get(i)? as usize;
        self.rotations?.get(id).copied()
    }
    fn display_sh_dc(&self, i: usize) -> Option<[f32; 3]> {
        let id = *self.inner.ids().get(i)? as usize;
        self.sh_dc?.get(id).copied()
    }
    fn segment(&self, i: usize) -> Option<u32> {
        self.inner.segment(i)
    }
}

/// A [`GaussianSource`] plus the scene's geometric segments ([`crate::segments::Segments`],
/// indexed by Gaussian id), so shards carry each row's segment id (format version 3).
#[derive(Debug, Clone, Copy)]
pub struct WithSegments<'a, S> {
    /// The embeddings (possibly with display columns).
    pub inner: &'a S,
    /// Segment id of every `.ply` Gaussian.
    pub segments: &'a crate::segments::Segments,
}

impl<'a, S: GaussianSource> WithSegments<'a, S> {
    /// Wraps `inner`; checks every id indexes `segments`.
    ///
    /// Errors: an id out of range (the segments come from another `.ply`;
    /// [`crate::Error::Mismatch`]).
    pub fn new(inner: &'a S, segments: &'a crate::segments::Segments) -> crate::Result<Self> {
        if let Some(id) = inner.ids().iter().find(|&&id| segments.of(id).is_none()) {
            return Err(crate::Error::mismatch(
                crate::Mismatched::Scene,
                format!(
                    "Gaussian id {id} but the segments cover {} Gaussians; segment the .ply the \
                     embeddings were made from",
                    segments.len()
                ),
            ));
        }
        Ok(WithSegments { inner, segments })
    }
}

impl<S: GaussianSource> GaussianSource for WithSegments<'_, S> {
    forward_rows_to_inner!();
    fn display(&self, i: usize) -> Option<([f32; 3], f32)> {
        self.inner.display(i)
    }
    fn display_rotation(&self, i: usize) -> Option<[f32; 4]> {
        self.inner.display_rotation(i)
    }
    fn display_sh_dc(&self, i: usize) -> Option<[f32; 3]> {
        self.inner.display_sh_dc(i)
    }
    fn segment(&self, i: usize) -> Option<u32> {
        self.segments.of(*self.inner.ids().get(i)?)
    }
}

/// The column methods of [`GaussianSource`] for a type that holds them as fields: ids in field
/// `$ids`, `means`, `dim`, and the model id in field `$model` (or a fixed string).
macro_rules! columns_from_fields {
    (ids: $ids:ident, model: $model:ident) => {
        $crate::shards::columns_from_fields!(ids: $ids);
        fn model(&self) -> &str {
            &self.$model
        }
    };
    (ids: $ids:ident, model = $model:literal) => {
        $crate::shards::columns_from_fields!(ids: $ids);
        fn model(&self) -> &str {
            $model
        }
    };
    (ids: $ids:ident) => {
        fn ids(&self) -> &[u32] {
            &self.$ids
        }
        fn means(&self) -> &[[f32; 3]] {
            &self.means
        }
        fn dim(&self) -> usize {
            self.dim
        }
    };
}
pub(crate) use columns_from_fields;

impl GaussianSource for Embeddings {
    columns_from_fields!(ids: ids, model: model);
    fn vector_into(&self, i: usize, out: &mut [f32]) {
        out.copy_from_slice(self.vector(i));
    }
}

/// The reconstructed rows of a mixture (`Σ_s weights · codebook[atoms]`, unit norm up to f16
/// rounding): a mixture can be partitioned densely (e.g. for Qdrant) like any embeddings file.
impl GaussianSource for crate::mixture::MixtureEmbeddings {
    columns_from_fields!(ids: gaussian_ids, model: model_id);
    fn vector_into(&self, i: usize, out: &mut [f32]) {
        out.iter_mut().for_each(|v| *v = 0.0);
        self.add_vector_into(i, out);
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
