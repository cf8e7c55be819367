//! nerfstudio `transforms.json` through [`slag_common::camera::load_views`] (the file goes to a
//! per-process folder on tmpfs: the loader reads paths).
#![no_main]

use std::path::PathBuf;
use std::sync::OnceLock;

use libfuzzer_sys::fuzz_target;

mod scratch;

fn dir() -> &'static PathBuf {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let d = scratch::scratch_dir("transforms");
        std::fs::create_dir_all(&d).unwrap();
        d
    })
}

fuzz_target!(|data: &[u8]| {
    let d = dir();
    std::fs::write(d.join("transforms.json"), data).unwrap();
    if let Ok(views) = slag_common::camera::load_views(d) {
        for v in &views {
            assert!(v.intrinsics.width >= 1 && v.intrinsics.height >= 1);
            assert!(v.intrinsics.fx > 0.0 && v.intrinsics.fy > 0.0);
        }
    }
});
