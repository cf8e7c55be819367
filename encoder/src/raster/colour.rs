//! Colour rendering with the per-pixel weights, to validate them against the training photos.
//!
//! `colour_p = Σ_k w_kp · c_k` over the pixel's contributors, on a black background (the scene was
//! trained with one), where `c_k = max(SH(dir_k) + 0.5, 0)` is gsplat's / INRIA's view-dependent
//! colour with `dir_k = normalize(mean_k − camera centre)` (world frame). Because this uses the
//! exact [`PixelWeights`] the encoder aggregates over, a high PSNR against the photo validates the
//! weights themselves.

use image::{Rgb, RgbImage};
use slag_common::camera::{Intrinsics, WorldToCamera};
use slag_common::scene::{Gaussians, ShCoeffs};
use slag_common::{Error, Result};

use super::PixelWeights;

const C0: f64 = 0.282_094_791_773_878_14;
const C1: f64 = 0.488_602_511_902_919_9;
const C2: [f64; 5] = [
    1.092_548_430_592_079_2,
    -1.092_548_430_592_079_2,
    0.315_391_565_252_520_05,
    -1.092_548_430_592_079_2,
    0.546_274_215_296_039_6,
];
const C3: [f64; 7] = [
    -0.590_043_589_926_643_5,
    2.890_611_442_640_554,
    -0.457_045_799_464_465_8,
    0.373_176_332_590_115_4,
    -0.457_045_799_464_465_8,
    1.445_305_721_320_277,
    -0.590_043_589_926_643_5,
];

/// Real spherical-harmonic basis (degree ≤ 3, 16 values) at unit direction `d`, in the order and
/// sign convention of the INRIA rasterizer / gsplat (`f_dc` = index 0, `f_rest` = 1..15).
pub fn sh_basis(d: [f64; 3]) -> [f64; 16] {
    let [x, y, z] = d;
    let (xx, yy, zz) = (x * x, y * y, z * z);
    [
        C0,
        -C1 * y,
        C1 * z,
        -C1 * x,
        C2[0] * x * y,
        C2[1] * y * z,
        C2[2] * (2.0 * zz - xx - yy),
        C2[3] * x * z,
        C2[4] * (xx - yy),
        C3[0] * y * (3.0 * xx - yy),
        C3[1] * x * y * z,
        C3[2] * y * (4.0 * zz - xx - yy),
        C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
        C3[4] * x * (4.0 * zz - xx - yy),
        C3[5] * z * (xx - yy),
        C3[6] * x * (xx - 3.0 * yy),
    ]
}

/// View-dependent RGB of Gaussian `i` seen along unit direction `dir`:
/// `max(Σ_l basis_l(dir)·sh_l + 0.5, 0)` per channel (not clamped above; compositing clamps).
pub fn sh_colour(sh: &ShCoeffs, i: usize, dir: [f64; 3]) -> [f64; 3] {
    let basis = sh_basis(dir);
    let k = sh.per_channel();
    let base = i * k * 3;
    let mut rgb = [0.5f64; 3];
    for (l, b) in basis.iter().enumerate().take(k) {
        for (c, v) in rgb.iter_mut().enumerate() {
            *v += b * sh.coeffs[base + l * 3 + c] as f64;
        }
    }
    rgb.map(|v| v.max(0.0))
}

/// Renders the colour image of a view from its pixel weights (see the module docs).
///
/// `gaussians` must carry SH colours (`PlyLoadOptions { colours: true }`); `weights` must have
/// been rasterized for `intrinsics` (same size) from the same Gaussians. Output: `width × height`
/// sRGB-as-stored 8-bit image, each channel `round(255·clamp(colour, 0, 1))`.
///
/// Errors: SH colours missing ([`Error::Param`] `colours`), weights of another size than the
/// camera or an id out of range ([`Error::Mismatch`]), malformed arrays ([`Error::Internal`]).
pub fn render_colour(
    gaussians: &Gaussians,
    intrinsics: &Intrinsics,
    world_to_camera: &WorldToCamera,
    weights: &PixelWeights,
) -> Result<RgbImage> {
    let sh = gaussians.sh.as_ref().ok_or_else(|| {
        Error::param(
            "colours",
            false,
            "Gaussians with SH colours: load the .ply with colours: true",
        )
    })?;
    if sh.coeffs.len() != gaussians.len() * sh.per_channel() * 3 {
        return Err(Error::internal(
            "SH coefficient array does not match the Gaussian count",
        ));
    }
    if weights.width != intrinsics.width || weights.height != intrinsics.height {
        return Err(Error::mismatch(
            slag_common::Mismatched::ImageSize,
            format!(
                "pixel weights are {}x{} but the camera is {}x{}; rasterize with the same \
                 intrinsics",
                weights.width, weights.height, intrinsics.width, intrinsics.height
            ),
        ));
    }
    let n_pix = weights.width as usize * weights.height as usize;
    if weights.offsets.len() != n_pix + 1 || weights.ids.len() != weights.weights.len() {
        return Err(Error::internal(
            "malformed PixelWeights (offsets/ids/weights lengths)",
        ));
    }
    if let Some(&bad) = weights
        .ids
        .iter()
        .find(|&&id| id as usize >= gaussians.len())
    {
        return Err(Error::mismatch(
            slag_common::Mismatched::Scene,
            format!(
                "pixel weights reference Gaussian {bad} but the scene has {}; rasterize the same \
                 scene",
                gaussians.len()
            ),
        ));
    }
    // Per-Gaussian colour (only for Gaussians that contribute at all would be cheaper; N is small).
    let centre = world_to_camera.camera_centre();
    let colours: Vec<[f64; 3]> = (0..gaussians.len())
        .map(|i| {
            let m = gaussians.means[i];
            let d = glam::DVec3::new(m[0] as f64, m[1] as f64, m[2] as f64) - centre;
            let d = d.normalize_or_zero();
            sh_colour(sh, i, [d.x, d.y, d.z])
        })
        .collect();
    let mut img = RgbImage::new(weights.width, weights.height);
    for (p, px) in img.pixels_mut().enumerate() {
        let (a, b) = (weights.offsets[p] as usize, weights.offsets[p + 1] as usize);
        if a > b || b > weights.ids.len() {
            return Err(Error::internal("malformed PixelWeights offsets"));
        }
        let mut rgb = [0.0f64; 3];
        for e in a..b {
            let c = colours[weights.ids[e] as usize];
            let w = weights.weights[e] as f64;
            for ch in 0..3 {
                rgb[ch] += w * c[ch];
            }
        }
        *px = Rgb(rgb.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8));
    }
    Ok(img)
}

/// Peak signal-to-noise ratio of two 8-bit RGB images, dB: `10·log10(255² / MSE)` over all
/// channels; `f64::INFINITY` for identical images.
///
/// Errors: [`Error::Mismatch`] when the sizes differ or the images are empty.
pub fn psnr(a: &RgbImage, b: &RgbImage) -> Result<f64> {
    if a.dimensions() != b.dimensions() || a.as_raw().is_empty() {
        return Err(Error::mismatch(
            slag_common::Mismatched::ImageSize,
            format!(
                "psnr needs two non-empty images of one size, got {:?} and {:?}",
                a.dimensions(),
                b.dimensions()
            ),
        ));
    }
    let se: f64 = a
        .as_raw()
        .iter()
        .zip(b.as_raw())
        .map(|(&x, &y)| {
            let d = x as f64 - y as f64;
            d * d
        })
        .sum();
    let mse = se / a.as_raw().len() as f64;
    Ok(if mse == 0.0 {
        f64::INFINITY
    } else {
        10.0 * (255.0f64 * 255.0 / mse).log10()
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sh_basis_dc_only_matches_c0_and_degree1_is_odd() {
        let b = sh_basis([0.0, 0.0, 1.0]);
        assert_eq!(b[0], C0);
        assert_eq!(b[2], C1);
        let p = sh_basis([0.6, 0.0, 0.8]);
        let n = sh_basis([-0.6, 0.0, -0.8]);
        for l in 1..4 {
            assert!((p[l] + n[l]).abs() < 1e-15);
        }
        for l in 4..9 {
            assert!((p[l] - n[l]).abs() < 1e-15);
        }
    }

    #[test]
    fn psnr_of_known_error() {
        let a = RgbImage::from_pixel(4, 4, Rgb([10, 10, 10]));
        let b = RgbImage::from_pixel(4, 4, Rgb([20, 10, 10]));
        // MSE = 100 / 3.
        let expected = 10.0 * (255.0f64 * 255.0 / (100.0 / 3.0)).log10();
        assert!((psnr(&a, &b).expect("same size") - expected).abs() < 1e-12);
        assert_eq!(psnr(&a, &a).expect("same size"), f64::INFINITY);
        assert!(psnr(&a, &RgbImage::new(2, 2)).is_err());
    }
}
