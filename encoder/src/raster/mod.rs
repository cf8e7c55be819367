//! The weight rasterizer: the 3DGS forward pass (EWA splatting, 16x16 tiles, front-to-back
//! alpha blending) that yields, per pixel, every contributing Gaussian's blend weight
//! `w_kp = α_kp · T_kp` instead of a colour (SLAG's Semantic Embedding stage).
//!
//! Conventions follow the INRIA rasterizer / gsplat: 0.3 px low-pass added to the 2D covariance,
//! `α = min(0.99, o · exp(-½ dᵀ Σ⁻¹ d))`, contributions with `α < 1/255` skipped, a pixel stops
//! once `T < 1e-4`.

/// Per-pixel contributor lists of one rendered view, in compressed-sparse-row form.
///
/// Pixel `p = y * width + x` owns entries `offsets[p] .. offsets[p + 1]` of `ids` / `weights`,
/// ordered front to back. `weights[e] = α·T` of Gaussian `ids[e]` at that pixel, in (0, 1];
/// per pixel the weights sum to `1 - T_final ≤ 1`.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PixelWeights {
    /// Raster width, pixels.
    pub width: u32,
    /// Raster height, pixels.
    pub height: u32,
    /// `width * height + 1` offsets into `ids` / `weights`.
    pub offsets: Vec<u32>,
    /// Gaussian indices (into the scene's Gaussians), front to back per pixel.
    pub ids: Vec<u32>,
    /// Blend weights `α·T`, parallel to `ids`.
    pub weights: Vec<f32>,
}

impl PixelWeights {
    /// The contributors `(ids, weights)` of pixel `(x, y)`.
    pub fn pixel(&self, x: u32, y: u32) -> (&[u32], &[f32]) {
        let p = (y * self.width + x) as usize;
        let (a, b) = (self.offsets[p] as usize, self.offsets[p + 1] as usize);
        (&self.ids[a..b], &self.weights[a..b])
    }
}

/// A weight rasterizer bound to one scene's Gaussians (uploaded once), rendering any view.
pub trait WeightRasterizer {
    /// Short name for reports (`"gpu:<adapter>"`, `"cpu-reference"`).
    fn name(&self) -> &str;
    /// Per-pixel contributors for a camera with `intrinsics` (already at raster resolution) and
    /// pose `world_to_camera`.
    fn rasterize(
        &mut self,
        intrinsics: &slag_common::camera::Intrinsics,
        world_to_camera: &slag_common::camera::WorldToCamera,
    ) -> slag_common::Result<PixelWeights>;
}
