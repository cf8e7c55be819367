//! Posed training images: intrinsics + world-to-camera extrinsics, read from COLMAP `sparse/0`
//! (binary or text) or nerfstudio `transforms.json`.
//!
//! Frame convention (COLMAP / OpenCV, also what gsplat and the INRIA rasterizer use): camera looks
//! down +z, x right, y down; `world_to_camera` maps world points to that frame. nerfstudio's OpenGL
//! camera-to-world matrices (y up, z backwards) are converted on load.

use std::path::{Path, PathBuf};

use glam::{DMat3, DVec3};

use crate::{Error, Result};

/// Pinhole intrinsics in pixels, for an image of `width` x `height`.
/// Pixel centres are at integer + 0.5 (COLMAP convention: the top-left pixel's centre is (0.5, 0.5)).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
}

impl Intrinsics {
    /// The same camera at `scale` times the resolution (`--raster-scale`): size rounded to whole
    /// pixels (at least 1), focal lengths and principal point scaled by the exact size ratio.
    pub fn scaled(&self, scale: f64) -> Intrinsics {
        let w = ((self.width as f64 * scale).round() as u32).max(1);
        let h = ((self.height as f64 * scale).round() as u32).max(1);
        let sx = w as f64 / self.width as f64;
        let sy = h as f64 / self.height as f64;
        Intrinsics {
            width: w,
            height: h,
            fx: self.fx * sx,
            fy: self.fy * sy,
            cx: self.cx * sx,
            cy: self.cy * sy,
        }
    }
}

/// A rigid world-to-camera transform `x_cam = rotation * x_world + translation` (COLMAP convention).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WorldToCamera {
    /// Rotation, world → camera.
    pub rotation: DMat3,
    /// Translation, camera frame, scene units.
    pub translation: DVec3,
}

impl WorldToCamera {
    /// The camera centre in world coordinates, `-Rᵀ t`.
    pub fn camera_centre(&self) -> DVec3 {
        -(self.rotation.transpose() * self.translation)
    }
}

/// One posed training image.
#[derive(Debug, Clone, PartialEq)]
pub struct View {
    /// Image file name as listed by the camera source (e.g. `20240212_003919.jpg`).
    pub name: String,
    /// Full path of the image file: `<scene>/images/<name>` for COLMAP, `<scene>/<file_path>` for
    /// nerfstudio (where `name` is `file_path` without a leading `./`).
    pub image_path: PathBuf,
    /// Intrinsics at the image's full resolution.
    pub intrinsics: Intrinsics,
    /// Extrinsics.
    pub world_to_camera: WorldToCamera,
}

/// Loads the posed views of a scene folder, sorted by image name.
///
/// Sources, first found wins: COLMAP `sparse/0/{cameras,images}.bin`, `sparse/0/*.txt`, the same in
/// `sparse/`, then nerfstudio `transforms.json`. COLMAP cameras must be `PINHOLE` or
/// `SIMPLE_PINHOLE`; the pose (qw qx qy qz, t) is world-to-camera. nerfstudio camera-to-world
/// matrices (OpenGL axes) are converted to OpenCV axes and inverted. `points3D` is never read.
///
/// Errors: no source present ([`crate::Error::Format`] listing every path looked for); a distorted
/// camera model ([`crate::Error::Unsupported`] naming it and telling to run
/// `colmap image_undistorter`); truncated binary files, unknown camera ids, duplicate names, bad
/// numbers ([`crate::Error::Format`]); I/O.
pub fn load_views(scene_dir: &Path) -> Result<Vec<View>> {
    discover(scene_dir)
}

/// Which file of `scene_dir` describes its posed images (COLMAP binary, then text, in `sparse/0`
/// then `sparse`; then `transforms.json`), read by its reader.
fn discover(scene_dir: &Path) -> Result<Vec<View>> {
    if !scene_dir.is_dir() {
        return Err(Error::io(
            scene_dir,
            std::io::Error::new(std::io::ErrorKind::NotFound, "scene folder not found"),
        ));
    }
    let images = scene_dir.join("images");
    let mut looked: Vec<PathBuf> = Vec::new();
    for sparse in [scene_dir.join("sparse").join("0"), scene_dir.join("sparse")] {
        let (cb, ib) = (sparse.join("cameras.bin"), sparse.join("images.bin"));
        if cb.is_file() && ib.is_file() {
            return colmap::load_binary(&cb, &ib, &images);
        }
        let (ct, it) = (sparse.join("cameras.txt"), sparse.join("images.txt"));
        if ct.is_file() && it.is_file() {
            return colmap::load_text(&ct, &it, &images);
        }
        looked.extend([cb, ib, ct, it]);
    }
    let transforms = scene_dir.join("transforms.json");
    if transforms.is_file() {
        return nerfstudio::load(&transforms, scene_dir);
    }
    looked.push(transforms);
    let list: Vec<String> = looked.iter().map(|p| p.display().to_string()).collect();
    Err(Error::format(
        scene_dir,
        format!(
            "no camera poses found; looked for a COLMAP model (cameras.bin + images.bin or \
             cameras.txt + images.txt) and a nerfstudio transforms.json: {}. Run COLMAP (then \
             `colmap image_undistorter`) or `ns-process-data` on the images first",
            list.join(", ")
        ),
    ))
}

/// Keeps every `every`-th view (indices 0, N, 2N, ... of the name-sorted list), the paper's 1:N
/// image subsampling. `every` = 0 is treated as 1.
pub fn subsample(views: Vec<View>, every: usize) -> Vec<View> {
    let every = every.max(1);
    views
        .into_iter()
        .enumerate()
        .filter(|(i, _)| i % every == 0)
        .map(|(_, v)| v)
        .collect()
}

pub mod colmap;
mod nerfstudio;
mod sources;
