//! Camera-source discovery: which file of a scene folder describes its posed images.

use std::path::{Path, PathBuf};

use super::{View, colmap, nerfstudio};
use crate::{Error, Result};

pub(super) fn load(scene_dir: &Path) -> Result<Vec<View>> {
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

/// Sorts views by name and rejects duplicate names.
pub(super) fn sort_views(source: &Path, mut views: Vec<View>) -> Result<Vec<View>> {
    views.sort_by(|a, b| a.name.cmp(&b.name));
    if let Some(w) = views.windows(2).find(|w| w[0].name == w[1].name) {
        return Err(Error::format(
            source,
            format!("image `{}` is listed twice", w[0].name),
        ));
    }
    if views.is_empty() {
        return Err(Error::format(
            source,
            "no images listed; the reconstruction is empty",
        ));
    }
    Ok(views)
}

/// The hint appended to every distorted-camera error.
pub(super) const UNDISTORT_HINT: &str = "slag needs undistorted pinhole images: run `colmap \
     image_undistorter --image_path <images> --input_path <sparse/0> --output_path <out>` and use \
     <out> as the scene folder (it has PINHOLE cameras and undistorted images)";
