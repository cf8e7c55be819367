//! Helpers shared by the encoder's integration tests.

use std::path::PathBuf;

/// `../shared` (or `$SLAG_SHARED`).
pub fn shared() -> PathBuf {
    slag_common::paths::source_tree_shared_dir()
}

/// Whether the ONNX Runtime tests should run. They need `ORT_DYLIB_PATH` (scripts/setup.sh
/// exports it); a missing runtime fails the test loudly, unless `SLAG_SKIP_ORT=1` asks to skip
/// (for quick local runs without ONNX Runtime), so CI can never pass them vacuously.
pub fn ort_available() -> bool {
    if std::env::var_os("ORT_DYLIB_PATH").is_some() {
        return true;
    }
    if std::env::var("SLAG_SKIP_ORT").as_deref() == Ok("1") {
        eprintln!("SKIPPED (SLAG_SKIP_ORT=1): ORT_DYLIB_PATH is not set");
        return false;
    }
    panic!("ORT_DYLIB_PATH is not set: run `. scripts/setup.sh` (or set SLAG_SKIP_ORT=1 to skip)");
}
