//! File writing shared by every format: a whole file written atomically.

use std::io::Write;
use std::path::{Path, PathBuf};

use crate::{Error, Result};

/// Writes `bytes` to `path` atomically (`<path>.partial`, fsync, rename). Creates parent folders.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let (tmp, mut f) = create_partial(path)?;
    f.write_all(bytes)
        .and_then(|_| f.sync_all())
        .map_err(|e| Error::io(&tmp, e))?;
    drop(f);
    std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))
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
