//! EWA projection of one 3D Gaussian to a 2D splat (Zwicker et al. 2001, as used by 3DGS and
//! gsplat 1.x "classic" `fully_fused_projection` + `isect_tiles`).
//!
//! This is the single written-down definition of the projection math; the CPU reference
//! ([`super::cpu`]) calls it in f64 and the GPU kernel (`gpu/project.wgsl`, `project` entry point)
//! mirrors it line by line in f32. Steps, for a Gaussian with world mean `μ`, per-axis standard
//! deviations `s`, unit quaternion `q = (w, x, y, z)` and opacity `o`:
//!
//! 1. camera-frame mean `t = R μ + T` ([`WorldToCamera`], COLMAP/OpenCV frame: +z forward, x right,
//!    y down); culled when `t.z < NEAR_PLANE` (0.01) or `t.z > FAR_PLANE` (1e10).
//! 2. world covariance `Σ = M Mᵀ`, `M = R(q) · diag(s)`; camera covariance `Σc = W Σ Wᵀ`
//!    (`W` the world-to-camera rotation).
//! 3. Jacobian of the pinhole projection at `t`, with `t.x/t.z`, `t.y/t.z` clamped to the view
//!    frustum widened by 30 % (gsplat `persp_proj`: `lim_x+ = (W - cx)/fx + 0.3·tan_fovx`,
//!    `lim_x- = cx/fx + 0.3·tan_fovx`, `tan_fovx = W / (2 fx)`; for a centred principal point this
//!    is the INRIA `±1.3·tan(fov/2)`):
//!    `J = [[fx/z, 0, -fx·tx/z²], [0, fy/z, -fy·ty/z²]]`, `tx = z·clamp(t.x/z)`, `ty = z·clamp(t.y/z)`.
//! 4. `Σ2D = J Σc Jᵀ + 0.3·I` (the low-pass / anti-aliasing dilation, [`LOW_PASS`]); culled when
//!    `det Σ2D ≤ 0`; `conic = Σ2D⁻¹` stored as `(a, b, c)` of `[[a, b], [b, c]]`.
//!    Evaluated as `P Pᵀ + 0.3·I` with `P = J W R diag(s)` (2×3) and the determinant by
//!    Cauchy-Binet: the same quantity, but without the cancellation that makes the f32 `Σ` of a very
//!    thin Gaussian inaccurate, so the GPU's f32 result tracks this f64 reference.
//! 5. `radius = ceil(3·sqrt(λ_max))` pixels, `λ_max = m + sqrt(max(0.01, m² - det))`,
//!    `m = ½ trace Σ2D` (gsplat 1.x).
//! 6. `mean2d = (fx·t.x/t.z + cx, fy·t.y/t.z + cy)` in pixels, pixel centres at `(x + 0.5, y + 0.5)`;
//!    culled when the square `mean2d ± radius` lies entirely outside `[0, W] × [0, H]`.
//! 7. tiles touched ([`tile_rect`]): `[floor((m - r)/16), ceil((m + r)/16))` per axis, clamped to the
//!    tile grid (gsplat `isect_tiles`).

use glam::{DMat3, DVec3};
use slag_common::camera::{Intrinsics, WorldToCamera};

/// Tile edge, pixels (gsplat / INRIA use 16×16 tiles).
pub const TILE_SIZE: u32 = 16;
/// Near clipping distance along the camera +z axis, scene units (gsplat default `near_plane`).
pub const NEAR_PLANE: f64 = 0.01;
/// Far clipping distance, scene units (gsplat default `far_plane`).
pub const FAR_PLANE: f64 = 1e10;
/// Variance added to both diagonal entries of the 2D covariance, pixels² (gsplat `eps2d`).
pub const LOW_PASS: f64 = 0.3;
/// Maximum alpha of one splat at one pixel (the spec of this project, INRIA 3DGS value).
pub const ALPHA_MAX: f64 = 0.99;
/// Splats with `α` below this are skipped at a pixel.
pub const ALPHA_MIN: f64 = 1.0 / 255.0;
/// A pixel stops accumulating once the next transmittance would fall below this; the splat that
/// would cross it is not included (gsplat's rule).
pub const T_MIN: f64 = 1e-4;

/// One projected Gaussian: the 2D splat the per-pixel blending evaluates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Splat2d {
    /// Projected centre, pixels (image x right, y down; pixel `(i, j)` has centre `(i+0.5, j+0.5)`).
    pub mean2d: [f64; 2],
    /// Inverse 2D covariance `(a, b, c)` of `[[a, b], [b, c]]`, 1/pixels².
    pub conic: [f64; 3],
    /// Camera-frame depth `t.z`, scene units (sort key).
    pub depth: f64,
    /// Screen-space radius, whole pixels (3σ of the major axis).
    pub radius: f64,
    /// Opacity in (0, 1), copied from the Gaussian.
    pub opacity: f64,
    /// The 2D covariance `Σ2D` (with the low-pass), `(a, b, c)`, pixels²; kept for diagnostics.
    pub cov2d: [f64; 3],
}

/// gsplat's frustum limits for the Jacobian clamp: `(lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg)`,
/// dimensionless (tangent units).
pub fn jacobian_limits(k: &Intrinsics) -> [f64; 4] {
    let tan_fovx = 0.5 * k.width as f64 / k.fx;
    let tan_fovy = 0.5 * k.height as f64 / k.fy;
    [
        (k.width as f64 - k.cx) / k.fx + 0.3 * tan_fovx,
        k.cx / k.fx + 0.3 * tan_fovx,
        (k.height as f64 - k.cy) / k.fy + 0.3 * tan_fovy,
        k.cy / k.fy + 0.3 * tan_fovy,
    ]
}

/// Rotation matrix of a (w, x, y, z) quaternion, normalised first; `None` for a zero or
/// non-finite quaternion.
pub fn quat_to_mat(q: [f64; 4]) -> Option<DMat3> {
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    if !(n > 0.0 && n.is_finite()) {
        return None;
    }
    let (w, x, y, z) = (q[0] / n, q[1] / n, q[2] / n, q[3] / n);
    // Columns of the rotation matrix (glam is column-major).
    Some(DMat3::from_cols(
        DVec3::new(
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y + w * z),
            2.0 * (x * z - w * y),
        ),
        DVec3::new(
            2.0 * (x * y - w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z + w * x),
        ),
        DVec3::new(
            2.0 * (x * z + w * y),
            2.0 * (y * z - w * x),
            1.0 - 2.0 * (x * x + y * y),
        ),
    ))
}

/// Camera-frame position `R·mean + T` of a world point (step 1), f64. Its `z` is the depth both
/// rasterizers sort by, computed by this one function so that the sort order is bit-identical.
pub fn camera_point(mean: [f64; 3], w2c: &WorldToCamera) -> DVec3 {
    w2c.rotation * DVec3::from(mean) + w2c.translation
}

/// Projects one Gaussian (steps 1-6 of the module docs). Returns `None` when it is culled: behind
/// the near plane or beyond the far plane, degenerate 2D covariance, radius box outside the image,
/// an opacity that is not a finite positive number (a NaN opacity would otherwise pass the
/// `min(0.99, ·)` clamp as 0.99), or any non-finite intermediate value (a zero quaternion, NaN or
/// infinite mean / scale). Zero scales are not culled: the 0.3 px² low-pass alone gives the splat
/// its footprint (gsplat's rule).
///
/// `mean`: world frame; `scale`: standard deviations, scene units; `quat`: (w, x, y, z);
/// `opacity` in (0, 1).
pub fn project_gaussian(
    mean: [f64; 3],
    scale: [f64; 3],
    quat: [f64; 4],
    opacity: f64,
    k: &Intrinsics,
    w2c: &WorldToCamera,
) -> Option<Splat2d> {
    if !(opacity > 0.0 && opacity.is_finite()) {
        return None;
    }
    let t = camera_point(mean, w2c);
    if !(t.z >= NEAR_PLANE && t.z <= FAR_PLANE) {
        return None;
    }
    let r = quat_to_mat(quat)?;
    let [lxp, lxn, lyp, lyn] = jacobian_limits(k);
    let rz = 1.0 / t.z;
    let rz2 = rz * rz;
    let tx = t.z * (t.x * rz).clamp(-lxn, lxp);
    let ty = t.z * (t.y * rz).clamp(-lyn, lyp);
    // J as a 2x3 matrix: rows j0, j1.
    let j0 = DVec3::new(k.fx * rz, 0.0, -k.fx * tx * rz2);
    let j1 = DVec3::new(0.0, k.fy * rz, -k.fy * ty * rz2);
    // Σ2D' = J W Σ Wᵀ Jᵀ = P Pᵀ with P = J W R S (2x3), evaluated in this factored form: the same
    // value, but without forming Σ (which loses the thin axes of very anisotropic Gaussians in
    // f32). Rows of P: p0 = (Wᵀ j0)ᵀ R S, p1 = (Wᵀ j1)ᵀ R S.
    let wt = w2c.rotation.transpose();
    let s = DVec3::from(scale);
    let p0 = (r.transpose() * (wt * j0)) * s;
    let p1 = (r.transpose() * (wt * j1)) * s;
    let a0 = p0.dot(p0);
    let b = p0.dot(p1);
    let c0 = p1.dot(p1);
    // det(P Pᵀ) by Cauchy-Binet (sum of squared 2x2 minors, no cancellation), then the low-pass:
    // det(Σ2D' + εI) = det(Σ2D') + ε (a0 + c0) + ε².
    let minors = p0.cross(p1);
    let det = minors.length_squared() + LOW_PASS * (a0 + c0) + LOW_PASS * LOW_PASS;
    let a = a0 + LOW_PASS;
    let c = c0 + LOW_PASS;
    if det.is_nan() || det <= 0.0 {
        return None;
    }
    let inv = 1.0 / det;
    let conic = [c * inv, -b * inv, a * inv];
    let mid = 0.5 * (a + c);
    let lambda = mid + (mid * mid - det).max(0.01).sqrt();
    let radius = (3.0 * lambda.sqrt()).ceil();
    let mean2d = [k.fx * t.x * rz + k.cx, k.fy * t.y * rz + k.cy];
    if !(radius.is_finite() && mean2d[0].is_finite() && mean2d[1].is_finite()) {
        return None;
    }
    if !conic.iter().all(|v| v.is_finite()) {
        return None;
    }
    if mean2d[0] + radius <= 0.0
        || mean2d[0] - radius >= k.width as f64
        || mean2d[1] + radius <= 0.0
        || mean2d[1] - radius >= k.height as f64
    {
        return None;
    }
    Some(Splat2d {
        mean2d,
        conic,
        depth: t.z,
        radius,
        opacity,
        cov2d: [a, b, c],
    })
}

/// Number of tiles `(tiles_x, tiles_y)` covering a `width × height` raster.
pub fn tile_grid(width: u32, height: u32) -> (u32, u32) {
    (width.div_ceil(TILE_SIZE), height.div_ceil(TILE_SIZE))
}

/// Tiles touched by a splat's radius box: half-open `[x0, x1) × [y0, y1)` in tile units, clamped to
/// the grid (gsplat `isect_tiles`). Empty (`x0 == x1` or `y0 == y1`) when it touches none.
pub fn tile_rect(mean2d: [f64; 2], radius: f64, tiles_x: u32, tiles_y: u32) -> [u32; 4] {
    let ts = TILE_SIZE as f64;
    let lo = |v: f64, n: u32| (v / ts).floor().clamp(0.0, n as f64) as u32;
    let hi = |v: f64, n: u32| (v / ts).ceil().clamp(0.0, n as f64) as u32;
    [
        lo(mean2d[0] - radius, tiles_x),
        lo(mean2d[1] - radius, tiles_y),
        hi(mean2d[0] + radius, tiles_x),
        hi(mean2d[1] + radius, tiles_y),
    ]
}

/// `α = min(ALPHA_MAX, o·exp(-σ))` with `σ = ½ dᵀ conic d`, `d = mean2d − pixel centre`; returns
/// `(σ, α)`. The caller skips the splat when `σ < 0` or `α < ALPHA_MIN`.
pub fn splat_alpha(s: &Splat2d, px: f64, py: f64) -> (f64, f64) {
    let dx = s.mean2d[0] - px;
    let dy = s.mean2d[1] - py;
    let sigma = 0.5 * (s.conic[0] * dx * dx + s.conic[2] * dy * dy) + s.conic[1] * dx * dy;
    (sigma, (s.opacity * (-sigma).exp()).min(ALPHA_MAX))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam() -> (Intrinsics, WorldToCamera) {
        (
            Intrinsics {
                width: 64,
                height: 48,
                fx: 50.0,
                fy: 50.0,
                cx: 32.0,
                cy: 24.0,
            },
            WorldToCamera {
                rotation: DMat3::IDENTITY,
                translation: DVec3::ZERO,
            },
        )
    }

    #[test]
    fn isotropic_gaussian_on_axis_projects_to_principal_point() {
        let (k, w2c) = cam();
        let s = project_gaussian(
            [0.0, 0.0, 2.0],
            [0.1; 3],
            [1.0, 0.0, 0.0, 0.0],
            0.5,
            &k,
            &w2c,
        )
        .expect("visible");
        assert_eq!(s.mean2d, [32.0, 24.0]);
        // Σ2D = (f/z)² s² + 0.3 on the diagonal = 6.25 + 0.3.
        let var = (50.0f64 / 2.0).powi(2) * 0.01 + 0.3;
        assert!((s.cov2d[0] - var).abs() < 1e-12 && s.cov2d[1].abs() < 1e-12);
        assert!((s.conic[0] - 1.0 / var).abs() < 1e-12);
        assert_eq!(s.radius, (3.0 * (var + 0.1).sqrt()).ceil());
    }

    #[test]
    fn quaternion_rotation_matches_axis_angle() {
        // 90° about z: (w, z) = (cos 45°, sin 45°); maps x to y.
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let r = quat_to_mat([h, 0.0, 0.0, h]).expect("unit");
        let v = r * DVec3::X;
        assert!((v - DVec3::Y).length() < 1e-12);
        assert!(quat_to_mat([0.0; 4]).is_none());
    }

    #[test]
    fn culls_behind_near_plane_and_outside_image() {
        let (k, w2c) = cam();
        let q = [1.0, 0.0, 0.0, 0.0];
        assert!(project_gaussian([0.0, 0.0, 0.005], [0.1; 3], q, 0.5, &k, &w2c).is_none());
        assert!(project_gaussian([0.0, 0.0, -1.0], [0.1; 3], q, 0.5, &k, &w2c).is_none());
        assert!(project_gaussian([100.0, 0.0, 1.0], [0.01; 3], q, 0.5, &k, &w2c).is_none());
    }

    #[test]
    fn tile_rect_is_half_open_and_clamped() {
        assert_eq!(tile_rect([20.0, 20.0], 3.0, 4, 3), [1, 1, 2, 2]);
        assert_eq!(tile_rect([16.0, 8.0], 2.0, 4, 3), [0, 0, 2, 1]);
        assert_eq!(tile_rect([-100.0, 8.0], 2.0, 4, 3), [0, 0, 0, 1]);
        assert_eq!(tile_rect([30.0, 30.0], 1e9, 4, 3), [0, 0, 4, 3]);
    }
}
