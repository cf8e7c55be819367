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
//!
//! The cap is set in bytes by default ([`ShardCap::Bytes`], `--max-shard-mb`): the largest count
//! whose encoded shard fits, from the shard format's exact size model
//! ([`ShardLayout::max_rows_within`]), so a robot's download unit stays the same whether the
//! vectors are stored as f32, f16 or int8. [`storage_report`] compares what was stored with a
//! naive dense `N × D` f32 tensor of the whole scene.

use rayon::prelude::*;
use slag_common::mixture::MixtureEmbeddings;
use slag_common::shards::signature::sha256_hex;
use slag_common::shards::{
    DisplaySlices, Dtype, GaussianSource, GroundFrame, MANIFEST_FORMAT, MANIFEST_VERSION,
    MIXTURE_MANIFEST_VERSION, MIXTURE_SEGMENTS_SHARD_FORMAT_VERSION, MIXTURE_SHARD_FORMAT_VERSION,
    Manifest, MixtureInfo, MixtureLayout, MixtureShardInput, SEGMENTS_SHARD_FORMAT_VERSION,
    SHARD_FORMAT_VERSION, SceneToMap, ShardInput, ShardLayout, TileInfo, encode_codebook,
    encode_mixture_shard, encode_shard, shard_checksum, valid_scene_id,
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
    /// Most Gaussians per tile (≥ 1), as recorded in the manifest. From a byte budget, resolve it
    /// with [`resolve_max_per_shard`].
    pub max_per_shard: usize,
    /// Up axis choice.
    pub up: UpChoice,
    /// Storage type of the vectors in the shards.
    pub dtype: Dtype,
    /// Scene-to-map transform recorded in the manifest (`Frames::scene_to_map`); `None`: the
    /// manifest has no map frame. It does not change the tiling (footprints stay in the scene
    /// frame); pass [`UpChoice::Given`] with [`map_ground_frame`] to tile on the map's ground.
    pub to_map: Option<SceneToMap>,
}

/// The ground frame whose up axis is the map's z axis seen from the scene
/// ([`SceneToMap::map_up_in_scene`]), [`slag_common::shards::UpSource::Map`]: discs on it are
/// horizontal discs of the map.
///
/// Errors: none in practice (the rotation is orthonormal); as [`GroundFrame::from_up`].
pub fn map_ground_frame(to_map: &SceneToMap) -> Result<GroundFrame> {
    GroundFrame::from_up(to_map.map_up_in_scene(), slag_common::shards::UpSource::Map)
}

/// Default `--max-shard-mb`, in MiB (2^20 bytes) of encoded shard per tile.
///
/// 16 MiB keeps the f16 default where the old `--max-per-shard 16384` put it (16,384 f16 rows
/// were 17.0 MB = 16.25 MiB): a dim-512 f16 row is 1040 bytes (1084 with `--display-ply`), so
/// with a ~100-byte header the cap is 16,131 Gaussians (15,477 with display columns), 1.5 %
/// fewer than before, and snowmiku's 117,880 observed Gaussians still make 8 shards of 14,735.
/// The same 16 MiB holds 8,128 Gaussians at f32 and 31,535 at int8, where the count cap gave
/// 34 MB and 8.7 MB shards: a robot fetches the same unit whatever the dtype. It also keeps the
/// manifest short (a 10 M-Gaussian f16 scene makes ~1000 tiles).
pub const DEFAULT_MAX_SHARD_MIB: f64 = 16.0;

/// Bytes in one MiB (`--max-shard-mb` counts MiB).
pub const MIB: u64 = 1 << 20;

/// How large one tile may grow.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ShardCap {
    /// At most this many bytes of encoded shard (header + payload: what `TileInfo::bytes` records
    /// and a robot downloads); `--max-shard-mb`.
    Bytes(u64),
    /// At most this many Gaussians, whatever their size; `--max-per-shard`.
    Gaussians(usize),
}

impl ShardCap {
    /// A budget of `mib` MiB: `floor(mib · 2^20)` bytes.
    ///
    /// Errors ([`Error::Param`] `max_shard_mib`): `mib` not finite or not positive, or below one
    /// byte.
    pub fn from_mib(mib: f64) -> Result<ShardCap> {
        let bytes = mib * MIB as f64;
        if !bytes.is_finite() || bytes < 1.0 {
            return Err(Error::param(
                "max_shard_mib",
                mib,
                format!(
                    "a positive size in MiB, e.g. {DEFAULT_MAX_SHARD_MIB} (or a max_per_shard \
                     count of Gaussians instead)"
                ),
            ));
        }
        Ok(ShardCap::Bytes(bytes.min(u64::MAX as f64) as u64))
    }
}

/// The layout every shard of `src` gets from [`partition`] (same dtype, scene and model ids, and
/// the same display-section choice as [`encode_tile`]: sections present when the source has
/// them for row 0).
pub fn shard_layout(src: &impl GaussianSource, scene_id: &str, dtype: Dtype) -> ShardLayout {
    let display = !src.ids().is_empty() && src.display(0).is_some();
    ShardLayout {
        dtype,
        dim: src.dim(),
        scales: display,
        opacities: display,
        rotations: display && src.display_rotation(0).is_some(),
        sh_dc: display && src.display_sh_dc(0).is_some(),
        segments: !src.ids().is_empty() && src.segment(0).is_some(),
        scene_id_len: scene_id.len(),
        model_len: src.model().len(),
    }
}

/// Resolves `cap` to [`PartitionParams::max_per_shard`]: a count is taken as is; a byte budget
/// becomes the largest N whose shard under `layout` fits in it
/// ([`ShardLayout::max_rows_within`], exact: no estimate), so every written shard is ≤ the
/// budget and a full tile is within one row of it.
///
/// Errors ([`Error::Param`] `max_per_shard` / `max_shard_mib`, saying what works): a count of 0,
/// a budget of 0 bytes, or a budget smaller than a shard of one Gaussian.
pub fn resolve_max_per_shard(layout: &ShardLayout, cap: ShardCap) -> Result<usize> {
    match cap {
        ShardCap::Gaussians(0) => Err(Error::param(
            "max_per_shard",
            0,
            "at least 1 Gaussian per shard (or a max_shard_mib byte budget instead)",
        )),
        ShardCap::Gaussians(n) => Ok(n),
        ShardCap::Bytes(0) => Err(Error::param(
            "max_shard_mib",
            0,
            format!("a positive size in MiB, e.g. {DEFAULT_MAX_SHARD_MIB}"),
        )),
        ShardCap::Bytes(b) => {
            let n = layout.max_rows_within(b);
            if n == 0 {
                let one = layout.shard_len(1);
                return Err(Error::param(
                    "max_shard_mib",
                    format!("{:.6} ({b} bytes)", b as f64 / MIB as f64),
                    format!(
                        "at least {:.6} MiB: a shard of one Gaussian is {one} bytes at {:?}, dim \
                         {}{}",
                        (one as f64 / MIB as f64 * 1e6).ceil() / 1e6,
                        layout.dtype,
                        layout.dim,
                        if layout.scales {
                            ", with display columns"
                        } else {
                            ""
                        },
                    ),
                ));
            }
            Ok(usize::try_from(n).unwrap_or(usize::MAX))
        }
    }
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
/// Errors: `max_per_shard == 0` ([`Error::Param`]), more than `u32::MAX` Gaussians, non-finite
/// means ([`Error::Invalid`]).
pub fn plan_tiles(
    means: &[[f32; 3]],
    ground: &GroundFrame,
    max_per_shard: usize,
) -> Result<Vec<TilePlan>> {
    if max_per_shard == 0 {
        return Err(Error::param(
            "max_per_shard",
            0,
            "at least 1 Gaussian per shard",
        ));
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

/// The columns of one tile other than its embeddings: ids, means and the display columns the
/// source has ([`GaussianSource::display`] for row 0 decides, as for every tile).
struct TileColumns {
    ids: Vec<u32>,
    means: Vec<[f32; 3]>,
    display: Option<(Vec<[f32; 3]>, Vec<f32>)>,
    rotations: Option<Vec<[f32; 4]>>,
    sh_dc: Option<Vec<[f32; 3]>>,
    segments: Option<Vec<u32>>,
}

impl TileColumns {
    /// The display sections, borrowed for a shard input.
    fn display(&self) -> DisplaySlices<'_> {
        DisplaySlices {
            scales: self.display.as_ref().map(|d| d.0.as_slice()),
            opacities: self.display.as_ref().map(|d| d.1.as_slice()),
            rotations: self.rotations.as_deref(),
            sh_dc: self.sh_dc.as_deref(),
        }
    }

    fn info(&self, plan: &TilePlan, bytes: &[u8]) -> TileInfo {
        TileInfo {
            id: plan.id,
            footprint: TileInfo::rect_ring(plan.min, plan.max),
            aabb: slag_common::shards::Aabb::of_points(self.means.iter().copied())
                .unwrap_or_default(),
            count: self.ids.len() as u64,
            bytes: bytes.len() as u64,
            checksum: format!("{:08x}", shard_checksum(bytes)),
            sha256: Some(sha256_hex(bytes)),
        }
    }
}

fn tile_columns(src: &impl GaussianSource, plan: &TilePlan) -> TileColumns {
    let n = plan.rows.len();
    let (ids_all, means_all) = (src.ids(), src.means());
    let ids: Vec<u32> = plan.rows.iter().map(|&r| ids_all[r as usize]).collect();
    let means: Vec<[f32; 3]> = plan.rows.iter().map(|&r| means_all[r as usize]).collect();
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
    let segments: Option<Vec<u32>> = (n > 0 && src.segment(0).is_some()).then(|| {
        plan.rows
            .iter()
            .map(|&r| {
                src.segment(r as usize)
                    .unwrap_or(slag_common::segments::NO_SEGMENT)
            })
            .collect()
    });
    TileColumns {
        ids,
        means,
        display,
        rotations,
        sh_dc,
        segments,
    }
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
    let mut vectors = vec![0.0f32; n * d];
    for (row, out) in plan.rows.iter().zip(vectors.chunks_exact_mut(d.max(1))) {
        src.vector_into(*row as usize, out);
    }
    let c = tile_columns(src, plan);
    let input = ShardInput {
        scene_id,
        model: src.model(),
        tile_id: plan.id,
        dim: d,
        dtype,
        ids: &c.ids,
        means: &c.means,
        vectors: &vectors,
        ..Default::default()
    };
    let bytes = encode_shard(&input.with_display(c.display(), c.segments.as_deref()))?;
    Ok((c.info(plan, &bytes), bytes))
}

/// Encodes the mixture shard of one planned tile: rows `plan.rows` of `mix` (same row order as
/// `src`, whose ids, means and display columns it takes), naming the codebook's checksum.
///
/// Errors: as [`encode_mixture_shard`].
pub fn encode_mixture_tile(
    src: &impl GaussianSource,
    mix: &MixtureEmbeddings,
    scene_id: &str,
    codebook_crc: u32,
    plan: &TilePlan,
) -> Result<(TileInfo, Vec<u8>)> {
    let s = mix.keep;
    let mut atoms = Vec::with_capacity(plan.rows.len() * s);
    let mut weights = Vec::with_capacity(plan.rows.len() * s);
    for &r in &plan.rows {
        let slots = r as usize * s..(r as usize + 1) * s;
        atoms.extend_from_slice(&mix.atoms[slots.clone()]);
        weights.extend_from_slice(&mix.weights[slots]);
    }
    let c = tile_columns(src, plan);
    let input = MixtureShardInput {
        scene_id,
        model: src.model(),
        tile_id: plan.id,
        dim: mix.dim,
        slots: s,
        codebook_crc,
        ids: &c.ids,
        means: &c.means,
        atoms: &atoms,
        weights: &weights,
        ..Default::default()
    };
    let bytes = encode_mixture_shard(&input.with_display(c.display(), c.segments.as_deref()))?;
    Ok((c.info(plan, &bytes), bytes))
}

/// The layout every mixture shard of `src` gets from [`partition_mixture_with`] with `slots`
/// slots per Gaussian (display sections as [`shard_layout`]).
pub fn mixture_layout(src: &impl GaussianSource, scene_id: &str, slots: usize) -> MixtureLayout {
    MixtureLayout {
        base: shard_layout(src, scene_id, Dtype::F16),
        slots,
    }
}

/// Resolves `cap` for mixture shards ([`resolve_max_per_shard`] with the mixture size model).
///
/// Errors: as [`resolve_max_per_shard`].
pub fn resolve_mixture_max_per_shard(layout: &MixtureLayout, cap: ShardCap) -> Result<usize> {
    match cap {
        ShardCap::Bytes(b) if b > 0 && layout.max_rows_within(b) == 0 => Err(Error::param(
            "max_shard_mib",
            format!("{:.6} ({b} bytes)", b as f64 / MIB as f64),
            format!(
                "at least {} bytes: a mixture shard of one Gaussian with {} slots",
                layout.shard_len(1),
                layout.slots
            ),
        )),
        ShardCap::Bytes(b) if b > 0 => {
            Ok(usize::try_from(layout.max_rows_within(b)).unwrap_or(usize::MAX))
        }
        other => resolve_max_per_shard(&layout.base, other),
    }
}

/// Partitions a mixture scene: the same ground tiles as [`partition_with`] over `src`'s means,
/// one mixture shard per tile (format version 2, rows of `mix`: `src` must list the same
/// Gaussians in the same order, e.g. `mix` itself or a [`slag_common::shards::WithDisplay`]
/// around it), and the scene's codebook file. Cut `mix` to fewer slots first with
/// [`MixtureEmbeddings::truncated`]. `params.dtype` is ignored (mixture weights are f16; the
/// manifest says f16). Returns the manifest (version 2, with its [`MixtureInfo`]) and the
/// codebook bytes; shards go to `sink` in tile-id order.
///
/// Errors: `src` and `mix` listing other Gaussians ([`Error::Mismatch`]), an inconsistent
/// mixture ([`Error::Internal`]), and as [`partition_with`].
pub fn partition_mixture_with(
    src: &impl GaussianSource,
    mix: &MixtureEmbeddings,
    params: &PartitionParams,
    mut sink: impl FnMut(&TileInfo, Vec<u8>) -> Result<()>,
) -> Result<(Manifest, Vec<u8>)> {
    check_scene_and_source(src, params)?;
    mix.validate()?;
    if src.ids() != mix.gaussian_ids.as_slice() || src.dim() != mix.dim {
        return Err(Error::mismatch(
            slag_common::Mismatched::Scene,
            "the rows to partition and the mixture list other Gaussians (or another width); \
             partition the mixture file with the display .ply of the same scene",
        ));
    }
    let codebook = encode_codebook(&params.scene_id, src.model(), mix.dim, &mix.codebook)?;
    let crc = shard_checksum(&codebook);
    let ground = ground_frame(src.means(), &params.up)?;
    let plans = plan_tiles(src.means(), &ground, params.max_per_shard)?;
    let tiles = encode_in_batches(&plans, &mut sink, |p| {
        encode_mixture_tile(src, mix, &params.scene_id, crc, p)
    })?;
    let mut m = manifest_of(src, params, ground, tiles, Dtype::F16);
    m.manifest_version = MIXTURE_MANIFEST_VERSION;
    // Mixture shards carry segment ids (format version 4) when the source has them.
    m.shard_format_version = if !src.ids().is_empty() && src.segment(0).is_some() {
        MIXTURE_SEGMENTS_SHARD_FORMAT_VERSION
    } else {
        MIXTURE_SHARD_FORMAT_VERSION
    };
    m.mixture = Some(MixtureInfo {
        slots: mix.keep as u32,
        atoms: mix.codebook_len() as u32,
        codebook_bytes: codebook.len() as u64,
        codebook_checksum: format!("{crc:08x}"),
        codebook_sha256: Some(sha256_hex(&codebook)),
    });
    Ok((m, codebook))
}

/// Encodes `plans` in parallel, a bounded batch at a time, handing each shard to `sink` in
/// order; returns the tiles.
fn encode_in_batches(
    plans: &[TilePlan],
    sink: &mut impl FnMut(&TileInfo, Vec<u8>) -> Result<()>,
    encode: impl Fn(&TilePlan) -> Result<(TileInfo, Vec<u8>)> + Sync,
) -> Result<Vec<TileInfo>> {
    let batch = 4 * rayon::current_num_threads().max(1);
    let mut tiles = Vec::with_capacity(plans.len());
    for chunk in plans.chunks(batch) {
        let encoded: Vec<Result<(TileInfo, Vec<u8>)>> = chunk.par_iter().map(&encode).collect();
        for e in encoded {
            let (info, bytes) = e?;
            sink(&info, bytes)?;
            tiles.push(info);
        }
    }
    Ok(tiles)
}

fn check_scene_and_source(src: &impl GaussianSource, params: &PartitionParams) -> Result<()> {
    if !valid_scene_id(&params.scene_id) {
        return Err(Error::param(
            "scene_id",
            format!("{:?}", params.scene_id),
            "1-64 characters of A-Z a-z 0-9 _ - . (not starting with '.')",
        ));
    }
    let n = src.ids().len();
    if src.means().len() != n {
        return Err(Error::internal(format!(
            "{n} ids but {} means",
            src.means().len()
        )));
    }
    if src.dim() == 0 {
        return Err(Error::param("dim", 0, "an embedding width of at least 1"));
    }
    Ok(())
}

/// The manifest of a partition (`generation` 0; a store sets it on commit).
fn manifest_of(
    src: &impl GaussianSource,
    params: &PartitionParams,
    ground: GroundFrame,
    tiles: Vec<TileInfo>,
    dtype: Dtype,
) -> Manifest {
    Manifest {
        format: MANIFEST_FORMAT.into(),
        manifest_version: MANIFEST_VERSION,
        shard_format_version: if !src.ids().is_empty() && src.segment(0).is_some() {
            SEGMENTS_SHARD_FORMAT_VERSION
        } else {
            SHARD_FORMAT_VERSION
        },
        scene_id: params.scene_id.clone(),
        generation: 0,
        model: src.model().to_string(),
        dim: src.dim() as u32,
        dtype,
        ground,
        frames: slag_common::shards::Frames {
            scene_to_map: params.to_map.clone(),
            ..Default::default()
        },
        mixture: None,
        max_per_shard: params.max_per_shard as u64,
        total_gaussians: src.ids().len() as u64,
        tiles,
    }
}

/// Partitions `src` and hands each shard to `sink` in tile-id order (tiles are encoded in
/// parallel, a bounded batch at a time, so memory stays at a few shards per thread). Returns the
/// manifest (`generation` 0; a store sets it on commit).
///
/// Errors: invalid scene id or parameters ([`Error::Param`]), encoding errors, and whatever
/// `sink` returns (partitioning stops at the first error).
pub fn partition_with(
    src: &impl GaussianSource,
    params: &PartitionParams,
    mut sink: impl FnMut(&TileInfo, Vec<u8>) -> Result<()>,
) -> Result<Manifest> {
    check_scene_and_source(src, params)?;
    let ground = ground_frame(src.means(), &params.up)?;
    let plans = plan_tiles(src.means(), &ground, params.max_per_shard)?;
    let tiles = encode_in_batches(&plans, &mut sink, |p| {
        encode_tile(src, &params.scene_id, params.dtype, p)
    })?;
    Ok(manifest_of(src, params, ground, tiles, params.dtype))
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

/// What a partition stored against a naive dense tensor of the whole scene: SLAG stores only
/// the observed Gaussians (unobserved ones are dropped by the encoder), at the chosen precision,
/// in shards sized to a byte budget; the baseline is an `N × D` f32 matrix over every Gaussian
/// of the source scene (`N × 512 × 4` bytes for CLIP ViT-B).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct StorageReport {
    /// Scene id.
    pub scene_id: String,
    /// Gaussians in the source scene (`.ply` vertex count), observed or not, when the
    /// embeddings file records it (`scene_gaussians` metadata); `None` when it does not, and the
    /// dense baseline then counts the stored rows only.
    pub scene_gaussians: Option<u64>,
    /// Rows stored over all shards (observed Gaussians).
    pub rows_stored: u64,
    /// Gaussians of the scene not stored (`scene_gaussians - rows_stored`), when known.
    pub dropped: Option<u64>,
    /// Storage type of the vectors (f16 for a mixture scene: its weights and codebook).
    pub dtype: Dtype,
    /// Mixture scenes: slots per Gaussian (the shards hold codebook mixtures, and
    /// `bytes_stored` includes the codebook file).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mixture_slots: Option<u32>,
    /// Embedding width D.
    pub dim: u32,
    /// Number of shards (tiles).
    pub shards: u64,
    /// Gaussian cap per tile used (manifest `max_per_shard`).
    pub max_per_shard: u64,
    /// Largest shard, bytes.
    pub largest_shard_bytes: u64,
    /// Bytes of all shards as stored (headers, ids, means, vectors, display columns).
    pub bytes_stored: u64,
    /// Rows of the dense baseline: `scene_gaussians` when known, else `rows_stored`.
    pub dense_rows: u64,
    /// `dense_rows × D × 4` bytes.
    pub dense_f32_bytes: u64,
    /// `bytes_stored / dense_f32_bytes` (0 for an empty scene).
    pub ratio: f64,
}

/// Builds the [`StorageReport`] of a committed partition. `bytes_stored` should be measured from
/// the store (the sum of its shard lengths, [`crate::store::ShardStore::scene_bytes`]);
/// `scene_gaussians` is the source scene's Gaussian count when known (0 means unknown, as in an
/// embeddings file without the metadata).
pub fn storage_report(
    manifest: &Manifest,
    scene_gaussians: Option<u64>,
    bytes_stored: u64,
) -> StorageReport {
    let rows = manifest.total_gaussians;
    let scene_gaussians = scene_gaussians.filter(|&n| n > 0);
    let dense_rows = scene_gaussians.unwrap_or(rows);
    let dense = dense_rows
        .saturating_mul(manifest.dim as u64)
        .saturating_mul(4);
    StorageReport {
        scene_id: manifest.scene_id.clone(),
        scene_gaussians,
        rows_stored: rows,
        dropped: scene_gaussians.map(|n| n.saturating_sub(rows)),
        dtype: manifest.dtype,
        mixture_slots: manifest.mixture.as_ref().map(|m| m.slots),
        dim: manifest.dim,
        shards: manifest.tiles.len() as u64,
        max_per_shard: manifest.max_per_shard,
        largest_shard_bytes: manifest.tiles.iter().map(|t| t.bytes).max().unwrap_or(0),
        bytes_stored,
        dense_rows,
        dense_f32_bytes: dense,
        ratio: if dense > 0 {
            bytes_stored as f64 / dense as f64
        } else {
            0.0
        },
    }
}

impl std::fmt::Display for StorageReport {
    /// One line: `stored R of N scene Gaussians (K unobserved dropped) as F16 dim D in S shards
    /// (largest B bytes, cap C Gaussians): X bytes vs dense N×D f32 Y bytes = Z % of dense`.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match (self.scene_gaussians, self.dropped) {
            (Some(n), Some(d)) => write!(
                f,
                "stored {} of {} scene Gaussians ({} unobserved dropped)",
                self.rows_stored, n, d
            )?,
            _ => write!(
                f,
                "stored {} Gaussians (the source's scene count is not recorded: dense baseline \
                 over the stored rows only)",
                self.rows_stored
            )?,
        }
        let form = match self.mixture_slots {
            Some(s) => format!("a mixture of {s} slots (+ codebook)"),
            None => format!("{:?}", self.dtype),
        };
        write!(
            f,
            " as {} dim {} in {} shards (largest {} bytes, cap {} Gaussians): {} bytes vs \
             dense {}×{} f32 {} bytes = {:.2} % of dense",
            form,
            self.dim,
            self.shards,
            self.largest_shard_bytes,
            self.max_per_shard,
            self.bytes_stored,
            self.dense_rows,
            self.dim,
            self.dense_f32_bytes,
            100.0 * self.ratio,
        )?;
        if self.ratio > 0.0 && self.ratio < 1.0 {
            write!(f, " ({:.2}× smaller)", 1.0 / self.ratio)?;
        } else if self.ratio >= 1.0 {
            // Possible at f32 when nearly every Gaussian is observed: ids and means add 16 B/row.
            write!(f, " (ids and means add 16 bytes a row)")?;
        }
        Ok(())
    }
}
