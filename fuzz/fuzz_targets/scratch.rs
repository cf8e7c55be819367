//! The per-process scratch folder of the targets whose parsers read paths.

use std::path::PathBuf;

/// `slag-fuzz-{name}-{pid}` on tmpfs (`/dev/shm`) when there is one, else in the system temp
/// folder; not created.
pub fn scratch_dir(name: &str) -> PathBuf {
    let base = if std::path::Path::new("/dev/shm").is_dir() {
        PathBuf::from("/dev/shm")
    } else {
        std::env::temp_dir()
    };
    base.join(format!("slag-fuzz-{name}-{}", std::process::id()))
}
