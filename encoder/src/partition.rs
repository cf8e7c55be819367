//! `slag-encoder partition`: cut per-Gaussian embeddings into spatial shards (SLAG, "Vector
//! Database and Partitioning").
//!
//! Tiles are sized from the scene: an adaptive k-d tree on the ground plane splits a cell at the
//! median of its longer side until each leaf holds at most `max_per_shard` Gaussians, so dense
//! areas get small tiles and empty space none. Each leaf becomes one shard
//! ([`slag_common::shards::format`]); its footprint is the tight ground-plane rectangle of its
//! means. Leaves are numbered in depth-first order (spatially coherent ids). Median splits make
//! leaf counts balanced (between `max/2` and `max` for large scenes) while their areas follow the
//! density.

use rayon::prelude::*;
use slag_common::shards::{
    Dtype, GaussianSource, GroundFrame, MANIFEST_FORMAT, MANIFEST_VERSION, Manifest,
    SHARD_FORMAT_VERSION, ShardInput, TileInfo, encode_shard, shard_checksum, valid_scene_id,
};
use slag_common::{Error, Result};

/// How to choose the ground plane's up axis.
#[derive(Debug, Clone, PartialEq)]
pub enum UpChoice {
    /// A user-given axis or vector (world frame), e.g. from `--up -y`.
    Given(GroundFrame),
    /// Training cameras' up vectors in world frame (COLMAP: camera −y axis); their mean is used.
    CameraUps(Vec<[f64; 3]>),
    /// Smallest-variance principal axis of the means.
    Pca,
}

/// Parameters of [`partition`].
#[derive(Debug, Clone)]
pub struct PartitionParams {
    /// Scene id (see [`valid_scene_id`]).
    pub scene_id: String,
    /// Most Gaussians per tile (≥ 1).
    pub max_per_shard: usize,
    /// Up axis choice.
    pub up: UpChoice,
    /// Storage type of the vectors in the shards.
    pub dtype: Dtype,
}

/// One planned tile: which Gaussians (row indices into the source) and their ground bounds.
#[derive(Debug, Clone, PartialEq)]
pub struct TilePlan {
    /// Tile id (depth-first leaf order).
    pub id: u64,
    /// Row indices into the source, ascending.
    pub rows: Vec<u32>,
    /// Ground-plane bounds `(g0, g1)` of the means, min corner.
    pub min: [f64; 2],
    /// Max corner.
    pub max: [f64; 2],
}

/// Resolves the ground frame for `means`.
///
/// Errors: as [`GroundFrame::from_camera_ups`] / [`GroundFrame::from_pca`].
pub fn ground_frame(means: &[[f32; 3]], up: &UpChoice) -> Result<GroundFrame> {
    match up {
        UpChoice::Given(g) => Ok(*g),
        UpChoice::CameraUps(v) => GroundFrame::from_camera_ups(v),
        UpChoice::Pca => GroundFrame::from_pca(means),
    }
}

/// Adaptive k-d tiling of `means` on the ground plane (see module doc).
///
/// Errors: `max_per_shard == 0`, more than `u32::MAX` Gaussians, non-finite means
/// ([`Error::Invalid`]).
pub fn plan_tiles(
    means: &[[f32; 3]],
    ground: &GroundFrame,
    max_per_shard: usize,
) -> Result<Vec<TilePlan>> {
    if max_per_shard == 0 {
        return Err(Error::Invalid("--max-per-shard must be at least 1".into()));
    }
    if u32::try_from(means.len()).is_err() {
        return Err(Error::Invalid(format!(
            "{} Gaussians exceed the u32 id range",
            means.len()
        )));
    }
    if let Some(i) = means.iter().position(|m| m.iter().any(|x| !x.is_finite())) {
        return Err(Error::Invalid(format!(
            "mean {i} is not finite; fix the embeddings file"
        )));
    }
    let g: Vec<[f64; 2]> = means
        .par_iter()
        .map(|&m| {
            let p = ground.to_ground(m);
            [p[0], p[1]]
        })
        .collect();
    let mut perm: Vec<u32> = (0..means.len() as u32).collect();
    let bounds = |rows: &[u32]| {
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for &r in rows {
            let p = g[r as usize];
            for a in 0..2 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        (lo, hi)
    };
    let mut tiles = Vec::new();
    // Depth-first with an explicit stack of ranges into `perm`; right child pushed first so the
    // left child is visited first.
    let mut stack = vec![(0usize, perm.len())];
    while let Some((a, b)) = stack.pop() {
        if a == b {
            continue;
        }
        let rows = &mut perm[a..b];
        let (lo, hi) = bounds(rows);
        if rows.len() <= max_per_shard {
            let mut r = rows.to_vec();
            r.sort_unstable();
            tiles.push(TilePlan {
                id: tiles.len() as u64,
                rows: r,
                min: lo,
                max: hi,
            });
            continue;
        }
        let axis = if hi[0] - lo[0] >= hi[1] - lo[1] { 0 } else { 1 };
        let mid = rows.len() / 2;
        rows.select_nth_unstable_by(mid, |&x, &y| {
            g[x as usize][axis].total_cmp(&g[y as usize][axis])
        });
        stack.push((a + mid, b));
        stack.push((a, a + mid));
    }
    Ok(tiles)
}

/// Encodes the shard of one planned tile.
///
/// Errors: as [`encode_shard`].
pub fn encode_tile(
    src: &impl GaussianSource,
    scene_id: &str,
    dtype: Dtype,
    plan: &TilePlan,
) -> Result<(TileInfo, Vec<u8>)> {
    let d = src.dim();
    let n = plan.rows.len();
    let (ids_all, means_all) = (src.ids(), src.means());
    let ids: Vec<u32> = plan.rows.iter().map(|&r| ids_all[r as usize]).collect();
    let means: Vec<[f32; 3]> = plan.rows.iter().map(|&r| means_all[r as usize]).collect();
    let mut vectors = vec![0.0f32; n * d];
    for (row, out) in plan.rows.iter().zip(vectors.chunks_exact_mut(d.max(1))) {
        src.vector_into(*row as usize, out);
    }
    let display: Option<(Vec<[f32; 3]>, Vec<f32>)> =
        (n > 0 && src.display(0).is_some()).then(|| {
            plan.rows
                .iter()
                .map(|&r| src.display(r as usize).unwrap_or(([0.0; 3], 0.0)))
                .unzip()
        });
    let has_display = display.is_some();
    let rotations: Option<Vec<[f32; 4]>> =
        (has_display && src.display_rotation(0).is_some()).then(|| {
            plan.rows
                .iter()
                .map(|&r| {
                    src.display_rotation(r as usize)
                        .unwrap_or([1.0, 0.0, 0.0, 0.0])
                })
                .collect()
        });
    let sh_dc: Option<Vec<[f32; 3]>> = (has_display && src.display_sh_dc(0).is_some()).then(|| {
        plan.rows
            .iter()
            .map(|&r| src.display_sh_dc(r as usize).unwrap_or([0.0; 3]))
            .collect()
    });
    let bytes = encode_shard(&ShardInput {
        scene_id,
        model: src.model(),
        tile_id: plan.id,
        dim: d,
        dtype,
        ids: &ids,
        means: &means,
        vectors: &vectors,
        scales: display.as_ref().map(|d| d.0.as_slice()),
        opacities: display.as_ref().map(|d| d.1.as_slice()),
        rotations: rotations.as_deref(),
        sh_dc: sh_dc.as_deref(),
    })?;
    let aabb = slag_common::shards::Aabb::of_points(means.iter().copied()).unwrap_or_default();
    let info = TileInfo {
        id: plan.id,
        footprint: TileInfo::rect_ring(plan.min, plan.max),
        aabb,
        count: n as u64,
        bytes: bytes.len() as u64,
        checksum: format!("{:08x}", shard_checksum(&bytes)),
    };
    Ok((info, bytes))
}

/// Partitions `src` and hands each shard to `sink` in tile-id order (tiles are encoded in
/// parallel, a bounded batch at a time, so memory stays at a few shards per thread). Returns the
/// manifest (`generation` 0; a store sets it on commit).
///
/// Errors: invalid scene id or parameters ([`Error::Invalid`]), encoding errors, and whatever
/// `sink` returns (partitioning stops at the first error).
pub fn partition_with(
    src: &impl GaussianSource,
    params: &PartitionParams,
    mut sink: impl FnMut(&TileInfo, Vec<u8>) -> Result<()>,
) -> Result<Manifest> {
    if !valid_scene_id(&params.scene_id) {
        return Err(Error::Invalid(format!(
            "scene id {:?}: use 1-64 characters of A-Z a-z 0-9 _ - . (not starting with '.')",
            params.scene_id
        )));
    }
    let (n, d) = (src.ids().len(), src.dim());
    if src.means().len() != n {
        return Err(Error::Invalid(format!(
            "{n} ids but {} means",
            src.means().len()
        )));
    }
    if d == 0 {
        return Err(Error::Invalid("embedding dim is 0".into()));
    }
    let ground = ground_frame(src.means(), &params.up)?;
    let plans = plan_tiles(src.means(), &ground, params.max_per_shard)?;
    let batch = 4 * rayon::current_num_threads().max(1);
    let mut tiles = Vec::with_capacity(plans.len());
    for chunk in plans.chunks(batch) {
        let encoded: Vec<Result<(TileInfo, Vec<u8>)>> = chunk
            .par_iter()
            .map(|p| encode_tile(src, &params.scene_id, params.dtype, p))
            .collect();
        for e in encoded {
            let (info, bytes) = e?;
            sink(&info, bytes)?;
            tiles.push(info);
        }
    }
    Ok(Manifest {
        format: MANIFEST_FORMAT.into(),
        manifest_version: MANIFEST_VERSION,
        shard_format_version: SHARD_FORMAT_VERSION,
        scene_id: params.scene_id.clone(),
        generation: 0,
        model: src.model().to_string(),
        dim: d as u32,
        dtype: params.dtype,
        ground,
        max_per_shard: params.max_per_shard as u64,
        total_gaussians: n as u64,
        tiles,
    })
}

/// `(tile id, shard bytes)` of every tile, ascending id.
pub type EncodedShards = Vec<(u64, Vec<u8>)>;

/// Partitions in memory: the manifest and `(tile id, shard bytes)` for every tile.
///
/// Errors: as [`partition_with`].
pub fn partition(
    src: &impl GaussianSource,
    params: &PartitionParams,
) -> Result<(Manifest, EncodedShards)> {
    let mut shards = Vec::new();
    let m = partition_with(src, params, |info, bytes| {
        shards.push((info.id, bytes));
        Ok(())
    })?;
    Ok((m, shards))
}
