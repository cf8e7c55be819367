//! Derives the embedded default scene `data/snowmiku-mini` from the full snowmiku scene.
//!
//! ```text
//! cargo run --example make_default_scene -- ../shared/scenes/snowmiku data/snowmiku-mini
//! ```
//!
//! Deterministic: the same input gives byte-identical output. What it does is written to
//! `<dst>/SOURCE.md` (see [`source_md`]).

use std::error::Error;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use glam::{DQuat, DVec3};
use image::codecs::jpeg::JpegEncoder;
use image::imageops::FilterType;
use slag_common::camera::{Intrinsics, View, colmap, load_views, subsample};
use slag_common::scene::{Gaussians, PlyLoadOptions, ShCoeffs, load_ply, write_ply};

/// Keep views 0, 8, 16, ... of the name-sorted list.
const EVERY: usize = 8;
/// Image (and intrinsics) scale.
const SCALE: f64 = 0.5;
/// JPEG quality of the downscaled images.
const JPEG_QUALITY: u8 = 90;
/// At most this many Gaussians are kept.
const MAX_GAUSSIANS: usize = 60_000;

type Res<T> = Result<T, Box<dyn Error>>;

fn main() -> Res<()> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() != 3 {
        return Err("usage: make_default_scene <snowmiku scene dir> <output dir>".into());
    }
    let (src, dst) = (PathBuf::from(&args[1]), PathBuf::from(&args[2]));
    let all = load_views(&src)?;
    let total_views = all.len();
    let views = subsample(all, EVERY);
    std::fs::create_dir_all(dst.join("images"))?;
    std::fs::create_dir_all(dst.join("sparse").join("0"))?;

    // Images, half size.
    let mut small: Vec<Intrinsics> = Vec::new();
    for v in &views {
        let img = image::open(&v.image_path)?.to_rgb8();
        if (img.width(), img.height()) != (v.intrinsics.width, v.intrinsics.height) {
            return Err(format!("{}: size differs from its camera", v.image_path.display()).into());
        }
        let k = v.intrinsics.scaled(SCALE);
        let resized = image::imageops::resize(&img, k.width, k.height, FilterType::Lanczos3);
        let out = std::fs::File::create(dst.join("images").join(&v.name))?;
        let mut out = std::io::BufWriter::new(out);
        JpegEncoder::new_with_quality(&mut out, JPEG_QUALITY).encode_image(&resized)?;
        small.push(k);
    }

    // COLMAP text model: one PINHOLE camera per distinct intrinsics, same poses.
    let mut cams: Vec<Intrinsics> = Vec::new();
    let mut images_txt = String::from(
        "# Image list with two lines of data per image:\n\
         #   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n\
         #   POINTS2D[] as (X, Y, POINT3D_ID) (empty: no 2D points)\n",
    );
    for (i, (v, k)) in views.iter().zip(&small).enumerate() {
        let cam = match cams.iter().position(|c| c == k) {
            Some(c) => c,
            None => {
                cams.push(*k);
                cams.len() - 1
            }
        };
        let mut q = DQuat::from_mat3(&v.world_to_camera.rotation).normalize();
        if q.w < 0.0 {
            q = -q;
        }
        let t = v.world_to_camera.translation;
        images_txt.push_str(&colmap::images_txt_entry(i + 1, q, t, cam + 1, &v.name));
    }
    let mut cameras_txt = String::from(
        "# Camera list with one line of data per camera:\n\
         #   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[] (PINHOLE: fx fy cx cy)\n",
    );
    for (c, k) in cams.iter().enumerate() {
        writeln!(
            cameras_txt,
            "{} PINHOLE {} {} {} {} {} {}",
            c + 1,
            k.width,
            k.height,
            k.fx,
            k.fy,
            k.cx,
            k.cy
        )?;
    }
    std::fs::write(dst.join("sparse/0/cameras.txt"), cameras_txt)?;
    std::fs::write(dst.join("sparse/0/images.txt"), images_txt)?;

    // Gaussians: the MAX_GAUSSIANS with the largest opacity-weighted projected footprint.
    let g = load_ply(
        &src.join("point_cloud.ply"),
        PlyLoadOptions { colours: true },
    )?;
    let scores = footprint_scores(&g, &views, &small);
    let mut order: Vec<usize> = (0..g.len()).filter(|&i| scores[i] > 0.0).collect();
    order.sort_by(|&a, &b| scores[b].total_cmp(&scores[a]).then(a.cmp(&b)));
    let seen = order.len();
    order.truncate(MAX_GAUSSIANS);
    let total: f64 = scores.iter().sum();
    let retained = order.iter().map(|&i| scores[i]).sum::<f64>() / total;
    order.sort_unstable();
    let sh = g.sh.as_ref().ok_or("no SH colours")?;
    let mini = Gaussians {
        means: order.iter().map(|&i| g.means[i]).collect(),
        scales: order.iter().map(|&i| g.scales[i]).collect(),
        rotations: order.iter().map(|&i| g.rotations[i]).collect(),
        opacities: order.iter().map(|&i| g.opacities[i]).collect(),
        sh: Some(ShCoeffs {
            degree: 0,
            coeffs: order.iter().flat_map(|&i| sh.dc(i)).collect(),
        }),
    };
    write_ply(&dst.join("point_cloud.ply"), &mini)?;

    std::fs::copy(src.join("LICENSE"), dst.join("LICENSE"))?;
    std::fs::write(
        dst.join("SOURCE.md"),
        source_md(
            &src,
            total_views,
            &views,
            &small,
            [g.len(), seen, mini.len()],
            retained,
            sh.degree,
        ),
    )?;
    println!(
        "{}: {} of {} views at {}x{}, {} of {} Gaussians ({seen} seen, {:.1}% of the footprint score)",
        dst.display(),
        views.len(),
        total_views,
        small[0].width,
        small[0].height,
        mini.len(),
        g.len(),
        100.0 * retained
    );
    Ok(())
}

/// Per Gaussian, `Σ_views opacity · min(π fx fy s1 s2 / z², W·H)`: its opacity times the pixel area
/// of its projected footprint (s1, s2 = its two largest standard deviations, z = depth; a
/// face-on approximation of the EWA-splatted ellipse), summed over the kept views where its centre
/// is in front of the camera (z > 0.05) and within 3 projected radii of the image. A Gaussian no
/// kept view sees scores 0 and is dropped.
fn footprint_scores(g: &Gaussians, views: &[View], ks: &[Intrinsics]) -> Vec<f64> {
    let mut scores = vec![0f64; g.len()];
    for (v, k) in views.iter().zip(ks) {
        let (w, h) = (k.width as f64, k.height as f64);
        for (i, score) in scores.iter_mut().enumerate() {
            let m = g.means[i];
            let p = v.world_to_camera.rotation * DVec3::new(m[0] as f64, m[1] as f64, m[2] as f64)
                + v.world_to_camera.translation;
            if p.z <= 0.05 {
                continue;
            }
            let mut s = g.scales[i].map(|x| x as f64);
            s.sort_by(|a, b| b.total_cmp(a));
            let r = 3.0 * k.fx.max(k.fy) * s[0] / p.z;
            let (u, vv) = (k.fx * p.x / p.z + k.cx, k.fy * p.y / p.z + k.cy);
            if u < -r || u > w + r || vv < -r || vv > h + r {
                continue;
            }
            let area = (std::f64::consts::PI * k.fx * k.fy * s[0] * s[1] / (p.z * p.z)).min(w * h);
            *score += g.opacities[i] as f64 * area;
        }
    }
    scores
}

fn source_md(
    src: &Path,
    total_views: usize,
    views: &[View],
    ks: &[Intrinsics],
    [total_gaussians, seen, kept]: [usize; 3],
    retained: f64,
    degree: u8,
) -> String {
    let retained = format!("{:.1}", 100.0 * retained);
    let names: Vec<&str> = views.iter().map(|v| v.name.as_str()).collect();
    let k0 = views[0].intrinsics;
    let k = ks[0];
    format!(
        "# snowmiku-mini: slag's embedded default scene\n\n\
         A small subset of the snowmiku scene (plush on a bed, 97 photos, 3DGS trained with gsplat).\n\n\
         ## Origin and licence\n\n\
         Photos and COLMAP poses: github.com/noname0310/snowmiku2023plush-splat @ \
         70fedae4fe163642ef71489e7e445f21ec0783e2, MIT licence, (c) 2024 noname (see `LICENSE`, a \
         copy of the original). The full scene (images undistorted to PINHOLE and downscaled by 4, \
         sparse/0 rebuilt from the authors' cameras.json, a 120,000-Gaussian point_cloud.ply \
         trained on those images) is slag's `shared/scenes/snowmiku`.\n\n\
         ## Derivation (reproducible, deterministic)\n\n\
         ```\ncargo run --example make_default_scene -- {src} data/snowmiku-mini\n```\n\n\
         (`common/examples/make_default_scene.rs`)\n\n\
         - Views: every {EVERY}th of the {total_views} name-sorted views (indices 0, {EVERY}, \
         {e2}, ...): {n} images: {names}.\n\
         - Images: decoded, resized from {w0}x{h0} to {w}x{h} (scale {SCALE}, Lanczos3), \
         re-encoded as baseline JPEG quality {JPEG_QUALITY} (`image` crate) under `images/`.\n\
         - `sparse/0/cameras.txt`: PINHOLE with the original intrinsics scaled by the exact size \
         ratio (fx {fx0} -> {fx}, fy {fy0} -> {fy}, cx {cx0} -> {cx}, cy {cy0} -> {cy}).\n\
         - `sparse/0/images.txt`: the same world-to-camera poses (quaternion recomputed from the \
         rotation matrix, qw >= 0), image ids renumbered 1..{n}, no 2D points.\n\
         - `point_cloud.ply`: binary little-endian, INRIA properties `x y z f_dc_0..2 opacity \
         scale_0..2 rot_0..3` (SH degree 0: the DC colour only; the source has degree {degree}). \
         {kept} of the {total_gaussians} Gaussians: those with the largest opacity-weighted \
         projected footprint summed over the kept views, `Σ_views sigmoid(opacity) · min(π fx fy \
         s1 s2 / z², W·H)` (s1, s2 the two largest scales, z the depth; a view counts when the \
         centre is in front of it and within 3 projected radii of the image; ties broken by \
         index), stored in their original order. {seen} Gaussians are seen by the kept views; the kept \
         ones carry {retained}% of the summed score. Unseen Gaussians are dropped; big, opaque, \
         often-visible splats, which make most of the rendered pixels, are kept.\n",
        src = src.display(),
        e2 = 2 * EVERY,
        n = views.len(),
        names = names.join(", "),
        w0 = k0.width,
        h0 = k0.height,
        w = k.width,
        h = k.height,
        fx0 = k0.fx,
        fy0 = k0.fy,
        cx0 = k0.cx,
        cy0 = k0.cy,
        fx = k.fx,
        fy = k.fy,
        cx = k.cx,
        cy = k.cy,
    )
}
