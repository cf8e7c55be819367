//! PIL-compatible image resampling and the SAM / CLIP input tensors built on it.
//!
//! [`resize_rgb`] reimplements Pillow's `ImagingResample` for 8-bit images (`Image.resize` with
//! `reducing_gap=None`, as torchvision's `F.resize` calls it on PIL images): a separable
//! convolution, horizontal pass first, then vertical, with
//! - the filter support scaled by the downscale factor (antialiasing; no scaling when upsampling),
//! - per-output-pixel coefficients normalised to sum 1, then quantised to 22-bit fixed point
//!   (`PRECISION_BITS = 32 - 8 - 2`, rounded half away from zero),
//! - accumulation from `1 << 21` and `>> 22` with clamping to `0..=255` after *each* pass (the
//!   intermediate image is uint8, like PIL's),
//! - the vertical pass first when the height shrinks by more than twice as many pixels as the
//!   width (Pillow 13's `ImagingResampleInner`), otherwise horizontal first.
//!
//! The result is bit-identical to Pillow for `RGB` images with the bilinear (triangle, support 1)
//! and bicubic (Keys, `a = -0.5`, support 2) filters.
//!
//! On top of it:
//! - [`sam_pixel_values`]: segment_anything's `ResizeLongestSide(1024).apply_image` (PIL
//!   bilinear), `(x - pixel_mean) / pixel_std`, zero padding to 1024x1024 → `f32[1,3,1024,1024]`.
//! - [`clip_pixel_values`] ([`clip_pixels`] + [`clip_normalize`]): open_clip's `ViT-B-32`
//!   preprocessing: torchvision `Resize(224)` (shortest side, PIL bicubic), `CenterCrop(224)`,
//!   `ToTensor`, `Normalize(CLIP mean, std)` → `f32[3,224,224]`.

use std::path::Path;

use image::RgbImage;
use slag_common::{Error, Result};

mod jpeg;

/// Loads an image as RGB8, decoding JPEGs exactly as Pillow does (libjpeg-turbo defaults: islow
/// IDCT, fancy upsampling), so SAM/CLIP inputs match the Python references bit for bit.
///
/// Baseline JPEGs (grey, 4:4:4 or 4:2:0) use slag's libjpeg-turbo-compatible decoder; other JPEGs
/// (progressive, 4:2:2, CMYK, ...) and every other format go through the `image` crate, whose
/// JPEG decoder differs from libjpeg-turbo by a few levels on some pixels. EXIF orientation is
/// not applied (neither Pillow's `Image.open` nor COLMAP apply it).
///
/// # Errors
/// [`Error::Io`] when the file cannot be read, [`Error::Format`] when it cannot be decoded.
pub fn load_rgb(path: &Path) -> Result<RgbImage> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    if bytes.starts_with(&[0xFF, 0xD8]) {
        match jpeg::decode(&bytes) {
            Ok(Some(img)) => return Ok(img),
            Ok(None) => {}
            Err(e) => return Err(Error::format(path, format!("corrupt JPEG: {e}"))),
        }
    }
    image::load_from_memory(&bytes)
        .map(|i| i.to_rgb8())
        .map_err(|e| Error::format(path, format!("cannot decode image: {e}")))
}

/// Resampling filter (Pillow's names).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Filter {
    /// `Image.BILINEAR`: triangle filter, support 1.
    Bilinear,
    /// `Image.BICUBIC`: cubic convolution with `a = -0.5`, support 2.
    Bicubic,
}

impl Filter {
    fn support(self) -> f64 {
        match self {
            Filter::Bilinear => 1.0,
            Filter::Bicubic => 2.0,
        }
    }

    fn eval(self, x: f64) -> f64 {
        let x = x.abs();
        match self {
            Filter::Bilinear => {
                if x < 1.0 {
                    1.0 - x
                } else {
                    0.0
                }
            }
            Filter::Bicubic => {
                const A: f64 = -0.5;
                if x < 1.0 {
                    ((A + 2.0) * x - (A + 3.0)) * x * x + 1.0
                } else if x < 2.0 {
                    (((x - 5.0) * x + 8.0) * x - 4.0) * A
                } else {
                    0.0
                }
            }
        }
    }
}

const PRECISION_BITS: u32 = 32 - 8 - 2;

/// Fixed-point coefficients of one resampling axis (Pillow's `precompute_coeffs` followed by
/// `normalize_coeffs_8bpc`).
struct Coeffs {
    /// Per output pixel: first input index and number of taps.
    bounds: Vec<(usize, usize)>,
    /// `out_size * ksize` fixed-point weights.
    weights: Vec<i32>,
    ksize: usize,
}

fn precompute_coeffs(in_size: usize, out_size: usize, filter: Filter) -> Coeffs {
    // Pillow passes the box as float[4]; the default box is (0, 0, in_size, ...).
    let (in0, in1) = (0.0f32, in_size as f32);
    let scale = f64::from(in1 - in0) / out_size as f64;
    let filterscale = scale.max(1.0);
    let support = filter.support() * filterscale;
    let ksize = support.ceil() as usize * 2 + 1;
    let inv_filterscale = 1.0 / filterscale;
    let mut bounds = Vec::with_capacity(out_size);
    let mut weights = vec![0i32; out_size * ksize];
    let mut k = vec![0f64; ksize];
    for xx in 0..out_size {
        let center = f64::from(in0) + (xx as f64 + 0.5) * scale;
        // C's (int) truncates toward zero.
        let xmin = ((center - support + 0.5) as i64).max(0) as usize;
        let xmax = ((center + support + 0.5) as i64).min(in_size as i64) as usize;
        let n = xmax.saturating_sub(xmin);
        let mut ww = 0.0;
        for (x, kx) in k.iter_mut().enumerate().take(n) {
            let w = filter.eval((x as f64 + xmin as f64 - center + 0.5) * inv_filterscale);
            *kx = w;
            ww += w;
        }
        for (x, kx) in k.iter().enumerate().take(n) {
            let v = if ww != 0.0 { kx / ww } else { *kx };
            let f = v * f64::from(1u32 << PRECISION_BITS);
            weights[xx * ksize + x] = if v < 0.0 {
                (f - 0.5) as i32
            } else {
                (f + 0.5) as i32
            };
        }
        bounds.push((xmin, n));
    }
    Coeffs {
        bounds,
        weights,
        ksize,
    }
}

#[inline]
fn clip8(acc: i64) -> u8 {
    (acc >> PRECISION_BITS).clamp(0, 255) as u8
}

/// Horizontal 8-bit pass of Pillow's resampler: `iw` x `h` RGB → `ow` x `h`.
fn horizontal_pass(src: &[u8], iw: usize, h: usize, ow: usize, filter: Filter) -> Vec<u8> {
    let half = 1i64 << (PRECISION_BITS - 1);
    let c = precompute_coeffs(iw, ow, filter);
    let mut out = vec![0u8; ow * h * 3];
    for y in 0..h {
        let line = &src[y * iw * 3..(y + 1) * iw * 3];
        let dst = &mut out[y * ow * 3..(y + 1) * ow * 3];
        for (xx, &(xmin, n)) in c.bounds.iter().enumerate() {
            let k = &c.weights[xx * c.ksize..xx * c.ksize + n];
            let (mut s0, mut s1, mut s2) = (half, half, half);
            for (x, &kx) in k.iter().enumerate() {
                let p = (xmin + x) * 3;
                let kx = i64::from(kx);
                s0 += i64::from(line[p]) * kx;
                s1 += i64::from(line[p + 1]) * kx;
                s2 += i64::from(line[p + 2]) * kx;
            }
            dst[xx * 3] = clip8(s0);
            dst[xx * 3 + 1] = clip8(s1);
            dst[xx * 3 + 2] = clip8(s2);
        }
    }
    out
}

/// Vertical 8-bit pass of Pillow's resampler: `w` x `ih` RGB → `w` x `oh`.
fn vertical_pass(src: &[u8], w: usize, ih: usize, oh: usize, filter: Filter) -> Vec<u8> {
    let half = 1i64 << (PRECISION_BITS - 1);
    let c = precompute_coeffs(ih, oh, filter);
    let row = w * 3;
    let mut out = vec![0u8; row * oh];
    let mut acc = vec![0i64; row];
    for (yy, &(ymin, n)) in c.bounds.iter().enumerate() {
        acc.fill(half);
        let k = &c.weights[yy * c.ksize..yy * c.ksize + n];
        for (y, &ky) in k.iter().enumerate() {
            let line = &src[(ymin + y) * row..(ymin + y + 1) * row];
            let ky = i64::from(ky);
            for (a, &p) in acc.iter_mut().zip(line) {
                *a += i64::from(p) * ky;
            }
        }
        for (d, &a) in out[yy * row..(yy + 1) * row].iter_mut().zip(&acc) {
            *d = clip8(a);
        }
    }
    out
}

/// Resizes an RGB image to `width` x `height` exactly as Pillow's `Image.resize(size, filter)`
/// (Pillow 13's pass order: vertical first when the height shrinks by more than twice as many
/// pixels as the width).
///
/// # Errors
/// [`Error::Invalid`] when the source or the target has a zero dimension.
pub fn resize_rgb(img: &RgbImage, width: u32, height: u32, filter: Filter) -> Result<RgbImage> {
    let (iw, ih) = (img.width() as usize, img.height() as usize);
    if iw == 0 || ih == 0 || width == 0 || height == 0 {
        return Err(Error::Invalid(format!(
            "cannot resize a {iw}x{ih} image to {width}x{height}: sizes must be non-zero"
        )));
    }
    let (ow, oh) = (width as usize, height as usize);
    let src = img.as_raw().as_slice();
    // Pillow (ImagingResampleInner, since 13.0): the vertical pass runs first when the height
    // shrinks by more than twice as many pixels as the width does.
    let vertical_first = ih > oh && (ih - oh) as i64 > (iw as i64 - ow as i64) * 2;
    // Each pass is skipped (`None`) when its side keeps its size; the argument is the other
    // side's length as it enters the pass.
    let vertical = |px: &[u8], w: usize| (oh != ih).then(|| vertical_pass(px, w, ih, oh, filter));
    let horizontal =
        |px: &[u8], h: usize| (ow != iw).then(|| horizontal_pass(px, iw, h, ow, filter));
    let out = if vertical_first {
        let tmp = vertical(src, iw).unwrap_or_else(|| src.to_vec());
        horizontal(&tmp, oh).unwrap_or(tmp)
    } else {
        let tmp = horizontal(src, ih).unwrap_or_else(|| src.to_vec());
        vertical(&tmp, ow).unwrap_or(tmp)
    };
    RgbImage::from_raw(width, height, out)
        .ok_or_else(|| Error::internal("resize buffer size mismatch"))
}

/// SAM's input side length (`ImageEncoderViT.img_size`).
pub const SAM_IMAGE_SIZE: u32 = 1024;
/// SAM's `pixel_mean` (RGB, 0..255).
pub const SAM_PIXEL_MEAN: [f32; 3] = [123.675, 116.28, 103.53];
/// SAM's `pixel_std` (RGB, 0..255).
pub const SAM_PIXEL_STD: [f32; 3] = [58.395, 57.12, 57.375];

/// segment_anything's `ResizeLongestSide.get_preprocess_shape`: the `(height, width)` after
/// scaling the longest side to `long_side` (each rounded half up).
pub fn sam_preprocess_shape(height: u32, width: u32, long_side: u32) -> (u32, u32) {
    let scale = f64::from(long_side) / f64::from(height.max(width));
    let h = (f64::from(height) * scale + 0.5) as u32;
    let w = (f64::from(width) * scale + 0.5) as u32;
    (h, w)
}

/// SAM encoder input of one image: `f32[3, 1024, 1024]` (channel-major RGB) plus the resized
/// `(height, width)` of the image inside it.
///
/// ResizeLongestSide(1024) with PIL bilinear, `(x - mean) / std` (SAM's `pixel_mean`/`pixel_std`
/// computed as the reference does: `(mean / 255) * 255` in f32), zero padding on the bottom/right.
///
/// # Errors
/// [`Error::Invalid`] for an empty image.
pub fn sam_pixel_values(img: &RgbImage) -> Result<(Vec<f32>, (u32, u32))> {
    let (h, w) = sam_preprocess_shape(img.height(), img.width(), SAM_IMAGE_SIZE);
    if img.width() == 0 || img.height() == 0 || h == 0 || w == 0 {
        return Err(Error::Invalid(format!(
            "image of {}x{} pixels is too small for SAM",
            img.width(),
            img.height()
        )));
    }
    let resized = resize_rgb(img, w, h, Filter::Bilinear)?;
    let s = SAM_IMAGE_SIZE as usize;
    let mut out = vec![0f32; 3 * s * s];
    for c in 0..3 {
        let mean = (SAM_PIXEL_MEAN[c] / 255.0) * 255.0;
        let std = (SAM_PIXEL_STD[c] / 255.0) * 255.0;
        let plane = &mut out[c * s * s..(c + 1) * s * s];
        for (y, row) in resized.rows().enumerate() {
            for (x, p) in row.enumerate() {
                plane[y * s + x] = (f32::from(p.0[c]) - mean) / std;
            }
        }
    }
    Ok((out, (h, w)))
}

/// CLIP's input side length.
pub const CLIP_IMAGE_SIZE: u32 = 224;
/// OpenAI CLIP normalisation mean (RGB, 0..1), as written in open_clip.
#[allow(clippy::excessive_precision)]
pub const CLIP_MEAN: [f32; 3] = [0.481_454_66, 0.457_827_5, 0.408_210_73];
/// OpenAI CLIP normalisation std (RGB, 0..1), as written in open_clip.
#[allow(clippy::excessive_precision)]
pub const CLIP_STD: [f32; 3] = [0.268_629_54, 0.261_302_58, 0.275_777_11];

/// torchvision `Resize(size)` with an int size: the `(width, height)` whose shorter side is `size`
/// and whose longer side is `int(size * long / short)`.
pub fn shortest_side_shape(width: u32, height: u32, size: u32) -> (u32, u32) {
    let (short, long) = if width <= height {
        (width, height)
    } else {
        (height, width)
    };
    let new_long = (f64::from(size) * f64::from(long) / f64::from(short)) as u32;
    if width <= height {
        (size, new_long)
    } else {
        (new_long, size)
    }
}

/// torchvision `center_crop` offset: `int(round((len - crop) / 2))` with Python's round-half-even.
fn center_offset(len: u32, crop: u32) -> u32 {
    let v = (f64::from(len) - f64::from(crop)) / 2.0;
    v.round_ties_even().max(0.0) as u32
}

/// open_clip preprocessing of one crop into `out` = `f32[3, 224, 224]` (channel-major RGB):
/// [`clip_pixels`], then [`clip_normalize`] (`/255`, `(x - mean) / std`).
///
/// # Errors
/// As [`clip_pixels`]; [`Error::Internal`] for an `out` of the wrong length.
pub fn clip_pixel_values(img: &RgbImage, out: &mut [f32]) -> Result<()> {
    let mut bytes = vec![0u8; CLIP_PIXELS];
    clip_pixels(img, &mut bytes)?;
    clip_normalize(&bytes, out)
}

/// Values in one CLIP crop, `3 × 224 × 224`.
pub const CLIP_PIXELS: usize = 3 * (CLIP_IMAGE_SIZE as usize) * (CLIP_IMAGE_SIZE as usize);

/// The geometric half of open_clip's preprocessing, one crop into `out` = `u8[3, 224, 224]`
/// (channel-major RGB bytes): resize the shortest side to 224 (PIL bicubic, rounded to bytes as
/// PIL does), centre crop 224 (torchvision rounding). [`clip_normalize`] is the other half; a
/// CLIP tower with byte input (`scripts/clip-u8-pixels.py`) does it in its graph.
///
/// # Errors
/// [`Error::Invalid`] for an empty image, [`Error::Internal`] for an `out` of the wrong length.
pub fn clip_pixels(img: &RgbImage, out: &mut [u8]) -> Result<()> {
    let s = CLIP_IMAGE_SIZE as usize;
    if out.len() != CLIP_PIXELS {
        return Err(Error::internal(format!(
            "CLIP crop buffer has {} values, expected 3*224*224",
            out.len()
        )));
    }
    if img.width() == 0 || img.height() == 0 {
        return Err(Error::Invalid(
            "cannot embed an empty (0-pixel) crop".into(),
        ));
    }
    let (w, h) = shortest_side_shape(img.width(), img.height(), CLIP_IMAGE_SIZE);
    let resized = if (w, h) == img.dimensions() {
        img.clone()
    } else {
        resize_rgb(img, w, h, Filter::Bicubic)?
    };
    let (x0, y0) = (
        center_offset(w, CLIP_IMAGE_SIZE),
        center_offset(h, CLIP_IMAGE_SIZE),
    );
    let (rw, raw) = (resized.width() as usize, resized.as_raw());
    let (x0, y0) = (x0 as usize, y0 as usize);
    for c in 0..3 {
        let plane = &mut out[c * s * s..(c + 1) * s * s];
        for (y, prow) in plane.chunks_exact_mut(s).enumerate() {
            let row = &raw[((y0 + y) * rw + x0) * 3..][..s * 3];
            for (o, px) in prow.iter_mut().zip(row.chunks_exact(3)) {
                *o = px[c];
            }
        }
    }
    Ok(())
}

/// CLIP's scaling and normalisation of crops made by [`clip_pixels`]: `bytes` = `u8[n, 3, 224,
/// 224]` into `out` = `f32[n, 3, 224, 224]`, `(x / 255 - mean[c]) / std[c]` in f32 (open_clip's
/// `ToTensor` + `Normalize`; the same operations as `scripts/clip-u8-pixels.py`'s graph).
///
/// # Errors
/// [`Error::Internal`] when the lengths differ or are not whole crops.
pub fn clip_normalize(bytes: &[u8], out: &mut [f32]) -> Result<()> {
    if bytes.len() != out.len() || !bytes.len().is_multiple_of(CLIP_PIXELS) {
        return Err(Error::internal(format!(
            "CLIP normalisation of {} bytes into {} values: both must be the same whole number \
             of 3*224*224 crops",
            bytes.len(),
            out.len()
        )));
    }
    let plane = CLIP_PIXELS / 3;
    let table: [[f32; 256]; 3] = std::array::from_fn(|c| {
        std::array::from_fn(|v| (v as f32 / 255.0 - CLIP_MEAN[c]) / CLIP_STD[c])
    });
    for (i, (o, b)) in out.chunks_mut(plane).zip(bytes.chunks(plane)).enumerate() {
        let t = &table[i % 3];
        for (o, &b) in o.iter_mut().zip(b) {
            *o = t[usize::from(b)];
        }
    }
    Ok(())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn coefficients_sum_to_one_in_fixed_point() {
        for (i, o) in [(990, 1024), (742, 767), (491, 224), (1000, 3), (5, 224)] {
            for f in [Filter::Bilinear, Filter::Bicubic] {
                let c = precompute_coeffs(i, o, f);
                for (xx, &(_, n)) in c.bounds.iter().enumerate() {
                    let s: i64 = c.weights[xx * c.ksize..xx * c.ksize + n]
                        .iter()
                        .map(|&v| i64::from(v))
                        .sum();
                    assert!(
                        (s - (1 << PRECISION_BITS)).abs() <= n as i64,
                        "{i}->{o} {f:?}: {s}"
                    );
                }
            }
        }
    }

    #[test]
    fn constant_image_stays_constant() {
        let img = RgbImage::from_pixel(37, 23, image::Rgb([10, 200, 255]));
        for f in [Filter::Bilinear, Filter::Bicubic] {
            let r = resize_rgb(&img, 101, 9, f).unwrap();
            assert!(r.pixels().all(|p| p.0 == [10, 200, 255]), "{f:?}");
        }
    }

    #[test]
    fn downscale_by_two_bilinear_averages_pixel_pairs_with_neighbours() {
        // PIL bilinear 4 -> 2 on a row [0, 100, 200, 40]: support 2, centre 1.0 and 3.0; taps are
        // the triangle over x + 0.5 - centre scaled by 1/2: weights (.25,.75,.75,.25)/2 around.
        let img = RgbImage::from_fn(4, 1, |x, _| {
            let v = [0u8, 100, 200, 40][x as usize];
            image::Rgb([v, v, v])
        });
        let r = resize_rgb(&img, 2, 1, Filter::Bilinear).unwrap();
        // out0: taps x=0..2 (centre 1): w = 1-|x+0.5-1|/2 -> .75,.75,.25 -> (0*.75+100*.75+200*.25)/1.75
        let e0 = ((100.0 * 0.75 + 200.0 * 0.25) / 1.75f64).round() as u8;
        // out1: taps x=1..4 (centre 3): .25,.75,.75 -> (100*.25+200*.75+40*.75)/1.75
        let e1 = ((100.0 * 0.25 + 200.0 * 0.75 + 40.0 * 0.75) / 1.75f64).round() as u8;
        assert_eq!(r.get_pixel(0, 0).0[0], e0);
        assert_eq!(r.get_pixel(1, 0).0[0], e1);
    }

    /// Pillow 13.0.0 `Image.fromarray(pattern).resize((W, H), filter)` on the integer pattern
    /// `(3x² + 7y + 85c + xy) mod 256`: sum, index-weighted checksum (`Σ v · (i mod 251)` over the
    /// row-major HWC buffer) and the first 4 pixels of row `H / 2`, computed in Python.
    #[test]
    fn resize_matches_pillow_bit_for_bit() {
        type Case = (u32, u32, u32, u32, Filter, i64, i64, [u8; 12]);
        let cases: [Case; 6] = [
            // 244x491 -> 224x450: height shrinks by 41 > 2 * 20 pixels: vertical pass first.
            (
                244,
                491,
                224,
                450,
                Filter::Bicubic,
                38_582_273,
                4_822_558_280,
                [182, 9, 96, 175, 19, 89, 174, 98, 88, 181, 0, 95],
            ),
            (
                37,
                23,
                101,
                9,
                Filter::Bicubic,
                345_189,
                42_844_360,
                [76, 161, 255, 77, 162, 236, 81, 166, 185, 87, 172, 117],
            ),
            (
                990,
                742,
                1024,
                767,
                Filter::Bilinear,
                300_770_448,
                37_596_274_687,
                [34, 119, 204, 145, 230, 72, 30, 115, 179, 133, 218, 77],
            ),
            (
                491,
                244,
                450,
                224,
                Filter::Bicubic,
                38_593_068,
                4_823_584_110,
                [97, 160, 15, 193, 59, 108, 115, 145, 33, 202, 94, 103],
            ),
            (
                50,
                300,
                224,
                1344,
                Filter::Bicubic,
                115_130_766,
                14_385_236_018,
                [6, 122, 205, 13, 116, 200, 28, 104, 189, 59, 78, 166],
            ),
            (
                300,
                200,
                17,
                31,
                Filter::Bilinear,
                201_865,
                24_383_270,
                [127, 128, 125, 129, 125, 129, 123, 129, 127, 125, 129, 128],
            ),
        ];
        for (w, h, ow, oh, f, sum, check, row) in cases {
            let img = RgbImage::from_fn(w, h, |x, y| {
                let v = |c: u32| ((3 * x * x + 7 * y + 85 * c + x * y) % 256) as u8;
                image::Rgb([v(0), v(1), v(2)])
            });
            let r = resize_rgb(&img, ow, oh, f).unwrap();
            let raw = r.as_raw();
            let s: i64 = raw.iter().map(|&v| i64::from(v)).sum();
            let c: i64 = raw
                .iter()
                .enumerate()
                .map(|(i, &v)| i64::from(v) * (i % 251) as i64)
                .sum();
            let start = (oh / 2 * ow * 3) as usize;
            assert_eq!((s, c), (sum, check), "{w}x{h} -> {ow}x{oh} {f:?}");
            assert_eq!(&raw[start..start + 12], &row, "{w}x{h} -> {ow}x{oh} {f:?}");
        }
    }

    #[test]
    fn shapes_follow_torchvision_and_segment_anything() {
        assert_eq!(sam_preprocess_shape(742, 990, 1024), (767, 1024));
        assert_eq!(shortest_side_shape(244, 491, 224), (224, 450));
        assert_eq!(shortest_side_shape(491, 244, 224), (450, 224));
        assert_eq!(center_offset(225, 224), 0); // round(0.5) = 0 (half-even)
        assert_eq!(center_offset(227, 224), 2); // round(1.5) = 2
        assert_eq!(center_offset(450, 224), 113);
    }
}
