//! Test/benchmark helpers for the shared snowmiku scene, over the real loaders
//! (`slag_common::scene::load_ply`, `slag_common::camera::load_views`), and the GPU tests' skip
//! rule. Shared by `raster::tests`, `tests/stability.rs` and `benches/raster.rs` (via `#[path]`).

#![allow(dead_code, clippy::unwrap_used)]

use std::path::{Path, PathBuf};

use slag_common::camera::{Intrinsics, WorldToCamera};
use slag_common::scene::{Gaussians, PlyLoadOptions};

/// `<shared>/scenes/snowmiku`.
pub fn snowmiku_dir() -> PathBuf {
    slag_common::paths::source_tree_shared_dir()
        .join("scenes")
        .join("snowmiku")
}

/// Loads a `.ply` (with SH colours when `colours`), panicking with the error on failure.
pub fn load_ply_for_test(path: &Path, colours: bool) -> Gaussians {
    slag_common::scene::load_ply(path, PlyLoadOptions { colours })
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The scene's views as (image name, intrinsics, world-to-camera), name-sorted.
pub fn load_views_for_test(scene: &Path) -> Vec<(String, Intrinsics, WorldToCamera)> {
    slag_common::camera::load_views(scene)
        .unwrap_or_else(|e| panic!("{}: {e}", scene.display()))
        .into_iter()
        .map(|v| (v.name, v.intrinsics, v.world_to_camera))
        .collect()
}

/// Whether `SLAG_SKIP_GPU=1` asks to skip the GPU parts of the tests.
pub fn skip_gpu() -> bool {
    std::env::var("SLAG_SKIP_GPU").is_ok_and(|v| v == "1")
}

/// `None` when [`skip_gpu`] (said on stderr); else what `make` builds (the GPU rasterizer),
/// panicking with a hint when it fails: without `SLAG_SKIP_GPU=1` a missing Vulkan adapter fails
/// the test rather than skipping it.
pub fn gpu_unless_skipped<R, E: std::fmt::Display>(
    make: impl FnOnce() -> Result<R, E>,
) -> Option<R> {
    if skip_gpu() {
        eprintln!("SLAG_SKIP_GPU=1: skipping the GPU part of this test");
        return None;
    }
    Some(make().unwrap_or_else(|e| {
        panic!("no usable Vulkan adapter ({e}); install mesa-vulkan-drivers or set SLAG_SKIP_GPU=1")
    }))
}
