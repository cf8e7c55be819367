//! Synthetic scenes for scale tests: a drone-style survey of a coloured terrain with any number of
//! Gaussians, written as an ordinary scene folder (`point_cloud.ply`, `images/`, `sparse/0/*.txt`)
//! so that `slag-encoder encode` runs on it unchanged.
//!
//! The terrain is the height field `z = A·sin(x/λ)·cos(y/λ)` over a square of side `extent`
//! (scene units, read as metres) centred on the origin, z up, painted in a 4 × 3 grid of the 12
//! colour-clip colours, so colour prompts have a ground truth here too. Gaussians are flat discs
//! on the terrain, spaced `extent / √N`. Cameras fly a ring at `0.6 · extent` height, looking at
//! points on the ground, COLMAP/OpenCV camera axes (x right, y down, z forward), PINHOLE.
//! Each image is the terrain colour at the ray's ground hit (ray-cast against the plane z = 0, with
//! a little texture), so masks follow the colour patches the Gaussians carry.

use std::io::Write;
use std::path::Path;

use glam::{DMat3, DQuat, DVec3};
use rayon::prelude::*;
use slag_common::rng::SplitMix64;
use slag_common::scene::{Gaussians, ShCoeffs, write_ply};
use slag_common::{Error, Result};

/// The 12 colour-clip colours (sRGB in [0, 1]) painting the terrain's 4 × 3 patches, in
/// color-clip's class order: red orange yellow green teal blue purple pink brown white gray black.
pub const PALETTE: [[f32; 3]; 12] = [
    [0.85, 0.10, 0.10],
    [0.95, 0.55, 0.10],
    [0.95, 0.90, 0.15],
    [0.15, 0.65, 0.20],
    [0.10, 0.60, 0.60],
    [0.15, 0.25, 0.85],
    [0.50, 0.20, 0.65],
    [0.95, 0.60, 0.75],
    [0.50, 0.30, 0.15],
    [0.97, 0.97, 0.97],
    [0.50, 0.50, 0.50],
    [0.05, 0.05, 0.05],
];

/// Size of a synthetic scene.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SyntheticSceneParams {
    /// Number of Gaussians N.
    pub gaussians: usize,
    /// Number of posed views.
    pub views: usize,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Side of the square terrain, scene units (metres).
    pub extent: f64,
    /// Seed of the deterministic generator.
    pub seed: u64,
}

impl Default for SyntheticSceneParams {
    fn default() -> Self {
        Self {
            gaussians: 1_000_000,
            views: 16,
            width: 990,
            height: 742,
            extent: 100.0,
            seed: 1,
        }
    }
}

/// Terrain height at (x, y): amplitude 2 % of the extent, wavelength 1/6 of it.
fn height(x: f64, y: f64, extent: f64) -> f64 {
    let l = extent / (6.0 * std::f64::consts::TAU);
    0.02 * extent * (x / l).sin() * (y / l).cos()
}

/// Palette index of the patch holding ground point (x, y).
fn patch(x: f64, y: f64, extent: f64) -> usize {
    let u = ((x / extent + 0.5) * 4.0).floor().clamp(0.0, 3.0) as usize;
    let v = ((y / extent + 0.5) * 3.0).floor().clamp(0.0, 2.0) as usize;
    v * 4 + u
}

/// The Gaussians of the terrain (with SH DC colours), deterministic in `p.seed`.
pub fn terrain_gaussians(p: &SyntheticSceneParams) -> Gaussians {
    const SH_C0: f64 = 0.282_094_791_773_878_14;
    let n = p.gaussians;
    let spacing = p.extent / (n.max(1) as f64).sqrt();
    // Chunks with their own seeds so generation is parallel and still deterministic.
    const CHUNK: usize = 1 << 16;
    let parts: Vec<_> = (0..n.div_ceil(CHUNK))
        .into_par_iter()
        .map(|c| {
            let mut rng = SplitMix64::new(p.seed ^ (c as u64).wrapping_mul(0xD1B5_4A32_D192_ED03));
            let len = CHUNK.min(n - c * CHUNK);
            let mut out = Vec::with_capacity(len);
            for _ in 0..len {
                let x = (rng.next_f64() - 0.5) * p.extent;
                let y = (rng.next_f64() - 0.5) * p.extent;
                let z = height(x, y, p.extent);
                let s = spacing * (0.6 + 0.8 * rng.next_f64());
                // A disc lying on the ground: thin along z, random spin about z.
                let a = rng.next_f64() * std::f64::consts::PI;
                let rot = [(a * 0.5).cos() as f32, 0.0, 0.0, (a * 0.5).sin() as f32];
                let col = PALETTE[patch(x, y, p.extent)];
                let jitter = 0.9 + 0.2 * rng.next_f64();
                let dc = col.map(|c| (((c as f64 * jitter).min(1.0) - 0.5) / SH_C0) as f32);
                let opacity = (0.6 + 0.35 * rng.next_f64()) as f32;
                out.push((
                    [x as f32, y as f32, z as f32],
                    [s as f32, s as f32, (s * 0.1) as f32],
                    rot,
                    opacity,
                    dc,
                ));
            }
            out
        })
        .collect();
    let mut g = Gaussians {
        means: Vec::with_capacity(n),
        scales: Vec::with_capacity(n),
        rotations: Vec::with_capacity(n),
        opacities: Vec::with_capacity(n),
        sh: None,
    };
    let mut dc = Vec::with_capacity(n * 3);
    for (m, s, r, o, d) in parts.into_iter().flatten() {
        g.means.push(m);
        g.scales.push(s);
        g.rotations.push(r);
        g.opacities.push(o);
        dc.extend_from_slice(&d);
    }
    g.sh = Some(ShCoeffs {
        degree: 0,
        coeffs: dc,
    });
    g
}

/// One view: world-to-camera rotation (rows = camera x right, y down, z forward in world
/// coordinates) and camera centre, world frame.
fn camera(i: usize, p: &SyntheticSceneParams) -> (DMat3, DVec3) {
    let a = std::f64::consts::TAU * i as f64 / p.views.max(1) as f64;
    let r = 0.35 * p.extent;
    let centre = DVec3::new(r * a.cos(), r * a.sin(), 0.6 * p.extent);
    // Look at a ground point on the ring's far side of the centre: oblique, drone-like.
    let target = DVec3::new(-0.15 * p.extent * a.cos(), -0.15 * p.extent * a.sin(), 0.0);
    let fwd = (target - centre).normalize();
    let right = fwd.cross(DVec3::Z).normalize();
    let down = fwd.cross(right);
    (DMat3::from_cols(right, down, fwd).transpose(), centre)
}

/// Focal length (pixels) giving a 60° horizontal field of view.
fn focal(p: &SyntheticSceneParams) -> f64 {
    p.width as f64 / (2.0 * (30f64).to_radians().tan())
}

/// The image of view `i`: per pixel, the colour of the ground patch its ray meets (plane z = 0),
/// with a faint per-Gaussian-spacing texture; pixels above the horizon are sky white.
fn render_image(i: usize, p: &SyntheticSceneParams) -> image::RgbImage {
    let (r, c) = camera(i, p);
    let rt = r.transpose();
    let f = focal(p);
    let (cx, cy) = (p.width as f64 / 2.0, p.height as f64 / 2.0);
    let mut img = image::RgbImage::new(p.width, p.height);
    let w = p.width as usize;
    let buf: &mut [u8] = &mut img;
    buf.par_chunks_mut(w * 3).enumerate().for_each(|(y, row)| {
        for x in 0..w {
            let d = rt * DVec3::new((x as f64 + 0.5 - cx) / f, (y as f64 + 0.5 - cy) / f, 1.0);
            let rgb = if d.z < -1e-9 {
                let t = -c.z / d.z;
                let g = c + d * t;
                if g.x.abs() <= p.extent / 2.0 && g.y.abs() <= p.extent / 2.0 {
                    let k = 0.95 + 0.05 * ((g.x * 7.0).sin() * (g.y * 7.0).cos());
                    PALETTE[patch(g.x, g.y, p.extent)].map(|v| (v as f64 * k).min(1.0))
                } else {
                    [0.35, 0.35, 0.35]
                }
            } else {
                [1.0, 1.0, 1.0]
            };
            for ch in 0..3 {
                row[3 * x + ch] = (rgb[ch] * 255.0).round() as u8;
            }
        }
    });
    img
}

/// What [`write_synthetic_scene`] wrote.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SyntheticSummary {
    /// Gaussians in `point_cloud.ply`.
    pub gaussians: usize,
    /// Posed views.
    pub views: usize,
    /// Bytes of `point_cloud.ply`.
    pub ply_bytes: u64,
}

/// Writes a synthetic scene folder at `dir`: `point_cloud.ply` (INRIA layout, SH degree 0),
/// `images/view_XXXX.png` and `sparse/0/{cameras,images,points3D}.txt` (COLMAP text, one PINHOLE
/// camera, world-to-camera poses). Every file is written whole before the next starts;
/// `sparse/0/images.txt` is written last, so a folder without it is incomplete.
///
/// Errors: [`Error::Param`] (the field) for zero Gaussians/views, an empty image size or a
/// non-positive extent; I/O errors naming the path.
pub fn write_synthetic_scene(dir: &Path, p: &SyntheticSceneParams) -> Result<SyntheticSummary> {
    for (name, v) in [
        ("gaussians", p.gaussians),
        ("views", p.views),
        ("width", p.width as usize),
        ("height", p.height as usize),
    ] {
        if v == 0 {
            return Err(Error::param(
                name,
                0,
                "at least 1 (a synthetic scene needs Gaussians, views and a non-empty image size)",
            ));
        }
    }
    if !(p.extent.is_finite() && p.extent > 0.0) {
        return Err(Error::param(
            "extent",
            p.extent,
            "a positive number of metres",
        ));
    }
    let images = dir.join("images");
    let sparse = dir.join("sparse").join("0");
    for d in [&images, &sparse] {
        std::fs::create_dir_all(d).map_err(|e| Error::io(d, e))?;
    }
    // Stale poses first: an interrupted rewrite must not look complete.
    let images_txt = sparse.join("images.txt");
    if images_txt.exists() {
        std::fs::remove_file(&images_txt).map_err(|e| Error::io(&images_txt, e))?;
    }
    let g = terrain_gaussians(p);
    let ply = dir.join("point_cloud.ply");
    write_ply(&ply, &g)?;
    drop(g);
    for i in 0..p.views {
        let path = images.join(format!("view_{i:04}.png"));
        render_image(i, p)
            .save(&path)
            .map_err(|e| Error::io(&path, std::io::Error::other(e)))?;
    }
    let f = focal(p);
    let cameras = format!(
        "# Camera list: CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n1 PINHOLE {} {} {f} {f} {} {}\n",
        p.width,
        p.height,
        p.width as f64 / 2.0,
        p.height as f64 / 2.0
    );
    write_file(&sparse.join("cameras.txt"), cameras.as_bytes())?;
    write_file(&sparse.join("points3D.txt"), b"# no points\n")?;
    let mut poses = String::from("# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n");
    for i in 0..p.views {
        let (r, c) = camera(i, p);
        let q = DQuat::from_mat3(&r).normalize();
        let t = -(r * c);
        poses.push_str(&format!(
            "{} {} {} {} {} {} {} {} 1 view_{i:04}.png\n\n",
            i + 1,
            q.w,
            q.x,
            q.y,
            q.z,
            t.x,
            t.y,
            t.z
        ));
    }
    write_file(&images_txt, poses.as_bytes())?;
    let ply_bytes = std::fs::metadata(&ply)
        .map_err(|e| Error::io(&ply, e))?
        .len();
    Ok(SyntheticSummary {
        gaussians: p.gaussians,
        views: p.views,
        ply_bytes,
    })
}

fn write_file(path: &Path, bytes: &[u8]) -> Result<()> {
    let mut f = std::fs::File::create(path).map_err(|e| Error::io(path, e))?;
    f.write_all(bytes).map_err(|e| Error::io(path, e))?;
    f.sync_all().map_err(|e| Error::io(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raster::{CpuRasterizer, WeightRasterizer, raster_intrinsics};

    #[test]
    fn synthetic_scene_loads_and_its_views_see_the_terrain() {
        let dir = tempfile::tempdir().expect("tempdir");
        let p = SyntheticSceneParams {
            gaussians: 20_000,
            views: 3,
            width: 160,
            height: 120,
            extent: 50.0,
            seed: 7,
        };
        let s = write_synthetic_scene(dir.path(), &p).expect("write");
        assert_eq!((s.gaussians, s.views), (20_000, 3));
        let g = slag_common::scene::load_ply(
            &dir.path().join("point_cloud.ply"),
            slag_common::scene::PlyLoadOptions { colours: true },
        )
        .expect("ply");
        assert_eq!(g.len(), 20_000);
        let views = slag_common::camera::load_views(dir.path()).expect("views");
        assert_eq!(views.len(), 3);
        let mut r = CpuRasterizer::new(&g);
        for v in &views {
            // The camera centre recovered from the written pose is above the terrain.
            let img = image::open(&v.image_path).expect("image").to_rgb8();
            assert_eq!(img.dimensions(), (160, 120));
            let k = raster_intrinsics(&v.intrinsics, 0.5).expect("intrinsics");
            let w = r.rasterize(&k, &v.world_to_camera).expect("raster");
            // Most pixels look at the terrain, so most are covered by Gaussians.
            let covered = (0..w.height)
                .flat_map(|y| (0..w.width).map(move |x| (x, y)))
                .filter(|&(x, y)| !w.pixel(x, y).0.is_empty())
                .count();
            let total = (w.width * w.height) as usize;
            assert!(
                covered * 2 > total,
                "only {covered} of {total} pixels covered"
            );
            // The Gaussian seen at the image centre has the colour the image shows there.
            let (ids, wts) = w.pixel(w.width / 2, w.height / 2);
            let best = ids
                .iter()
                .zip(wts)
                .max_by(|a, b| a.1.total_cmp(b.1))
                .map(|(&i, _)| i as usize)
                .expect("centre pixel covered");
            let sh = g.sh.as_ref().expect("colours");
            let dc = sh.dc(best);
            let rgb = dc.map(|c| 0.5 + 0.282_094_8 * c);
            let px = img.get_pixel(img.width() / 2, img.height() / 2).0;
            for ch in 0..3 {
                assert!(
                    (rgb[ch] - px[ch] as f32 / 255.0).abs() < 0.2,
                    "centre colour {rgb:?} vs image {px:?}"
                );
            }
        }
    }

    #[test]
    fn bad_sizes_are_refused() {
        let dir = tempfile::tempdir().expect("tempdir");
        let p = SyntheticSceneParams {
            gaussians: 0,
            ..Default::default()
        };
        assert!(matches!(
            write_synthetic_scene(dir.path(), &p),
            Err(Error::Param {
                name: "gaussians",
                ..
            })
        ));
        let p = SyntheticSceneParams {
            extent: f64::NAN,
            gaussians: 10,
            ..Default::default()
        };
        assert!(matches!(
            write_synthetic_scene(dir.path(), &p),
            Err(Error::Param { name: "extent", .. })
        ));
    }
}
