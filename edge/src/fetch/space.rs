//! The free-space check: the bytes still to come against the store's file system, before
//! anything is written.

use slag_common::shards::{Manifest, TileInfo};
use slag_common::{Error, Result};

use crate::store::EdgeStore;

/// Refuses a download that cannot fit: the bytes still to come for `tiles` (their sizes less
/// what their partial files already hold) against [`EdgeStore::free_bytes`], before anything is
/// written.
///
/// Errors: [`Error::Limit`] [`slag_common::Resource::DiskSpace`] naming the store's folder;
/// [`Error::Io`] when the free space cannot be read.
pub(super) fn check_free_space<'a>(
    store: &EdgeStore,
    manifest: &Manifest,
    tiles: impl Iterator<Item = &'a TileInfo>,
) -> Result<()> {
    let mut needed = 0u64;
    let mut count = 0usize;
    for t in tiles {
        let part = store.partial_path(&manifest.scene_id, t);
        let have = std::fs::symlink_metadata(&part)
            .ok()
            .filter(|m| m.is_file() && m.len() <= t.bytes)
            .map_or(0, |m| m.len());
        needed = needed.saturating_add(t.bytes - have);
        count += 1;
    }
    if needed == 0 {
        return Ok(());
    }
    let free = store.free_bytes()?;
    if needed > free {
        return Err(Error::limit(
            slag_common::Resource::DiskSpace,
            format!(
                "{needed} bytes for {count} shard(s) of scene {}",
                manifest.scene_id
            ),
            format!(
                "{free} bytes free for the store {}",
                store.root().join("partial").display()
            ),
        ));
    }
    Ok(())
}
