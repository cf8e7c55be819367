//! Where the read-only `shared/` folder (scenes, model fixtures) lives.
//!
//! A shipped binary finds it only through `$SLAG_SHARED` ([`shared_dir`]) or a flag naming the
//! file; nothing about the machine that built it is compiled in. Tests, benches and examples
//! that run from the source tree use [`source_tree_shared_dir`].

use std::path::PathBuf;

use crate::{Error, Result};

/// The environment variable naming the `shared/` folder (`scripts/setup.sh` exports it).
pub const SHARED_ENV: &str = "SLAG_SHARED";

/// The `shared/` folder named by `$SLAG_SHARED`.
///
/// Errors: [`Error::Invalid`] when the variable is unset or empty, saying what to set; the path
/// is returned even when it does not exist (callers report a missing file with its full path).
pub fn shared_dir() -> Result<PathBuf> {
    match std::env::var_os(SHARED_ENV) {
        Some(p) if !p.is_empty() => Ok(PathBuf::from(p)),
        _ => Err(Error::Invalid(format!(
            "${SHARED_ENV} is not set: export {SHARED_ENV}=<the shared/ folder with fixtures/ and \
             scenes/> (`. scripts/setup.sh` does), or name the files with their flags"
        ))),
    }
}

/// For code run from the source tree (tests, benches, examples): `$SLAG_SHARED`, else
/// `<workspace>/../shared`, the folder beside the repository on the machine that compiled it.
/// Never call it from a shipped binary's code path: that path does not exist on a robot.
pub fn source_tree_shared_dir() -> PathBuf {
    if let Ok(p) = shared_dir() {
        return p;
    }
    // common/ is one level below the workspace root.
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join("..")
        .join("shared")
}
