//! The store's side of a fetch: step 3 (the stored files of the selected tiles checked, a
//! damaged one set aside) and what to download, then steps 5 and 6 (the new generation
//! committed, shards it does not hold evicted, partial files tidied).

use rayon::prelude::*;
use slag_common::Error;
use slag_common::Result;
use slag_common::fault::boundary;
use slag_common::shards::{Manifest, TileInfo};

use super::FetchSummary;
use crate::store::{EdgeStore, FetchRecord, KeptTiles, SignedManifest, Stored, parse_checksum};

/// Step 3 of the module doc on the blocking pool: checks what the store holds for each of
/// `tiles` against `manifest` (hashes too when `hashed`), setting a damaged file aside under the
/// generation lock. Returns each tile with what was found, and `manifest` back.
///
/// Errors: store I/O; a failed task ([`Error::Internal`]).
pub(super) async fn check_stored_tiles(
    store: &EdgeStore,
    manifest: Manifest,
    tiles: Vec<TileInfo>,
    hashed: bool,
) -> Result<(Vec<(TileInfo, Stored)>, Manifest)> {
    let store = store.clone();
    tokio::task::spawn_blocking(move || {
        let states = check_each(&store, &manifest, &tiles, hashed)?;
        Ok::<_, Error>((tiles.into_iter().zip(states).collect(), manifest))
    })
    .await
    .map_err(|e| Error::internal(format!("store task failed: {e}")))?
}

/// [`EdgeStore::check_stored_signed`] of each of `tiles`, on the rayon pool (hashing is the
/// cost of a signed fetch's checks), then each damaged file set aside under the generation lock
/// (a load in progress reads the committed generation whole). In the order of `tiles`.
///
/// Errors: store I/O.
fn check_each(
    store: &EdgeStore,
    manifest: &Manifest,
    tiles: &[TileInfo],
    hashed: bool,
) -> Result<Vec<Stored>> {
    let states: Vec<Stored> = tiles
        .par_iter()
        .map(|t| store.check_stored_signed(manifest, t, hashed))
        .collect::<Result<_>>()?;
    for s in &states {
        if let Stored::Damaged { path, why } = s {
            let _generation = store.lock_generation();
            store.set_aside(path, why)?;
        }
    }
    Ok(states)
}

/// A fetch with a trusted key, without pruning: hashes the stored files of the manifest's tiles
/// outside the disc (`selected`), which the new generation would keep, against the signed
/// manifest. A file that matches counts as verified in `kept`; one that does not (a tile forged
/// while an unsigned fetch was trusted, a file rewritten on disk with its CRC-32 kept) is set
/// aside and counted as dropped: it is not part of the new generation, so it is never served. A
/// fetch downloads only its disc, so a dropped tile comes back with a fetch whose disc covers
/// it. Returns `manifest` back.
///
/// Errors: store I/O; a failed task ([`Error::Internal`]).
pub(super) async fn check_kept_outside(
    store: &EdgeStore,
    manifest: Manifest,
    selected: &[TileInfo],
    kept: &mut KeptTiles,
) -> Result<Manifest> {
    let inside: std::collections::HashSet<u64> = selected.iter().map(|t| t.id).collect();
    let store = store.clone();
    let outside: Vec<TileInfo> = manifest
        .tiles
        .iter()
        .filter(|t| !inside.contains(&t.id))
        .cloned()
        .collect();
    let (states, manifest) = tokio::task::spawn_blocking(move || {
        let mut stored = Vec::new();
        for t in outside {
            if store.has_shard(&manifest.scene_id, &t)? {
                stored.push(t);
            }
        }
        let states = check_each(&store, &manifest, &stored, true)?;
        Ok::<_, Error>((states, manifest))
    })
    .await
    .map_err(|e| Error::internal(format!("store task failed: {e}")))??;
    for s in states {
        match s {
            Stored::Verified => kept.verified += 1,
            Stored::Damaged { .. } => kept.dropped += 1,
            Stored::Missing => {}
        }
    }
    Ok(manifest)
}

/// What to download after [`check_stored_tiles`]: the shards not verified in the store, and the
/// codebook (`codebook`'s tile) when it is not; counts the verified shards (`skipped`) and the
/// files set aside in `summary`, and with a trusted key (`hashed`) the stored tiles verified and
/// re-fetched ([`FetchSummary::kept`]).
pub(super) fn plan_downloads(
    checked: Vec<(TileInfo, Stored)>,
    codebook: Option<&TileInfo>,
    hashed: bool,
    summary: &mut FetchSummary,
) -> (Vec<TileInfo>, Option<TileInfo>) {
    let mut todo = Vec::new();
    let mut codebook_todo = None;
    for (t, state) in checked {
        let is_codebook = codebook.is_some_and(|c| c.id == t.id);
        match state {
            Stored::Verified if is_codebook => {}
            Stored::Verified => {
                summary.skipped += 1;
                summary.kept.verified += hashed as usize;
            }
            Stored::Missing | Stored::Damaged { .. } => {
                let damaged = matches!(state, Stored::Damaged { .. });
                summary.set_aside += damaged as usize;
                summary.kept.refetched += (hashed && damaged && !is_codebook) as usize;
                if is_codebook {
                    codebook_todo = Some(t);
                } else {
                    todo.push(t);
                }
            }
        }
    }
    (todo, codebook_todo)
}

/// After the commit: removes the partial files of tiles now stored (a kill between a shard
/// commit and the file's removal) or of older generations, keeping those of this manifest's
/// other tiles for a later fetch, and the codebooks of older generations (or of a scene now
/// partitioned dense); flushes the store. Returns the codebooks removed.
///
/// Errors: store I/O.
pub(super) fn tidy_after_commit(
    store: &EdgeStore,
    scene: &str,
    manifest: &Manifest,
) -> Result<usize> {
    let mut keep = Vec::new();
    for t in &manifest.tiles {
        if !store.has_shard(scene, t)? {
            keep.push(store.partial_path(scene, t));
        }
    }
    let current_codebook = store.codebook_path(manifest)?;
    let removed = store.remove_other_codebooks(scene, current_codebook.as_deref())?;
    store.clean_partials(scene, &keep)?;
    store.flush()?;
    Ok(removed)
}

/// Steps 5 and 6 of the module doc under the store's generation lock
/// ([`EdgeStore::lock_generation`]), so that a load sees the generation before or after, never
/// between: commits `manifest` (as `signed`'s bytes with their signature, when fetched with a
/// trusted key) with `record` listing the tiles the new generation holds (the
/// disc's `selected`, plus, without `prune`, the manifest's other tiles with a stored file),
/// then evicts the shards it does not hold: older generations' always, those outside the disc
/// with `prune`. Returns (shards evicted, tiles kept outside the disc).
///
/// Errors: store I/O.
pub(super) fn commit_and_evict(
    store: &EdgeStore,
    manifest: &Manifest,
    signed: Option<&SignedManifest>,
    selected: &[TileInfo],
    mut record: FetchRecord,
    prune: bool,
) -> Result<(usize, usize)> {
    let key = |t: &TileInfo| parse_checksum(t).ok().map(|c| (t.id, c));
    let wanted: std::collections::HashSet<(u64, u32)> = selected.iter().filter_map(key).collect();
    let current: std::collections::HashSet<(u64, u32)> =
        manifest.tiles.iter().filter_map(key).collect();
    let _generation = store.lock_generation();
    let mut tiles: Vec<u64> = Vec::with_capacity(manifest.tiles.len());
    for t in &manifest.tiles {
        let in_disc = key(t).is_some_and(|k| wanted.contains(&k));
        if in_disc || (!prune && store.has_shard(&manifest.scene_id, t)?) {
            tiles.push(t.id);
        }
    }
    tiles.sort_unstable();
    record.tiles = Some(tiles);
    boundary("fetch:before_commit");
    store.commit_fetch_signed(manifest, signed, &record)?;
    let (mut evicted, mut kept_outside) = (0, 0);
    for (tile, checksum, _) in store.stored_shards(&manifest.scene_id)? {
        let in_manifest = current.contains(&(tile, checksum));
        let in_disc = wanted.contains(&(tile, checksum));
        if !in_manifest || (prune && !in_disc) {
            evicted += store.remove_shard(&manifest.scene_id, tile, checksum)? as usize;
        } else if !in_disc {
            kept_outside += 1;
        }
    }
    Ok((evicted, kept_outside))
}
