//! `slag-encoder export DIR`: the current generation of a scene as plain files for any static
//! host or object store.
//!
//! Layout: `DIR/manifest.json` (the same JSON as `GET /v1/scenes/{scene}/manifest`) and
//! `DIR/shards/{id}` (the same bytes as `GET /v1/scenes/{scene}/shards/{id}`), plus, for a
//! mixture scene, `DIR/codebook` (`GET /v1/scenes/{scene}/codebook`), so serving `DIR` at
//! `/v1/scenes/{scene}/` reproduces the shard URLs. `manifest.json` holds the exact bytes the
//! store holds; beside it `DIR/manifest.sig` (`GET /v1/scenes/{scene}/manifest.sig`) is their
//! signature: the one stored with a signed generation, or a new one by the export's own signing
//! key when given ([`export_signed`]); no `manifest.sig` for an unsigned scene without a key.
//!
//! Atomic: everything is written into a hidden sibling `.DIR.partial-<pid>` (each file fsynced,
//! `manifest.json` last), then renamed to `DIR`. A killed export leaves at most that hidden
//! folder, never a `DIR` that looks complete. Replacing an existing `DIR` (`force`) renames the
//! old one aside first and deletes it after the new one is in place.

use std::io::Write;
use std::path::{Path, PathBuf};

use slag_common::shards::signature::SigningKey;
use slag_common::shards::{Manifest, shard_checksum};
use slag_common::{Error, Result};

use crate::store::ShardStore;

fn write_synced(path: &Path, bytes: &[u8]) -> Result<()> {
    let mut f = std::fs::File::create(path).map_err(|e| Error::io(path, e))?;
    f.write_all(bytes)
        .and_then(|_| f.sync_all())
        .map_err(|e| Error::io(path, e))
}

fn sibling(dir: &Path, tag: &str) -> Result<PathBuf> {
    let name = dir.file_name().ok_or_else(|| {
        Error::param(
            "dir",
            dir.display(),
            "an export folder with a name, e.g. out/scene",
        )
    })?;
    let mut n = std::ffi::OsString::from(".");
    n.push(name);
    n.push(format!(".{tag}-{}", std::process::id()));
    Ok(dir.with_file_name(n))
}

/// Exports the current generation of `scene` from `store` into `dir`.
///
/// Errors: unknown scene ([`Error::Param`] `scene`), `dir` exists and `force` is false
/// ([`Error::Io`] of kind `AlreadyExists`), a shard missing or not matching the manifest checksum (the store changed
/// during export or is corrupted; [`Error::Format`]), I/O. On error nothing is left at `dir`
/// (or the previous `dir` is unchanged) and the temporary folder is removed.
pub fn export(store: &ShardStore, scene: &str, dir: &Path, force: bool) -> Result<Manifest> {
    export_signed(store, scene, dir, force, None)
}

/// [`export`], the manifest signed with `key` when given (module doc).
///
/// Errors: as [`export`].
pub fn export_signed(
    store: &ShardStore,
    scene: &str,
    dir: &Path,
    force: bool,
    key: Option<&SigningKey>,
) -> Result<Manifest> {
    let stored = store.stored_manifest(scene)?.ok_or_else(|| {
        Error::param(
            "scene",
            format!("{scene:?}"),
            "a scene of the store (partition it into the store first)",
        )
    })?;
    let manifest = Manifest::from_json(&stored.bytes, &format!("store manifest {scene}"))?;
    let signature = match key {
        Some(k) => Some(k.sign(&stored.bytes).to_json()),
        None => stored.signature.as_ref().map(|s| s.to_vec()),
    };
    if dir.exists() && !force {
        return Err(Error::io(
            dir,
            std::io::Error::new(
                std::io::ErrorKind::AlreadyExists,
                "exists; export replaces it only when forced",
            ),
        ));
    }
    if let Some(parent) = dir.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(|e| Error::io(parent, e))?;
    }
    let tmp = sibling(dir, "partial")?;
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp).map_err(|e| Error::io(&tmp, e))?;
    }
    let signed = (stored.bytes.as_ref(), signature.as_deref());
    let result = write_tree(store, &manifest, signed, &tmp).and_then(|_| publish(&tmp, dir));
    if result.is_err() {
        let _ = std::fs::remove_dir_all(&tmp);
    }
    result.map(|_| manifest)
}

/// Writes the export into `tmp`: shards, codebook, then `(manifest bytes, signature)`, the
/// manifest last.
fn write_tree(
    store: &ShardStore,
    manifest: &Manifest,
    (json, signature): (&[u8], Option<&[u8]>),
    tmp: &Path,
) -> Result<()> {
    let shards = tmp.join("shards");
    std::fs::create_dir_all(&shards).map_err(|e| Error::io(&shards, e))?;
    for t in &manifest.tiles {
        let bytes = store.shard(&manifest.scene_id, t.id)?.ok_or_else(|| {
            Error::format(
                "<shard store>",
                format!(
                    "tile {} missing; the store changed during export, re-run",
                    t.id
                ),
            )
        })?;
        if format!("{:08x}", shard_checksum(&bytes)) != t.checksum {
            return Err(Error::format(
                "<shard store>",
                format!(
                    "tile {} checksum differs from the manifest; the store changed during export, re-run",
                    t.id
                ),
            ));
        }
        write_synced(&shards.join(t.id.to_string()), &bytes)?;
    }
    if let Some(x) = &manifest.mixture {
        let bytes = store.codebook(&manifest.scene_id)?.ok_or_else(|| {
            Error::format(
                "<shard store>",
                "the mixture scene's codebook is missing; re-run partition",
            )
        })?;
        if format!("{:08x}", shard_checksum(&bytes)) != x.codebook_checksum {
            return Err(Error::format(
                "<shard store>",
                "codebook checksum differs from the manifest; the store changed during export, \
                 re-run",
            ));
        }
        write_synced(&tmp.join("codebook"), &bytes)?;
    }
    if let Some(sig) = signature {
        write_synced(&tmp.join("manifest.sig"), sig)?;
    }
    write_synced(&tmp.join("manifest.json"), json)?;
    for d in [&shards, tmp] {
        if let Ok(f) = std::fs::File::open(d) {
            let _ = f.sync_all();
        }
    }
    Ok(())
}

fn publish(tmp: &Path, dir: &Path) -> Result<()> {
    if dir.exists() {
        let old = sibling(dir, "old")?;
        std::fs::rename(dir, &old).map_err(|e| Error::io(dir, e))?;
        if let Err(e) = std::fs::rename(tmp, dir) {
            let _ = std::fs::rename(&old, dir);
            return Err(Error::io(dir, e));
        }
        std::fs::remove_dir_all(&old).map_err(|e| Error::io(&old, e))?;
    } else {
        std::fs::rename(tmp, dir).map_err(|e| Error::io(dir, e))?;
    }
    if let Some(parent) = dir.parent().filter(|p| !p.as_os_str().is_empty())
        && let Ok(f) = std::fs::File::open(parent)
    {
        let _ = f.sync_all();
    }
    Ok(())
}
