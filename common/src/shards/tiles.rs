//! Ground frame, manifest and the tile R-tree used for radius selection.
//!
//! Scenes from drones and indoor captures are mostly 2.5D, so tiles are cut on a *ground plane*:
//! a right-handed orthonormal basis `(e1, e2, up)` of the world frame. A world point `x` maps to
//! ground coordinates `g = R·x` where the rows of `R` are `e1, e2, up`; `(g0, g1)` is the position
//! on the plane (scene units, metres for metric reconstructions) and `g2` the height.

use geo::{Distance, Euclidean};
use glam::{DMat3, DVec3};
use rstar::{AABB, RTree, RTreeObject};

use super::format::{Aabb, Dtype};
use crate::{Error, Result};

/// Manifest `format` field.
pub const MANIFEST_FORMAT: &str = "slag-shards-manifest";
/// Manifest schema version of dense scenes.
pub const MANIFEST_VERSION: u32 = 1;
/// Largest manifest accepted, bytes of JSON ([`Manifest::from_json`], and what a fetch reads
/// from a server before refusing): about 60,000 tiles, far more than a robot's disc holds.
pub const MAX_MANIFEST_BYTES: u64 = 32 << 20;
/// Manifest schema version of mixture scenes (with [`Manifest::mixture`]): an older reader
/// refuses it by version instead of misreading its shards.
pub const MIXTURE_MANIFEST_VERSION: u32 = 2;

/// Where the ground plane's up axis came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum UpSource {
    /// Given by the user (the partition's `up` parameter).
    User,
    /// Mean of the training cameras' up vectors (COLMAP: camera −y axis in world frame).
    Cameras,
    /// Smallest-variance principal axis of the means (sign: largest |component| positive).
    Pca,
    /// The map frame's up axis (z) taken into the scene frame by the scene-to-map transform
    /// ([`super::SceneToMap::map_up_in_scene`]), so ground discs are horizontal in the map.
    Map,
}

/// World→ground rotation recorded in the manifest.
///
/// Stored as `f32` so the JSON manifest round-trips bit-exactly (the basis is computed in f64 and
/// rounded; it is orthonormal to ~1e-7, and [`GroundFrame::to_ground`] uses the stored values, so
/// partitioning and selection agree with what clients read).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct GroundFrame {
    /// Unit up vector, world frame.
    pub up: [f32; 3],
    /// Rows `e1, e2, up` of the world→ground rotation `R` (`g = R·x`); right-handed.
    pub world_to_ground: [[f32; 3]; 3],
    /// How `up` was chosen.
    pub up_source: UpSource,
}

impl GroundFrame {
    /// Frame with the given up vector (any non-zero length; normalised here). `e1` is the world
    /// axis least aligned with `up`, projected onto the plane; `e2 = up × e1`.
    ///
    /// Errors: zero or non-finite `up` ([`Error::Param`] `up`).
    pub fn from_up(up: [f64; 3], source: UpSource) -> Result<GroundFrame> {
        let u = DVec3::from(up);
        if !u.is_finite() || u.length() < 1e-12 {
            return Err(Error::param(
                "up",
                format!("{up:?}"),
                "a non-zero finite up vector, or an axis x|y|z|-x|-y|-z",
            ));
        }
        let u = u.normalize();
        let a = u.abs();
        let reference = if a.x <= a.y && a.x <= a.z {
            DVec3::X
        } else if a.y <= a.z {
            DVec3::Y
        } else {
            DVec3::Z
        };
        let e1 = (reference - u * reference.dot(u)).normalize();
        let e2 = u.cross(e1);
        Ok(GroundFrame {
            up: u.as_vec3().to_array(),
            world_to_ground: [
                e1.as_vec3().to_array(),
                e2.as_vec3().to_array(),
                u.as_vec3().to_array(),
            ],
            up_source: source,
        })
    }

    /// Parses `x|y|z|-x|-y|-z` (also `+y`) as a user up axis.
    ///
    /// Errors: any other string ([`Error::Param`] `up`).
    pub fn from_axis_name(name: &str) -> Result<GroundFrame> {
        let (sign, axis) = match name.trim().strip_prefix('-') {
            Some(rest) => (-1.0, rest),
            None => (1.0, name.trim().trim_start_matches('+')),
        };
        let v = match axis.to_ascii_lowercase().as_str() {
            "x" => [sign, 0.0, 0.0],
            "y" => [0.0, sign, 0.0],
            "z" => [0.0, 0.0, sign],
            _ => {
                return Err(Error::param(
                    "up",
                    format!("{name:?}"),
                    "one of x, y, z, -x, -y, -z",
                ));
            }
        };
        GroundFrame::from_up(v, UpSource::User)
    }

    /// Up = normalised mean of the cameras' up vectors (world frame). For COLMAP cameras pass
    /// the camera −y axis in world frame, `-(R_wc row 1)` of each world-to-camera rotation.
    ///
    /// Errors: empty list or vectors that cancel out ([`Error::Param`] `up`: give the axis).
    pub fn from_camera_ups(ups: &[[f64; 3]]) -> Result<GroundFrame> {
        let sum: DVec3 = ups
            .iter()
            .map(|&u| DVec3::from(u).normalize_or_zero())
            .sum();
        if ups.is_empty() || sum.length() < 1e-6 * ups.len() as f64 {
            return Err(Error::param(
                "up",
                format!("the mean of {} camera up vectors", ups.len()),
                "an up axis x|y|z|-x|-y|-z: the camera up vectors are missing or cancel out",
            ));
        }
        GroundFrame::from_up(sum.to_array(), UpSource::Cameras)
    }

    /// Up = eigenvector of the smallest eigenvalue of the means' covariance (2.5D scenes are
    /// flattest along up). Sign: the largest-magnitude component is made positive (PCA cannot
    /// tell up from down; tiling does not depend on it).
    ///
    /// Errors: fewer than 3 means ([`Error::Param`] `up`: give the axis), non-finite values
    /// ([`Error::Invalid`]).
    pub fn from_pca(means: &[[f32; 3]]) -> Result<GroundFrame> {
        if means.len() < 3 {
            return Err(Error::param(
                "up",
                format!("estimated from {} Gaussians", means.len()),
                "an up axis x|y|z|-x|-y|-z: estimating it needs at least 3 Gaussians",
            ));
        }
        let n = means.len() as f64;
        let mean: DVec3 = means
            .iter()
            .map(|m| DVec3::new(m[0] as f64, m[1] as f64, m[2] as f64))
            .sum::<DVec3>()
            / n;
        let mut c = [[0.0f64; 3]; 3];
        for m in means {
            let d = DVec3::new(m[0] as f64, m[1] as f64, m[2] as f64) - mean;
            let d = d.to_array();
            for i in 0..3 {
                for j in 0..3 {
                    c[i][j] += d[i] * d[j] / n;
                }
            }
        }
        if c.iter().flatten().any(|x| !x.is_finite()) {
            return Err(Error::Invalid(
                "non-finite means; cannot estimate the up axis".into(),
            ));
        }
        let v = smallest_eigenvector(DMat3::from_cols_array_2d(&c));
        let a = v.abs();
        let big = if a.x >= a.y && a.x >= a.z {
            v.x
        } else if a.y >= a.z {
            v.y
        } else {
            v.z
        };
        let v = if big < 0.0 { -v } else { v };
        GroundFrame::from_up(v.to_array(), UpSource::Pca)
    }

    /// Ground coordinates `(g0, g1, height)` of a world point.
    pub fn to_ground(&self, p: [f32; 3]) -> [f64; 3] {
        let x = DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64);
        let r = self
            .world_to_ground
            .map(|row| DVec3::new(row[0] as f64, row[1] as f64, row[2] as f64));
        [r[0].dot(x), r[1].dot(x), r[2].dot(x)]
    }
}

/// Eigenvector of the smallest eigenvalue of a symmetric 3×3 matrix ([`super::eigen`]).
fn smallest_eigenvector(m: DMat3) -> DVec3 {
    let (w, v) = super::eigen::jacobi_eigen(m.to_cols_array_2d());
    let i = (0..3).min_by(|&i, &j| w[i].total_cmp(&w[j])).unwrap_or(0);
    DVec3::new(v[0][i], v[1][i], v[2][i]).normalize_or_zero()
}

/// One tile (= one shard) in the manifest.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TileInfo {
    /// Tile id; also the shard id in URLs and store keys.
    pub id: u64,
    /// Footprint on the ground plane: closed polygon ring `[[g0, g1], …]` (first = last), ground
    /// coordinates, scene units. Partition writes the tight rectangle of the tile's means, rounded
    /// outward to `f32` (exact JSON round trip).
    pub footprint: Vec<[f32; 2]>,
    /// Box of the tile's means, world frame.
    pub aabb: Aabb,
    /// Number of Gaussians in the shard.
    pub count: u64,
    /// Shard size in bytes.
    pub bytes: u64,
    /// CRC-32 of the whole shard ([`super::shard_checksum`]), 8 lowercase hex digits.
    pub checksum: String,
    /// SHA-256 of the whole shard, 64 lowercase hex digits ([`super::signature::sha256_hex`]):
    /// what a signed manifest vouches for. Absent in manifests written before it existed (and
    /// not written then): readers that predate it ignore it; a fetch with a trusted key refuses
    /// a signed manifest without it ([`super::signature::check_hashes`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sha256: Option<String>,
}

impl TileInfo {
    /// The footprint as a `geo` polygon.
    pub fn footprint_polygon(&self) -> geo::Polygon<f64> {
        geo::Polygon::new(
            geo::LineString::from(
                self.footprint
                    .iter()
                    .map(|p| (p[0] as f64, p[1] as f64))
                    .collect::<Vec<_>>(),
            ),
            vec![],
        )
    }
    /// A closed rectangle ring from ground-plane bounds, rounded outward to `f32`.
    pub fn rect_ring(min: [f64; 2], max: [f64; 2]) -> Vec<[f32; 2]> {
        let min = min.map(f32_down);
        let max = max.map(f32_up);
        vec![
            [min[0], min[1]],
            [max[0], min[1]],
            [max[0], max[1]],
            [min[0], max[1]],
            [min[0], min[1]],
        ]
    }
}

/// The codebook of a mixture scene ([`super::mixture`]), listed in its manifest like a shard.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct MixtureInfo {
    /// Slots per Gaussian S in every shard.
    pub slots: u32,
    /// Codebook rows A.
    pub atoms: u32,
    /// Size of the codebook file in bytes.
    pub codebook_bytes: u64,
    /// CRC-32 of the whole codebook file ([`super::shard_checksum`]), 8 lowercase hex digits;
    /// every shard's header names the same value.
    pub codebook_checksum: String,
    /// SHA-256 of the whole codebook file, 64 lowercase hex digits, as
    /// [`TileInfo::sha256`] (absent in manifests written before it existed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub codebook_sha256: Option<String>,
}

/// The scene's shard catalogue (`manifest.json`, `GET /v1/scenes/{scene}/manifest`).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Manifest {
    /// Always [`MANIFEST_FORMAT`].
    pub format: String,
    /// Manifest schema version ([`MANIFEST_VERSION`]).
    pub manifest_version: u32,
    /// Shard byte-layout version ([`super::SHARD_FORMAT_VERSION`]; dense shards with segment
    /// ids [`super::SEGMENTS_SHARD_FORMAT_VERSION`]; mixture shards
    /// [`super::MIXTURE_SHARD_FORMAT_VERSION`], with segment ids
    /// [`super::MIXTURE_SEGMENTS_SHARD_FORMAT_VERSION`]).
    pub shard_format_version: u16,
    /// Scene id (`[A-Za-z0-9_.-]`, 1..=64, not starting with `.`).
    pub scene_id: String,
    /// Partition generation, incremented on each store commit (0 before commit).
    pub generation: u64,
    /// Embedding model id (the CLIP pair id, [`crate::embeddings::Embeddings::model`]); the edge
    /// refuses a text tower of another model.
    pub model: String,
    /// Embedding width D.
    pub dim: u32,
    /// Storage type of the vectors in every shard.
    pub dtype: Dtype,
    /// Ground plane used for tiling and selection.
    pub ground: GroundFrame,
    /// Which frame the coordinates above and below are in (always the scene's), and the
    /// scene-to-map transform when the partition was given one. Absent in manifests written
    /// before it existed: no map frame (fetch radii and answers in scene units).
    #[serde(default)]
    pub frames: super::Frames,
    /// Mixture scenes only ([`MIXTURE_MANIFEST_VERSION`], shard format version 2): slots per
    /// Gaussian and the codebook file. Absent (and not written) for dense scenes, whose
    /// manifests are byte-identical to version 1's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mixture: Option<MixtureInfo>,
    /// `--max-per-shard` used.
    pub max_per_shard: u64,
    /// Gaussians over all tiles.
    pub total_gaussians: u64,
    /// Tiles, ascending id.
    pub tiles: Vec<TileInfo>,
}

impl Manifest {
    /// Parses and checks a manifest: size, format string, version, mixture section, and every
    /// declared byte size against what the shard format allows ([`Manifest::check_sizes`]).
    ///
    /// Errors: [`Error::Limit`] [`crate::Resource::ManifestBytes`] for more than
    /// [`MAX_MANIFEST_BYTES`], [`Error::Format`] naming `origin` otherwise.
    pub fn from_json(bytes: &[u8], origin: &str) -> Result<Manifest> {
        if bytes.len() as u64 > MAX_MANIFEST_BYTES {
            return Err(manifest_too_large(bytes.len() as u64, origin));
        }
        let m: Manifest = serde_json::from_slice(bytes)
            .map_err(|e| Error::format(origin, format!("not a slag shard manifest: {e}")))?;
        if m.format != MANIFEST_FORMAT
            || (m.manifest_version != MANIFEST_VERSION
                && m.manifest_version != MIXTURE_MANIFEST_VERSION)
        {
            return Err(Error::format(
                origin,
                format!(
                    "manifest {} v{}, expected {MANIFEST_FORMAT} v{MANIFEST_VERSION} or \
                     v{MIXTURE_MANIFEST_VERSION}; upgrade slag or re-partition",
                    m.format, m.manifest_version
                ),
            ));
        }
        let mixture = m.manifest_version == MIXTURE_MANIFEST_VERSION;
        // Dense shards are version 1, or 3 when they carry segment ids; mixture shards 2, or 4.
        let shard_version_ok = if mixture {
            super::is_mixture_version(m.shard_format_version)
        } else {
            m.shard_format_version == super::SHARD_FORMAT_VERSION
                || m.shard_format_version == super::SEGMENTS_SHARD_FORMAT_VERSION
        };
        if mixture != m.mixture.is_some() || !shard_version_ok {
            return Err(Error::format(
                origin,
                format!(
                    "manifest v{} with shard format {} {} a mixture section; v{MANIFEST_VERSION} \
                     (shard format 1, or 3 with segments) describes dense shards, v{MIXTURE_MANIFEST_VERSION} (shard \
                     format 2, or 4 with segments) mixture shards and their codebook: re-partition",
                    m.manifest_version,
                    m.shard_format_version,
                    if m.mixture.is_some() {
                        "and"
                    } else {
                        "without"
                    }
                ),
            ));
        }
        if let Some(x) = &m.mixture {
            let hex = x.codebook_checksum.len() == 8
                && u32::from_str_radix(&x.codebook_checksum, 16).is_ok();
            if !hex || x.slots == 0 || x.slots > super::format::MAX_SLOTS || m.dtype != Dtype::F16 {
                return Err(Error::format(
                    origin,
                    format!(
                        "mixture section (slots {}, codebook checksum {:?}, dtype {:?}) is \
                         invalid: slots 1..={}, 8 hex digits, f16 weights",
                        x.slots,
                        x.codebook_checksum,
                        m.dtype,
                        super::format::MAX_SLOTS
                    ),
                ));
            }
        }
        m.check_sizes(origin)?;
        m.check_set(origin)?;
        Ok(m)
    }

    /// Checks that the tiles form a set that adds up: no tile id listed twice (a store names a
    /// shard file by tile id and checksum, so two entries of one id would be one file counted
    /// twice, or two files for one tile), no tile with the id of a mixture scene's codebook
    /// ([`super::CODEBOOK_TILE`], whose file and partial download it would share), and Gaussian
    /// counts whose sum is `total_gaussians`. Gaussian ids are inside the shards, not the
    /// manifest: a loader checks that no id is in two shards.
    ///
    /// Errors: [`crate::Error::Shard`] [`super::ShardError::ManifestNotASet`] naming `origin`,
    /// the tile and the rule.
    pub fn check_set(&self, origin: &str) -> Result<()> {
        let refuse = |what: String| {
            Err(Error::Shard(super::ShardError::ManifestNotASet(format!(
                "{origin}: {what}"
            ))))
        };
        let mut ids = std::collections::HashSet::with_capacity(self.tiles.len());
        let mut sum = 0u64;
        for t in &self.tiles {
            if !ids.insert(t.id) {
                return refuse(format!(
                    "tile {} is listed twice (a shard would be stored and counted twice)",
                    t.id
                ));
            }
            if self.mixture.is_some() && t.id == super::CODEBOOK_TILE {
                return refuse(format!(
                    "tile {} has the id of the scene's codebook file",
                    t.id
                ));
            }
            sum = sum.saturating_add(t.count);
        }
        if sum != self.total_gaussians {
            return refuse(format!(
                "its tiles hold {sum} Gaussians, but total_gaussians says {}",
                self.total_gaussians
            ));
        }
        Ok(())
    }

    /// Checks every declared size against the shard format ([`super::format`] module doc), so
    /// that nothing is downloaded on the word of a manifest that cannot be right: the embedding
    /// width is in 1..=[`super::format::MAX_DIM`], each tile's Gaussian count fits the header's
    /// 32-bit field and its byte size is one the format allows for that count, width, dtype (or
    /// mixture slots) and the manifest's scene and model ids: any header length from the
    /// smallest for those ids up to the decoders' limit (1 MiB, a multiple of 8), plus the
    /// payload of one of the 16 combinations of display sections. A mixture scene's codebook is
    /// checked the same way (an f16 dense shard of `atoms` rows).
    ///
    /// Errors: [`Error::Format`] naming `origin` and the first tile that disagrees.
    pub fn check_sizes(&self, origin: &str) -> Result<()> {
        use super::format::{MAX_DIM, expected_payload, header_len_for, payload_with_rows};
        if self.dim == 0 || self.dim > MAX_DIM {
            return Err(damaged_manifest(
                origin,
                format!("embedding dim {} outside 1..={MAX_DIM}", self.dim),
            ));
        }
        let d = self.dim as u64;
        let (scene, model) = (self.scene_id.len(), self.model.len());
        let dense_header = header_len_for(scene, model, false) as u64;
        let Some(x) = &self.mixture else {
            for t in &self.tiles {
                let (what, n) = (
                    format!("tile {} ({:?}, dim {d})", t.id, self.dtype),
                    t.count,
                );
                let payload = |f: u8| expected_payload(self.dtype, f, n, d);
                check_declared_size(origin, what, (t.bytes, n), dense_header, &payload)?;
            }
            return Ok(());
        };
        let header = header_len_for(scene, model, true) as u64;
        let s = x.slots as u64;
        for t in &self.tiles {
            let (what, n) = (format!("tile {} (mixture, {s} slots)", t.id), t.count);
            let payload = |f: u8| payload_with_rows(f, n, 6 * n * s);
            check_declared_size(origin, what, (t.bytes, n), header, &payload)?;
        }
        let a = x.atoms as u64;
        let what = format!("the codebook ({a} rows of dim {d})");
        let payload = |f: u8| expected_payload(Dtype::F16, f, a, d);
        check_declared_size(origin, what, (x.codebook_bytes, a), dense_header, &payload)
    }

    /// R-tree over this manifest's tile footprints.
    pub fn tile_index(&self) -> TileIndex {
        TileIndex::new(&self.tiles)
    }
    /// Pretty JSON.
    pub fn to_json(&self) -> Vec<u8> {
        serde_json::to_vec_pretty(self).unwrap_or_default()
    }
}

/// The error of [`Manifest::check_sizes`]: `message` about the manifest at `origin`, and what
/// to do about it.
fn damaged_manifest(origin: &str, message: String) -> Error {
    Error::format(
        origin,
        format!("{message}; the manifest is damaged or not from a slag partitioner: re-partition"),
    )
}

/// One declared size of [`Manifest::check_sizes`]: `what` (a tile or the codebook) declares
/// `bytes` bytes for `count` Gaussians (or codebook rows); a shard of them is a header of
/// `min_header` to [`super::format::MAX_HEADER_LEN`] bytes (a multiple of 8) plus `payload(flags)`
/// bytes for one of the combinations of display sections.
///
/// Errors: [`Error::Format`] naming `origin` and `what`, for a count past the header's 32-bit
/// field or a length no such shard has (the message says how the lengths are made, never a
/// range that holds `bytes`).
fn check_declared_size(
    origin: &str,
    what: String,
    (bytes, count): (u64, u64),
    min_header: u64,
    payload: &dyn Fn(u8) -> u64,
) -> Result<()> {
    if count > u32::MAX as u64 {
        return Err(damaged_manifest(
            origin,
            format!("{what} declares {count} Gaussians, more than a shard's 32-bit count"),
        ));
    }
    if shard_len_allowed(bytes, min_header, payload) {
        return Ok(());
    }
    let mut payloads: Vec<u64> = (0..=super::format::KNOWN_FLAGS).map(payload).collect();
    payloads.sort_unstable();
    payloads.dedup();
    let payloads: Vec<String> = payloads.iter().map(u64::to_string).collect();
    Err(damaged_manifest(
        origin,
        format!(
            "{what} declares {bytes} bytes, a length no shard of {count} Gaussians of this \
             scene has: a shard is a header of {min_header} to {} bytes (a multiple of 8) \
             plus a payload of {} bytes",
            super::format::MAX_HEADER_LEN,
            payloads.join(" or ")
        ),
    ))
}

/// True when `bytes` = a header length in `min_header..=MAX_HEADER_LEN` (a multiple of 8) plus
/// `payload(flags)` for some combination of the display-section flags.
fn shard_len_allowed(bytes: u64, min_header: u64, payload: &dyn Fn(u8) -> u64) -> bool {
    (0..=super::format::KNOWN_FLAGS).any(|flags| {
        bytes.checked_sub(payload(flags)).is_some_and(|h| {
            h >= min_header && h <= super::format::MAX_HEADER_LEN as u64 && h.is_multiple_of(8)
        })
    })
}

/// The refusal of a manifest of more than [`MAX_MANIFEST_BYTES`] (`len`: its size, or at least
/// what was read of it, from `origin`): [`Error::Limit`] [`crate::Resource::ManifestBytes`].
pub fn manifest_too_large(len: u64, origin: &str) -> Error {
    Error::limit(
        crate::Resource::ManifestBytes,
        format!("{len} bytes of manifest from {origin}"),
        format!("{MAX_MANIFEST_BYTES} bytes"),
    )
}

/// Largest `f32` ≤ `v`.
fn f32_down(v: f64) -> f32 {
    let f = v as f32;
    if (f as f64) > v { f.next_down() } else { f }
}

/// Smallest `f32` ≥ `v`.
fn f32_up(v: f64) -> f32 {
    let f = v as f32;
    if (f as f64) < v { f.next_up() } else { f }
}

/// R-tree entry: a tile's footprint envelope.
#[derive(Debug, Clone)]
struct Entry {
    id: u64,
    polygon: geo::Polygon<f64>,
    envelope: AABB<[f64; 2]>,
}

impl RTreeObject for Entry {
    type Envelope = AABB<[f64; 2]>;
    fn envelope(&self) -> Self::Envelope {
        self.envelope
    }
}

/// R-tree (`rstar`) over tile footprints on the ground plane.
#[derive(Debug, Clone)]
pub struct TileIndex {
    tree: RTree<Entry>,
}

impl TileIndex {
    /// Builds the index from manifest tiles. Tiles with an empty or non-finite footprint are
    /// skipped (they can never intersect a disc).
    pub fn new(tiles: &[TileInfo]) -> TileIndex {
        let entries = tiles
            .iter()
            .filter(|t| {
                !t.footprint.is_empty() && t.footprint.iter().flatten().all(|x| x.is_finite())
            })
            .map(|t| {
                let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
                for p in &t.footprint {
                    for a in 0..2 {
                        lo[a] = lo[a].min(p[a] as f64);
                        hi[a] = hi[a].max(p[a] as f64);
                    }
                }
                Entry {
                    id: t.id,
                    polygon: t.footprint_polygon(),
                    envelope: AABB::from_corners(lo, hi),
                }
            })
            .collect();
        TileIndex {
            tree: RTree::bulk_load(entries),
        }
    }

    /// Ids (ascending) of exactly the tiles whose footprint intersects the closed disc of
    /// `radius` around `center` (ground coordinates `(g0, g1)`, scene units; see
    /// [`GroundFrame::to_ground`]). A negative or NaN radius selects nothing.
    pub fn select_tiles(&self, center: [f64; 2], radius: f64) -> Vec<u64> {
        if radius.is_nan() || radius < 0.0 || !center.iter().all(|c| c.is_finite()) {
            return Vec::new();
        }
        let query = AABB::from_corners(
            [center[0] - radius, center[1] - radius],
            [center[0] + radius, center[1] + radius],
        );
        let pt = geo::Point::new(center[0], center[1]);
        let mut ids: Vec<u64> = self
            .tree
            .locate_in_envelope_intersecting(&query)
            .filter(|e| Euclidean.distance(&pt, &e.polygon) <= radius)
            .map(|e| e.id)
            .collect();
        ids.sort_unstable();
        ids
    }

    /// Number of indexed tiles.
    pub fn len(&self) -> usize {
        self.tree.size()
    }
    /// True when no tile is indexed.
    pub fn is_empty(&self) -> bool {
        self.tree.size() == 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Independent reference: distance from a point to an axis-aligned rectangle by clamping.
    fn rect_distance(c: [f64; 2], lo: [f64; 2], hi: [f64; 2]) -> f64 {
        let dx = (lo[0] - c[0]).max(0.0).max(c[0] - hi[0]);
        let dy = (lo[1] - c[1]).max(0.0).max(c[1] - hi[1]);
        (dx * dx + dy * dy).sqrt()
    }

    fn tile(id: u64, lo: [f64; 2], hi: [f64; 2]) -> TileInfo {
        TileInfo {
            id,
            footprint: TileInfo::rect_ring(lo, hi),
            aabb: Aabb::default(),
            count: 1,
            bytes: 1,
            checksum: String::new(),
            sha256: None,
        }
    }

    proptest! {
        #[test]
        fn radius_selection_matches_brute_force(
            rects in proptest::collection::vec((-100f32..100.0, -100f32..100.0, 0f32..20.0, 0f32..20.0), 0..60),
            cx in -130f64..130.0, cy in -130f64..130.0, r in 0f64..60.0,
        ) {
            let tiles: Vec<TileInfo> = rects.iter().enumerate()
                .map(|(i, &(x, y, w, h))| tile(i as u64, [x as f64, y as f64], [(x + w) as f64, (y + h) as f64])).collect();
            let idx = TileIndex::new(&tiles);
            let got = idx.select_tiles([cx, cy], r);
            let want: Vec<u64> = rects.iter().enumerate()
                .filter(|&(_, &(x, y, w, h))| rect_distance([cx, cy], [x as f64, y as f64], [(x + w) as f64, (y + h) as f64]) <= r)
                .map(|(i, _)| i as u64).collect();
            prop_assert_eq!(got, want);
        }
    }

    /// A manifest of scene `s`, model `m`, one tile of one 4-d f16 Gaussian (or mixture row of
    /// the section's slots), every byte size the one the writers give.
    fn manifest(mixture: Option<MixtureInfo>) -> Manifest {
        use crate::shards::format::{expected_payload, header_len_for, payload_with_rows};
        let mixture = mixture.map(|m| MixtureInfo {
            codebook_bytes: header_len_for(1, 1, false) as u64
                + expected_payload(Dtype::F16, 0, m.atoms as u64, 4),
            ..m
        });
        let mut tile = tile(0, [0.0, 0.0], [1.0, 1.0]);
        tile.bytes = match &mixture {
            None => header_len_for(1, 1, false) as u64 + expected_payload(Dtype::F16, 0, 1, 4),
            Some(m) => {
                header_len_for(1, 1, true) as u64 + payload_with_rows(0, 1, 6 * m.slots as u64)
            }
        };
        Manifest {
            format: MANIFEST_FORMAT.into(),
            manifest_version: if mixture.is_some() {
                MIXTURE_MANIFEST_VERSION
            } else {
                MANIFEST_VERSION
            },
            shard_format_version: if mixture.is_some() { 2 } else { 1 },
            scene_id: "s".into(),
            generation: 1,
            model: "m".into(),
            dim: 4,
            dtype: Dtype::F16,
            ground: GroundFrame::from_up([0.0, 0.0, 1.0], UpSource::User).expect("frame"),
            frames: Default::default(),
            mixture,
            max_per_shard: 10,
            total_gaussians: 1,
            tiles: vec![tile],
        }
    }

    #[test]
    fn a_manifest_whose_tiles_are_not_a_set_that_adds_up_is_refused() {
        let not_a_set = |m: &Manifest| match Manifest::from_json(&m.to_json(), "t") {
            Err(Error::Shard(crate::shards::ShardError::ManifestNotASet(why))) => why,
            other => panic!("{:?}", other.map(|_| ())),
        };
        let mixture = Some(MixtureInfo {
            slots: 8,
            atoms: 300,
            codebook_bytes: 0,
            codebook_checksum: "0badf00d".into(),
            codebook_sha256: None,
        });
        for m in [manifest(None), manifest(mixture)] {
            Manifest::from_json(&m.to_json(), "t").expect("a set");
            // The same tile twice (one shard file, counted twice), with the total adjusted.
            let mut twice = m.clone();
            twice.tiles.push(m.tiles[0].clone());
            twice.total_gaussians = 2;
            assert!(not_a_set(&twice).contains("tile 0 is listed twice"));
            // Another checksum for the same id: two files for one tile.
            twice.tiles[1].checksum = "00000001".into();
            assert!(not_a_set(&twice).contains("listed twice"));
            // Counts that do not add up.
            let mut total = m.clone();
            total.total_gaussians = 2;
            let why = not_a_set(&total);
            assert!(
                why.contains("hold 1 Gaussians") && why.contains("says 2"),
                "{why}"
            );
            // Two distinct tiles whose counts add up pass.
            let mut two = m.clone();
            let mut t1 = m.tiles[0].clone();
            t1.id = 1;
            two.tiles.push(t1);
            two.total_gaussians = 2;
            Manifest::from_json(&two.to_json(), "t").expect("two tiles");
            // A tile with the codebook's id, in a mixture scene.
            if m.mixture.is_some() {
                two.tiles[1].id = crate::shards::CODEBOOK_TILE;
                assert!(not_a_set(&two).contains("codebook"));
            }
        }
        let e = Error::Shard(crate::shards::ShardError::ManifestNotASet("x".into()));
        assert!(e.to_string().contains("re-partition"), "{e}");
    }

    #[test]
    fn declared_sizes_must_be_ones_the_shard_format_allows() {
        for m in [
            manifest(None),
            manifest(Some(MixtureInfo {
                slots: 8,
                atoms: 300,
                codebook_bytes: 0,
                codebook_checksum: "0badf00d".into(),
                codebook_sha256: None,
            })),
        ] {
            Manifest::from_json(&m.to_json(), "t").expect("the writers' sizes");
            // Display sections (here scales + opacities: 16 bytes a row) and a padded header
            // are allowed; one byte more or less, a huge size or count is not.
            let mut with_display = m.clone();
            with_display.tiles[0].bytes += 16;
            let mut padded = m.clone();
            padded.tiles[0].bytes += 64;
            for ok in [with_display, padded] {
                Manifest::from_json(&ok.to_json(), "t").expect("allowed");
            }
            let mut cases = Vec::new();
            for bytes in [
                m.tiles[0].bytes + 1,
                m.tiles[0].bytes - 1,
                1_000_000_000_000,
                0,
            ] {
                let mut b = m.clone();
                b.tiles[0].bytes = bytes;
                cases.push(b);
            }
            let mut count = m.clone();
            count.tiles[0].count = 1 << 40;
            cases.push(count);
            let mut dim = m.clone();
            dim.dim = 0;
            cases.push(dim);
            if let Some(x) = &m.mixture {
                let mut cb = m.clone();
                cb.mixture.as_mut().expect("m").codebook_bytes = x.codebook_bytes * 1000;
                cases.push(cb);
            }
            for b in cases {
                let e = Manifest::from_json(&b.to_json(), "t").expect_err("refused");
                let msg = e.to_string();
                assert!(matches!(e, Error::Format { .. }), "{msg}");
                assert!(msg.contains("re-partition"), "{msg}");
            }
        }
        let huge = vec![b' '; MAX_MANIFEST_BYTES as usize + 1];
        let e = Manifest::from_json(&huge, "t").expect_err("too large");
        assert!(
            matches!(
                e,
                Error::Limit {
                    resource: crate::Resource::ManifestBytes,
                    ..
                }
            ),
            "{e}"
        );
    }

    #[test]
    fn mixture_manifests_are_version_2_and_dense_ones_unchanged() {
        let dense = manifest(None);
        let json = String::from_utf8(dense.to_json()).expect("utf8");
        assert!(!json.contains("mixture"), "{json}");
        assert_eq!(
            Manifest::from_json(json.as_bytes(), "t").expect("v1"),
            dense
        );
        let info = MixtureInfo {
            slots: 8,
            atoms: 300,
            codebook_bytes: 0,
            codebook_checksum: "0badf00d".into(),
            codebook_sha256: None,
        };
        let mix = manifest(Some(info));
        let back = Manifest::from_json(&mix.to_json(), "t").expect("v2");
        assert_eq!(back.mixture, mix.mixture);
        // Version and section must agree, the checksum must be hex, slots in range.
        let mut v1_with_section = mix.clone();
        v1_with_section.manifest_version = MANIFEST_VERSION;
        let mut v2_without = dense.clone();
        v2_without.manifest_version = MIXTURE_MANIFEST_VERSION;
        let mut bad_sum = mix.clone();
        bad_sum.mixture.as_mut().expect("m").codebook_checksum = "xyz".into();
        let mut no_slots = mix.clone();
        no_slots.mixture.as_mut().expect("m").slots = 0;
        let mut v3 = mix;
        v3.manifest_version = 3;
        for m in [v1_with_section, v2_without, bad_sum, no_slots, v3] {
            let r = Manifest::from_json(&m.to_json(), "t");
            assert!(matches!(r, Err(Error::Format { .. })), "{r:?}");
        }
    }

    #[test]
    fn disc_touching_a_corner_counts_and_missing_it_does_not() {
        let idx = TileIndex::new(&[tile(4, [0.0, 0.0], [1.0, 1.0])]);
        // Corner (1,1) at distance 5 from (4,5).
        assert_eq!(idx.select_tiles([4.0, 5.0], 5.0), vec![4]);
        assert!(idx.select_tiles([4.0, 5.0], 4.999).is_empty());
        // Disc inside the tile.
        assert_eq!(idx.select_tiles([0.5, 0.5], 0.01), vec![4]);
        assert!(idx.select_tiles([0.5, 0.5], -1.0).is_empty());
    }

    #[test]
    fn ground_frames_are_orthonormal_right_handed() {
        for up in [
            [0.0, 0.0, 1.0],
            [0.0, -1.0, 0.0],
            [0.3, 0.2, -0.9],
            [1.0, 1.0, 1.0],
        ] {
            let g = GroundFrame::from_up(up, UpSource::User).expect("frame");
            let r = g.world_to_ground.map(|v| glam::Vec3::from(v).as_dvec3());
            for i in 0..3 {
                assert!((r[i].length() - 1.0).abs() < 1e-6);
                for j in 0..i {
                    assert!(r[i].dot(r[j]).abs() < 1e-6);
                }
            }
            assert!((r[0].cross(r[1]) - r[2]).length() < 1e-6);
            assert!((r[2] - DVec3::from(up).normalize()).length() < 1e-6);
        }
        assert!(GroundFrame::from_up([0.0; 3], UpSource::User).is_err());
        assert_eq!(
            GroundFrame::from_axis_name("-y").expect("axis").up,
            [0.0, -1.0, 0.0]
        );
        assert!(GroundFrame::from_axis_name("w").is_err());
    }

    #[test]
    fn pca_finds_the_flat_axis_of_a_tilted_plane() {
        // Points on a plane with normal n, spread ±50 in-plane and ±0.5 off-plane.
        let n = DVec3::new(0.2, -0.9, 0.3).normalize();
        let a = n.any_orthonormal_vector();
        let b = n.cross(a);
        let mut pts = Vec::new();
        let mut rng = crate::rng::SplitMix64::new(12345);
        let mut rnd = || rng.range(-0.5, 0.5);
        for _ in 0..2000 {
            let p = a * 100.0 * rnd() + b * 100.0 * rnd() + n * rnd() + DVec3::new(3.0, 4.0, 5.0);
            pts.push([p.x as f32, p.y as f32, p.z as f32]);
        }
        let g = GroundFrame::from_pca(&pts).expect("pca");
        assert!(
            glam::Vec3::from(g.up).as_dvec3().dot(n).abs() > 0.999,
            "{:?} vs {n:?}",
            g.up
        );
        assert_eq!(g.up_source, UpSource::Pca);
        let cams =
            GroundFrame::from_camera_ups(&[[0.1, 1.0, 0.0], [-0.1, 1.0, 0.0]]).expect("cams");
        assert!((glam::Vec3::from(cams.up).as_dvec3() - DVec3::Y).length() < 1e-7);
        assert!(GroundFrame::from_camera_ups(&[]).is_err());
    }
}
