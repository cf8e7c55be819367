//! Camera sources (to be implemented: COLMAP binary/text, nerfstudio transforms.json).

use std::path::Path;

use super::View;
use crate::{Error, Result};

pub(super) fn load(scene_dir: &Path) -> Result<Vec<View>> {
    Err(Error::Invalid(format!("{}: camera loading not implemented yet", scene_dir.display())))
}
