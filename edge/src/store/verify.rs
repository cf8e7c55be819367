//! What makes stored bytes a shard (or codebook) of a manifest: length, CRC-32s and a full decode
//! whose header agrees with the manifest entry. Every commit and every load runs these checks.

use slag_common::shards::{
    CODEBOOK_TILE, Codebook, Dtype, Manifest, MixtureShard, ShardHeader, StoredShard, TileInfo,
    decode_codebook, decode_mixture_shard, decode_shard_stored, shard_checksum,
};
use slag_common::{Error, Result};

use super::parse_checksum;

/// File-name extension of a stored codebook.
pub const CODEBOOK_EXTENSION: &str = "codebook";

/// The manifest entry of a mixture scene's codebook as a pseudo tile ([`CODEBOOK_TILE`], its
/// bytes and checksum, no footprint), so downloads and partial files treat it like a shard;
/// `None` for a dense scene.
pub fn codebook_tile(manifest: &Manifest) -> Option<TileInfo> {
    manifest.mixture.as_ref().map(|m| TileInfo {
        id: CODEBOOK_TILE,
        footprint: Vec::new(),
        aabb: Default::default(),
        count: m.atoms as u64,
        bytes: m.codebook_bytes,
        checksum: m.codebook_checksum.clone(),
        sha256: m.codebook_sha256.clone(),
    })
}

/// Checks downloaded codebook bytes against a mixture manifest: length, CRC-32, and a decode
/// ([`decode_codebook`]) whose scene, model, width and row count match.
///
/// Errors: [`Error::Format`] naming what differs (truncated, corrupted, another scene's), or
/// [`Error::Param`] `scene` for a dense manifest (it has no codebook).
pub fn verify_codebook(manifest: &Manifest, bytes: &[u8]) -> Result<Codebook> {
    let Some(info) = &manifest.mixture else {
        return Err(Error::param(
            "scene",
            format!("{:?}", manifest.scene_id),
            "a mixture scene: this one is dense and has no codebook",
        ));
    };
    let origin = format!("codebook of scene {}", manifest.scene_id);
    if bytes.len() as u64 != info.codebook_bytes {
        return Err(Error::format(
            &origin,
            format!(
                "{} bytes, the manifest says {}; fetch again",
                bytes.len(),
                info.codebook_bytes
            ),
        ));
    }
    let got = format!("{:08x}", shard_checksum(bytes));
    if got != info.codebook_checksum {
        return Err(Error::format(
            &origin,
            format!(
                "checksum {got}, the manifest says {}; the codebook is corrupted, fetch again",
                info.codebook_checksum
            ),
        ));
    }
    let cb = decode_codebook(bytes).map_err(|e| Error::format(&origin, e.to_string()))?;
    if cb.scene_id != manifest.scene_id
        || cb.model != manifest.model
        || cb.dim != manifest.dim as usize
        || cb.len() != info.atoms as usize
    {
        return Err(Error::format(
            &origin,
            format!(
                "header (scene {}, model {}, dim {}, {} rows) disagrees with the manifest (scene \
                 {}, model {}, dim {}, {} rows)",
                cb.scene_id,
                cb.model,
                cb.dim,
                cb.len(),
                manifest.scene_id,
                manifest.model,
                manifest.dim,
                info.atoms
            ),
        ));
    }
    Ok(cb)
}

/// [`verify_shard`] for a mixture scene's shard: length, CRC-32, a full decode
/// ([`decode_mixture_shard`]) whose header names the same scene, tile, model, dim and count, the
/// manifest's slot count and its codebook's checksum.
///
/// Errors: [`Error::Format`] naming the tile and what differs, [`Error::Unsupported`] for a shard
/// of a format version this slag does not read.
pub fn verify_mixture_shard(
    manifest: &Manifest,
    tile: &TileInfo,
    bytes: &[u8],
) -> Result<MixtureShard> {
    verify_mixture_shard_as(manifest, tile, bytes, WholeFile::Crc32)
}

/// [`verify_mixture_shard`] with the whole-file check `whole`.
fn verify_mixture_shard_as(
    manifest: &Manifest,
    tile: &TileInfo,
    bytes: &[u8],
    whole: WholeFile,
) -> Result<MixtureShard> {
    let origin = check_bytes(manifest, tile, bytes, whole)?;
    let shard = decode_mixture_shard(bytes).map_err(|e| shard_error(&origin, e))?;
    let h = &shard.header;
    let want = manifest
        .mixture
        .as_ref()
        .map(|m| (m.slots, m.codebook_checksum.clone()));
    if h.scene_id != manifest.scene_id
        || h.tile_id != tile.id
        || h.model != manifest.model
        || h.dim != manifest.dim
        || h.count as u64 != tile.count
        || want != Some((shard.slots, format!("{:08x}", shard.codebook_crc)))
    {
        return Err(Error::format(
            &origin,
            format!(
                "header (scene {}, tile {}, model {}, dim {}, {} Gaussians, {} slots, codebook \
                 {:08x}) disagrees with the manifest (scene {}, tile {}, model {}, dim {}, {} \
                 Gaussians, {})",
                h.scene_id,
                h.tile_id,
                h.model,
                h.dim,
                h.count,
                shard.slots,
                shard.codebook_crc,
                manifest.scene_id,
                tile.id,
                manifest.model,
                manifest.dim,
                tile.count,
                manifest.mixture.as_ref().map_or_else(
                    || "no mixture".to_string(),
                    |m| format!("{} slots, codebook {}", m.slots, m.codebook_checksum)
                )
            ),
        ));
    }
    Ok(shard)
}

/// Which whole-file check a shard's verification runs besides its decode (which checks the
/// CRC-32s inside the shard).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WholeFile {
    /// Length and the whole file's CRC-32 against the manifest entry.
    Crc32,
    /// Length only: the caller has compared the file's SHA-256 with a signed manifest's, so the
    /// bytes are the publisher's, whose CRC-32 the fetch checked before storing them.
    Hashed,
}

/// Length and (with [`WholeFile::Crc32`]) whole-file CRC-32 of downloaded bytes against their
/// manifest entry. Returns the name of the shard the later checks' errors give
/// (`shard <id> of scene <scene>`).
///
/// Errors: [`Error::Format`] under that name, saying what differs.
fn check_bytes(
    manifest: &Manifest,
    tile: &TileInfo,
    bytes: &[u8],
    whole: WholeFile,
) -> Result<String> {
    let origin = format!("shard {} of scene {}", tile.id, manifest.scene_id);
    if bytes.len() as u64 != tile.bytes {
        return Err(Error::format(
            &origin,
            format!("{} bytes, the manifest says {}", bytes.len(), tile.bytes),
        ));
    }
    if whole == WholeFile::Hashed {
        return Ok(origin);
    }
    let want = parse_checksum(tile)?;
    let got = shard_checksum(bytes);
    if got != want {
        return Err(Error::format(
            &origin,
            format!("checksum {got:08x}, the manifest says {want:08x}"),
        ));
    }
    Ok(origin)
}

/// A decoding failure as the store reports it: another version is [`Error::Unsupported`] (not
/// corruption: fetch does not download it again), anything else [`Error::Format`].
fn shard_error(origin: &str, e: slag_common::shards::ShardError) -> Error {
    match e {
        slag_common::shards::ShardError::UnsupportedVersion(_) => Error::Unsupported {
            path: origin.into(),
            message: e.to_string(),
        },
        e => Error::format(origin, e.to_string()),
    }
}

/// What a shard header `h` gets wrong against its manifest entry: scene, tile, model, dim,
/// `dtype` and count, and the format `version` when one is given; `None` when all agree. The
/// message names both sides.
pub(super) fn header_disagreement(
    h: &ShardHeader,
    manifest: &Manifest,
    tile: &TileInfo,
    version: Option<u16>,
    dtype: Dtype,
) -> Option<String> {
    if version.is_none_or(|v| h.version == v)
        && h.scene_id == manifest.scene_id
        && h.tile_id == tile.id
        && h.model == manifest.model
        && h.dim == manifest.dim
        && h.dtype == dtype
        && h.count as u64 == tile.count
    {
        return None;
    }
    let (hv, mv) = match version {
        Some(v) => (format!("version {}, ", h.version), format!("version {v}, ")),
        None => (String::new(), String::new()),
    };
    Some(format!(
        "header ({hv}scene {}, tile {}, model {}, dim {}, {:?}, {} Gaussians) disagrees with the \
         manifest ({mv}scene {}, tile {}, model {}, dim {}, {dtype:?}, {} Gaussians)",
        h.scene_id,
        h.tile_id,
        h.model,
        h.dim,
        h.dtype,
        h.count,
        manifest.scene_id,
        tile.id,
        manifest.model,
        manifest.dim,
        tile.count
    ))
}

/// A decoded shard type [`EdgeStore::load_shards`] reads: [`StoredShard`] (dense manifests) or
/// [`MixtureShard`] (mixture manifests).
pub trait LoadableShard: Sized + Send {
    /// Verifies the stored bytes of `tile` against `manifest` (the whole file as `whole` says)
    /// and decodes them.
    ///
    /// Errors: as [`verify_shard`] / [`verify_mixture_shard`].
    fn verify(manifest: &Manifest, tile: &TileInfo, bytes: &[u8], whole: WholeFile)
    -> Result<Self>;
}

impl LoadableShard for StoredShard {
    fn verify(
        manifest: &Manifest,
        tile: &TileInfo,
        bytes: &[u8],
        whole: WholeFile,
    ) -> Result<Self> {
        verify_shard_as(manifest, tile, bytes, whole)
    }
}

impl LoadableShard for MixtureShard {
    fn verify(
        manifest: &Manifest,
        tile: &TileInfo,
        bytes: &[u8],
        whole: WholeFile,
    ) -> Result<Self> {
        verify_mixture_shard_as(manifest, tile, bytes, whole)
    }
}

/// Checks downloaded bytes against the manifest entry and the manifest itself: length, whole-shard
/// CRC-32, and a full decode whose header names the same scene, tile, model, dim and dtype.
///
/// Errors: [`Error::Format`] naming the tile and what differs (the caller discards the bytes).
pub fn verify_shard(manifest: &Manifest, tile: &TileInfo, bytes: &[u8]) -> Result<StoredShard> {
    verify_shard_as(manifest, tile, bytes, WholeFile::Crc32)
}

/// [`verify_shard`] with the whole-file check `whole`.
fn verify_shard_as(
    manifest: &Manifest,
    tile: &TileInfo,
    bytes: &[u8],
    whole: WholeFile,
) -> Result<StoredShard> {
    let origin = check_bytes(manifest, tile, bytes, whole)?;
    // Another version is not corruption: a shard from a newer (or older) slag, typed apart so
    // that fetch does not download it again and the message names the version.
    let shard = decode_shard_stored(bytes).map_err(|e| shard_error(&origin, e))?;
    if let Some(m) = header_disagreement(&shard.header, manifest, tile, None, manifest.dtype) {
        return Err(Error::format(&origin, m));
    }
    Ok(shard)
}

/// [`verify_mixture_shard`] for a mixture manifest, [`verify_shard`] otherwise, with the
/// whole-file check `whole`.
pub(super) fn verify_any_shard(
    manifest: &Manifest,
    tile: &TileInfo,
    bytes: &[u8],
    whole: WholeFile,
) -> Result<()> {
    match manifest.mixture {
        Some(_) => verify_mixture_shard_as(manifest, tile, bytes, whole).map(drop),
        None => verify_shard_as(manifest, tile, bytes, whole).map(drop),
    }
}
