//! INRIA `.ply` reader (to be implemented: header parse by property name, binary LE/BE + ASCII).

use std::path::Path;

use super::{Gaussians, PlyLoadOptions};
use crate::{Error, Result};

pub(super) fn read(path: &Path, _options: PlyLoadOptions) -> Result<Gaussians> {
    Err(Error::Invalid(format!("{}: PLY reader not implemented yet", path.display())))
}
