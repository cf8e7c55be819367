//! 3DGS scene loading: the INRIA-layout `.ply` written by the reference 3DGS trainer, gsplat,
//! splatfacto (nerfstudio `ns-export gaussian-splat`) and brush.
//!
//! Properties are read by name, so extra properties (normals, custom fields) are ignored and any SH
//! degree 0-3 is accepted. Activations follow the INRIA/gsplat convention: `opacity = sigmoid(o)`,
//! `scale = exp(s)`, rotation = normalised quaternion stored `rot_0..3` = (w, x, y, z).
//! Only what a stage needs is loaded: the weight rasterizer needs means/scales/rotations/opacities,
//! never SH colours ([`PlyLoadOptions::colours`]).

use std::path::Path;

use crate::Result;

/// Which optional attributes to load besides the geometry needed by every stage.
#[derive(Debug, Clone, Copy, Default)]
pub struct PlyLoadOptions {
    /// Load spherical-harmonic colour coefficients (DC and, when present, the rest).
    pub colours: bool,
}

/// Spherical-harmonic colour coefficients, INRIA/gsplat convention
/// (`colour = 0.5 + SH_C0 * f_dc + ...`, `SH_C0 = 0.28209479177387814`).
#[derive(Debug, Clone, PartialEq)]
pub struct ShCoeffs {
    /// SH degree 0..=3.
    pub degree: u8,
    /// `[N, (degree+1)^2, 3]` row-major: per Gaussian, per coefficient (DC first), RGB.
    /// (The `.ply` stores `f_rest` channel-major; the loader transposes it.)
    pub coeffs: Vec<f32>,
}

impl ShCoeffs {
    /// Number of coefficients per colour channel, `(degree+1)^2`.
    pub fn per_channel(&self) -> usize {
        (self.degree as usize + 1).pow(2)
    }
    /// The DC term of Gaussian `i` (`f_dc_0..2`).
    pub fn dc(&self, i: usize) -> [f32; 3] {
        let o = i * self.per_channel() * 3;
        [self.coeffs[o], self.coeffs[o + 1], self.coeffs[o + 2]]
    }
}

/// The activated parameters of N Gaussians, in the scene's world frame (the COLMAP/trainer frame).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Gaussians {
    /// Centres, world frame, scene units (metres for metric reconstructions). `[N][xyz]`.
    pub means: Vec<[f32; 3]>,
    /// Per-axis standard deviations `exp(scale_i)`, scene units. `[N][3]`.
    pub scales: Vec<[f32; 3]>,
    /// Unit quaternions, (w, x, y, z), rotating the local axes into the world frame. `[N][4]`.
    pub rotations: Vec<[f32; 4]>,
    /// `sigmoid(opacity)` in (0, 1). `[N]`.
    pub opacities: Vec<f32>,
    /// SH colours, loaded only with [`PlyLoadOptions::colours`].
    pub sh: Option<ShCoeffs>,
}

impl Gaussians {
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.means.len()
    }
    /// True when there are no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }
}

/// Reads an INRIA-layout binary (little- or big-endian) or ASCII `.ply`.
///
/// Required properties: `x y z`, `scale_0..2`, `rot_0..3`, `opacity`; with
/// [`PlyLoadOptions::colours`] also `f_dc_0..2` and any `f_rest_*` (degree inferred from their count:
/// 0, 9, 24 or 45). Errors: missing property, truncated body, non-finite values (with the vertex
/// index), an unsupported property type; each message says which file and what to do.
///
/// Activated opacities stay inside the open interval (0, 1) in f32: `sigmoid(o)` is clamped to
/// [`f32::MIN_POSITIVE`, 1 - 2^-24] (trained scenes have logits up to ~19, whose sigmoid rounds to
/// 1.0 in f32). Scales are `exp(s)` (an overflow is an error); quaternions are normalised.
///
/// Property types `char uchar short ushort int uint float double` (and their `int8`.. aliases) are
/// converted to f32; list properties in the vertex element are rejected. The body is decoded in
/// 32 MiB chunks with fixed per-property offsets; only the requested columns are kept (no SH memory
/// when `colours` is false).
///
/// Errors ([`crate::Error::Format`] unless noted): not a PLY / no `end_header`; missing property
/// (the message lists those found); list vertex property; `f_rest_*` count not 0/9/24/45; truncated
/// body; a non-finite value (names the vertex index and property); a zero quaternion (names the
/// vertex); [`crate::Error::Io`] when the file cannot be read.
pub fn load_ply(path: &Path, options: PlyLoadOptions) -> Result<Gaussians> {
    ply::read(path, options)
}

/// [`load_ply`] on the bytes of a `.ply` file already in memory (a download, a fuzzer input);
/// `origin` only names the data in error messages. Same conventions and errors as [`load_ply`]
/// (never [`crate::Error::Io`] except for invalid UTF-8 in an ASCII body).
pub fn load_ply_bytes(bytes: &[u8], origin: &Path, options: PlyLoadOptions) -> Result<Gaussians> {
    ply::read_bytes(origin, bytes, options)
}

/// The zeroth-order real SH basis constant `1 / (2 sqrt(pi))`: `colour = 0.5 + SH_C0 * f_dc`
/// (INRIA/gsplat convention).
pub const SH_C0: f64 = 0.28209479177387814;

/// Copies the 3DGS `.ply` at `src` to `dst` with some Gaussians recoloured, so any splat viewer
/// shows them in a flat colour (used by `slag-encoder query` to highlight matches).
///
/// The copy is byte-for-byte (any property layout, binary little- or big-endian) except, for each
/// vertex `i` where `colour_of(i)` returns `Some(rgb)` (linear display RGB in 0..1), `f_dc_0..2` are
/// set to `(rgb - 0.5) / SH_C0` and every `f_rest_*` is zeroed (view-independent colour).
/// Written atomically (`<dst>.partial` then rename): a failure never leaves a partial `dst`.
///
/// Errors: ASCII input ([`crate::Error::Unsupported`]); no `f_dc_0..2` or a truncated body
/// ([`crate::Error::Format`]); SH stored as integers ([`crate::Error::Unsupported`]); a non-finite
/// colour ([`crate::Error::Param`] `colour`); I/O.
pub fn write_highlighted_ply(
    src: &Path,
    dst: &Path,
    colour_of: impl Fn(usize) -> Option<[f32; 3]>,
) -> Result<()> {
    ply::write_highlighted(src, dst, colour_of)
}

/// Writes `gaussians` as an INRIA-layout binary little-endian `.ply` that [`load_ply`] and 3DGS
/// viewers read: float properties `x y z [f_dc_0..2 f_rest_*] opacity scale_0..2 rot_0..3` (SH only
/// when `gaussians.sh` is set; `f_rest` written channel-major), with the activations inverted:
/// `opacity = logit(o)` (o clamped to [`f32::MIN_POSITIVE`, 1 - 2^-24] so the logit is finite),
/// `scale = ln(s)`, rotations as stored (w, x, y, z). Written atomically.
///
/// Errors: inconsistent array lengths or SH size ([`crate::Error::Internal`]); I/O.
pub fn write_ply(path: &Path, gaussians: &Gaussians) -> Result<()> {
    ply::write(path, gaussians)
}

/// The header of a binary little-endian PLY with one `vertex` element of `n` rows and one `float`
/// property per name, in order, up to and including `end_header\n` (the INRIA 3DGS `.ply` layout
/// when the names are `x y z f_dc_* f_rest_* opacity scale_* rot_*`). `comment` (line breaks
/// replaced by spaces) follows the format line. The one PLY header writer: [`write_ply`] and the
/// edge's `/query.ply` use it.
pub fn float_vertex_header<S: AsRef<str>>(n: usize, names: &[S], comment: Option<&str>) -> Vec<u8> {
    ply::float_vertex_header(n, names, comment)
}

mod ply;
