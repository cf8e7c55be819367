//! File writing shared by every format: a whole file written atomically, a stale file of an
//! earlier run removed, and folder syncs.

use std::io::Write;
use std::path::{Path, PathBuf};

use crate::fault::boundary_in;
use crate::{Error, Result};

/// Writes `bytes` to `path` atomically (`<path>.partial`, fsync, rename, the folder synced).
/// Creates parent folders. Each step is a durability boundary (`io.write_atomic:write`,
/// `:fsync`, `:rename`, `:dir_sync`; [`crate::fault`]): a crash leaves the old file or the new
/// one at `path`, at most with a `.partial` beside it.
///
/// Errors: [`Error::Io`] naming the file or folder that failed.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomic_parts(path, &[bytes])
}

/// Removes `path` if it exists: a file of an earlier run that this run does not write (a level
/// file, the mixture) must not sit beside this run's report.
///
/// Errors: [`Error::Io`] naming the file.
pub fn remove_stale(path: &Path) -> Result<()> {
    if path.exists() {
        std::fs::remove_file(path).map_err(|e| Error::io(path, e))?;
    }
    Ok(())
}

/// [`write_atomic`] of the concatenation of `parts`, written one after the other through a
/// buffer: a file made of large arrays is written without first being copied into one.
///
/// Errors: [`Error::Io`] naming the temporary file, the file or its folder.
pub fn write_atomic_parts(path: &Path, parts: &[&[u8]]) -> Result<()> {
    const SITE: &str = "io.write_atomic";
    let (tmp, f) = create_partial(path)?;
    let mut w = std::io::BufWriter::with_capacity(1 << 20, f);
    for part in parts {
        w.write_all(part).map_err(|e| Error::io(&tmp, e))?;
    }
    let f = w
        .into_inner()
        .map_err(|e| Error::io(&tmp, e.into_error()))?;
    boundary_in(SITE, "write");
    f.sync_all().map_err(|e| Error::io(&tmp, e))?;
    boundary_in(SITE, "fsync");
    drop(f);
    std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))?;
    boundary_in(SITE, "rename");
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        sync_dir(dir)?;
        boundary_in(SITE, "dir_sync");
    }
    Ok(())
}

/// Creates (truncating) `<path>.partial`, the file an atomic write fills before renaming it to
/// `path`, and `path`'s parent folders; returns its path and the open file.
///
/// Errors: [`Error::Io`] naming the folder or the file.
pub fn create_partial(path: &Path) -> Result<(PathBuf, std::fs::File)> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    }
    let mut partial = path.as_os_str().to_owned();
    partial.push(".partial");
    let partial = PathBuf::from(partial);
    let f = std::fs::File::create(&partial).map_err(|e| Error::io(&partial, e))?;
    Ok((partial, f))
}

/// Syncs a folder so that the renames, creations and removals inside it survive a power loss.
/// A file system that cannot sync a folder (`EINVAL`) is accepted: the rename itself is still
/// atomic.
///
/// Errors: [`Error::Io`] naming the folder.
pub fn sync_dir(dir: &Path) -> Result<()> {
    match std::fs::File::open(dir).and_then(|d| d.sync_all()) {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::InvalidInput => Ok(()),
        Err(e) => Err(Error::io(dir, e)),
    }
}
