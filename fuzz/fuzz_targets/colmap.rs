//! COLMAP `cameras` + `images` (binary or text) through [`slag_common::camera::load_views`].
//!
//! Input: byte 0 picks the encoding (even: `.bin`, odd: `.txt`), bytes 1..3 are the little-endian
//! length of the cameras file, the rest is cameras then images. The files go to a per-process
//! folder on tmpfs (the loader reads paths).
#![no_main]

use std::path::PathBuf;
use std::sync::OnceLock;

use libfuzzer_sys::fuzz_target;

mod scratch;

fn dirs() -> &'static [PathBuf; 2] {
    static DIRS: OnceLock<[PathBuf; 2]> = OnceLock::new();
    DIRS.get_or_init(|| {
        let root = scratch::scratch_dir("colmap");
        let d = [root.join("bin"), root.join("txt")];
        for x in &d {
            std::fs::create_dir_all(x.join("sparse/0")).unwrap();
        }
        d
    })
}

fuzz_target!(|data: &[u8]| {
    if data.len() < 3 {
        return;
    }
    let text = data[0] & 1 == 1;
    let n = (u16::from_le_bytes([data[1], data[2]]) as usize).min(data.len() - 3);
    let (cameras, images) = data[3..].split_at(n);
    let dir = &dirs()[text as usize];
    let ext = if text { "txt" } else { "bin" };
    let sparse = dir.join("sparse/0");
    std::fs::write(sparse.join(format!("cameras.{ext}")), cameras).unwrap();
    std::fs::write(sparse.join(format!("images.{ext}")), images).unwrap();
    if let Ok(views) = slag_common::camera::load_views(dir) {
        for v in &views {
            assert!(v.intrinsics.width >= 1 && v.intrinsics.height >= 1);
        }
    }
});
