//! What every camera source's reader ([`super::colmap`], [`super::nerfstudio`]) shares: the
//! checks of the view list and the undistortion hint.

use std::path::Path;

use super::View;
use crate::{Error, Result};

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
