//! Test/benchmark helpers for the shared snowmiku scene, over the real loaders
//! (`slag_common::scene::load_ply`, `slag_common::camera::load_views`). Shared by `raster::tests`
//! and `benches/raster.rs` (via `#[path]`).

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
