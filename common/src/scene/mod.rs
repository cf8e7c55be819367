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
pub fn load_ply(path: &Path, options: PlyLoadOptions) -> Result<Gaussians> {
    ply::read(path, options)
}

mod ply;
