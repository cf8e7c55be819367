//! The command line's face of the library, shared by the binaries that take its flags
//! (`slag-encoder`, and `slag-bench stages|scaling` with `encode`'s): [`EncodeArgs`] and the
//! values of the flags that pick a library setting ([`values`]). The library's own types derive
//! no command-line traits; these map to them.

pub mod encode;
pub mod values;

pub use encode::{EncodeArgs, OnOff, PrecisionArg, SegmentArgs};
pub use values::{
    CropFillArg, MaskSourceArg, MaskWeightingArg, OverlapArg, RasterArg, SmoothArg, ViewsArg,
};
