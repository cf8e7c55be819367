//! Helpers shared by the encoder's integration tests.
#![allow(dead_code, clippy::unwrap_used)]

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

/// segment_anything's `rle_to_mask`: uncompressed COCO RLE (`{"size": [h, w], "counts": [..]}`,
/// column-major, runs start with 0s) as (width, height, row-major 0/1 pixels).
pub fn rle_to_pixels(rle: &serde_json::Value) -> (u32, u32, Vec<u8>) {
    let size = rle["size"].as_array().unwrap();
    let (h, w) = (
        size[0].as_u64().unwrap() as usize,
        size[1].as_u64().unwrap() as usize,
    );
    let mut col_major = vec![0u8; h * w];
    let (mut idx, mut val) = (0usize, 0u8);
    for c in rle["counts"].as_array().unwrap() {
        let c = c.as_u64().unwrap() as usize;
        col_major[idx..idx + c].fill(val);
        idx += c;
        val ^= 1;
    }
    assert_eq!(idx, h * w, "RLE counts must cover the image");
    let mut px = vec![0u8; h * w];
    for x in 0..w {
        for y in 0..h {
            px[y * w + x] = col_major[x * h + y];
        }
    }
    (w as u32, h as u32, px)
}

/// `encoder/tests/fixtures/{file}`: the small models committed with the tests.
pub fn test_fixture(file: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(file)
}

/// `shared/fixtures/{name}` when the ONNX Runtime tests are to run ([`ort_available`]); `None`:
/// skip the test.
pub fn ort_fixtures(name: &str) -> Option<PathBuf> {
    ort_available().then(|| shared().join("fixtures").join(name))
}

/// A new temporary folder when the ONNX Runtime tests are to run ([`ort_available`]); `None`:
/// skip the test.
pub fn ort_tempdir() -> Option<tempfile::TempDir> {
    ort_available().then(|| tempfile::tempdir().expect("tempdir"))
}
