//! Where the read-only `shared/` folder (scenes, model fixtures) lives.

use std::path::PathBuf;

/// The `shared/` folder beside the repository (`$SLAG_SHARED` overrides it).
///
/// Resolution order: `$SLAG_SHARED`, then `<workspace>/../shared`. Returns the path even when it
/// does not exist; callers report a missing file with its full path.
pub fn shared_dir() -> PathBuf {
    if let Some(p) = std::env::var_os("SLAG_SHARED") {
        return PathBuf::from(p);
    }
    // common/ is one level below the workspace root.
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join("..")
        .join("shared")
}
