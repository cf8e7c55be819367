//! INRIA `.ply` reading and writing.
//!
//! The header ([`header`]) is parsed into a list of named, typed vertex properties; the body is
//! then decoded ([`decode`]) with fixed per-property byte offsets (binary) or fixed token
//! positions (ASCII), in large chunks, keeping only the columns the caller asked for. Writing a
//! scene, a float vertex header and a highlighted copy lives in [`encode`].

mod decode;
mod encode;
mod header;
#[cfg(test)]
mod tests;

pub(super) use decode::{read, read_bytes};
pub(crate) use encode::float_vertex_header;
pub(super) use encode::{write, write_highlighted};

/// The largest f32 below 1 (`1 - 2^-24`): activated opacities are clamped to it, both when
/// decoded (sigmoid of the stored logit) and before their logit is written.
pub(crate) const OPACITY_MAX: f32 = 1.0 - 1.0 / 16_777_216.0;
