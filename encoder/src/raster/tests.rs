//! Tests of the weight rasterizers: GPU vs the f64 CPU reference (random scenes and the real
//! snowmiku scene), invariants, and a colour render of snowmiku against its training photos.
//!
//! GPU tests run on whatever Vulkan adapter [`GpuRasterizer::new`] picks (lavapipe in CI). Without
//! one they fail, unless `SLAG_SKIP_GPU=1` is set.

use std::path::PathBuf;

use glam::{DMat3, DQuat, DVec3};
use slag_common::camera::{Intrinsics, WorldToCamera};
use slag_common::rng::SplitMix64;
use slag_common::scene::Gaussians;

use super::project::{ALPHA_MIN, Splat2d, T_MIN, TILE_SIZE, splat_alpha};
use super::testdata::{
    gpu_unless_skipped, load_ply_for_test, load_views_for_test, skip_gpu, snowmiku_dir,
};
use super::*;

// ---------------------------------------------------------------------------------------------
// helpers

/// The GPU rasterizer, with noise-filled outputs; `None` only when `SLAG_SKIP_GPU=1`.
pub(super) fn gpu(g: &Gaussians) -> Option<GpuRasterizer> {
    let mut r = gpu_unless_skipped(|| GpuRasterizer::new(g))?;
    r.set_noise_fill(Some(0x5eed));
    Some(r)
}

/// A random scene of `n` Gaussians around the origin: means in front of and behind a camera at
/// z = -4 looking down +z, scales over 4 orders of magnitude, random unit quaternions, opacities
/// including values near 0 and near 1.
pub(super) fn random_scene(seed: u64, n: usize) -> Gaussians {
    let mut r = SplitMix64::new(seed);
    let mut g = Gaussians::default();
    for _ in 0..n {
        g.means.push([
            r.range(-3.0, 3.0) as f32,
            r.range(-2.5, 2.5) as f32,
            r.range(-6.0, 4.0) as f32,
        ]);
        let base = 10f64.powf(r.range(-3.5, 0.0));
        g.scales
            .push([0, 1, 2].map(|_| (base * 10f64.powf(r.range(-1.0, 1.0))) as f32));
        let q = [
            r.range(-1.0, 1.0),
            r.range(-1.0, 1.0),
            r.range(-1.0, 1.0),
            r.range(-1.0, 1.0),
        ];
        let nq = q.iter().map(|v| v * v).sum::<f64>().sqrt().max(1e-9);
        g.rotations.push(q.map(|v| (v / nq) as f32));
        let o = match r.next_u64() % 4 {
            0 => r.range(0.0, 0.01),
            1 => r.range(0.98, 0.9999),
            _ => r.range(0.0, 1.0),
        };
        g.opacities.push(o as f32);
    }
    g
}

fn test_camera(seed: u64) -> (Intrinsics, WorldToCamera) {
    let mut r = SplitMix64::new(seed ^ 0xCA3E);
    let k = Intrinsics {
        width: 160 + (seed % 3) as u32 * 17,
        height: 120 + (seed % 2) as u32 * 9,
        fx: 140.0,
        fy: 150.0,
        cx: 83.0,
        cy: 61.5,
    };
    // Camera centre near (0, 0, -4), small random rotation.
    let rot = DMat3::from_quat(DQuat::from_euler(
        glam::EulerRot::XYZ,
        r.range(-0.2, 0.2),
        r.range(-0.2, 0.2),
        r.range(-0.3, 0.3),
    ));
    let centre = DVec3::new(r.range(-0.3, 0.3), r.range(-0.3, 0.3), -4.0);
    (
        k,
        WorldToCamera {
            rotation: rot,
            translation: -(rot * centre),
        },
    )
}

#[derive(Debug, Default)]
struct Agreement {
    _pixels: usize,
    identical_lists: usize,
    explained: usize,
    _entries: usize,
    max_weight_diff: f64,
    why: std::collections::BTreeMap<String, usize>,
}

/// Why a contributor may legitimately differ between f32 (GPU) and f64 (reference) at a pixel:
/// a value within f32 error of a decision threshold.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum Border {
    /// `α` within f32 error of `1/255`.
    Alpha,
    /// The next transmittance within f32 error of `1e-4`.
    Transmittance,
    /// The radius (before `ceil`) or a tile-rect edge within f32 error of an integer.
    TileEdge,
}

fn borderline(s: Option<&Splat2d>, px: f64, py: f64, t_before: f64) -> Option<Border> {
    let s = s?;
    let (sigma, alpha) = splat_alpha(s, px, py);
    let rel = |a: f64, b: f64| ((a - b) / b).abs();
    // f32 relative error of exp(-σ) grows with σ.
    if sigma >= 0.0 && rel(alpha, ALPHA_MIN) < 1e-4 * (1.0 + sigma) {
        return Some(Border::Alpha);
    }
    // The f32 product of up to a few thousand (1 - α) factors.
    if rel(t_before * (1.0 - alpha), T_MIN) < 1e-3 {
        return Some(Border::Transmittance);
    }
    let m = s.cov2d;
    let mid = 0.5 * (m[0] + m[2]);
    let det = m[0] * m[2] - m[1] * m[1];
    let r_exact = 3.0 * (mid + (mid * mid - det).max(0.01).sqrt()).sqrt();
    let near_int = |v: f64| (v - v.round()).abs() < 1e-4 * v.abs().max(1.0);
    let ts = TILE_SIZE as f64;
    let edges = [
        (s.mean2d[0] - s.radius) / ts,
        (s.mean2d[1] - s.radius) / ts,
        (s.mean2d[0] + s.radius) / ts,
        (s.mean2d[1] + s.radius) / ts,
    ];
    if near_int(r_exact) || edges.iter().any(|&e| near_int(e)) {
        return Some(Border::TileEdge);
    }
    None
}

/// Compares GPU output to the CPU reference pixel by pixel: identical id lists with weights within
/// 1e-4, except pixels whose first difference is explained by [`borderline`] or by an exact depth
/// tie; those are counted and must stay rare.
fn compare(
    gpu: &PixelWeights,
    cpu: &PixelWeights,
    splats: &[Option<Splat2d>],
    label: &str,
) -> Agreement {
    let n_pix = assert_same_csr_shape(gpu, cpu, label);
    let mut a = Agreement {
        _pixels: n_pix,
        _entries: cpu.ids.len(),
        ..Default::default()
    };
    for y in 0..cpu.height {
        for x in 0..cpu.width {
            let p = (y * cpu.width + x) as usize;
            assert!(
                gpu.offsets[p] <= gpu.offsets[p + 1],
                "{label}: offsets not monotone at {p}"
            );
            let (gi, gw) = gpu.pixel(x, y);
            let (ci, cw) = cpu.pixel(x, y);
            let px = PixelPair {
                x,
                y,
                gpu: (gi, gw),
                cpu: (ci, cw),
            };
            let first_diff = (0..gi.len().max(ci.len())).find(|&e| gi.get(e) != ci.get(e));
            let upto = first_diff.unwrap_or(gi.len());
            a.max_weight_diff = a.max_weight_diff.max(px.max_weight_diff(upto, label));
            let Some(e) = first_diff else {
                a.identical_lists += 1;
                continue;
            };
            let why = px.explain_difference(e, splats, label);
            a.explained += 1;
            *a.why.entry(why).or_default() += 1;
        }
    }
    eprintln!("{label}: {a:?}");
    assert!(
        a.explained as f64 <= 1e-3 * n_pix as f64 + 2.0,
        "{label}: {} of {} pixels differ (all at thresholds) — more than expected",
        a.explained,
        n_pix
    );
    a
}

/// Shape step of [`compare`]: same raster size, a CSR offsets array with one entry per pixel
/// plus one, starting at 0 and ending at the entry count; returns the pixel count.
fn assert_same_csr_shape(gpu: &PixelWeights, cpu: &PixelWeights, label: &str) -> usize {
    assert_eq!(
        (gpu.width, gpu.height),
        (cpu.width, cpu.height),
        "{label}: size"
    );
    let n_pix = (cpu.width * cpu.height) as usize;
    assert_eq!(gpu.offsets.len(), n_pix + 1, "{label}: offsets length");
    assert_eq!(gpu.offsets[0], 0, "{label}: first offset");
    assert_eq!(
        *gpu.offsets.last().expect("non-empty") as usize,
        gpu.ids.len(),
        "{label}: last offset"
    );
    assert_eq!(gpu.ids.len(), gpu.weights.len(), "{label}: ids/weights");
    n_pix
}

/// One pixel's contributor lists (ids, weights) from the GPU and the CPU reference.
struct PixelPair<'a> {
    x: u32,
    y: u32,
    gpu: (&'a [u32], &'a [f32]),
    cpu: (&'a [u32], &'a [f32]),
}

impl PixelPair<'_> {
    /// Weight step of [`compare`]: the entries before `upto` (same ids) agree within 1e-4;
    /// returns their largest difference.
    fn max_weight_diff(&self, upto: usize, label: &str) -> f64 {
        let ((gi, gw), (_, cw), (x, y)) = (self.gpu, self.cpu, (self.x, self.y));
        let mut max = 0.0f64;
        for e in 0..upto {
            let d = (gw[e] as f64 - cw[e] as f64).abs();
            max = max.max(d);
            assert!(
                d <= 1e-4,
                "{label}: pixel ({x},{y}) entry {e} id {}: gpu weight {} vs cpu {}",
                gi[e],
                gw[e],
                cw[e]
            );
        }
        max
    }

    /// Explanation step of [`compare`]: the lists' first difference, at entry `e`, is an exact
    /// depth tie or a contributor at a threshold ([`borderline`], transmittance replayed in f64);
    /// returns which, as the key of [`Agreement::why`].
    fn explain_difference(&self, e: usize, splats: &[Option<Splat2d>], label: &str) -> String {
        let ((gi, gw), (ci, cw), (x, y)) = (self.gpu, self.cpu, (self.x, self.y));
        let (px, py) = (x as f64 + 0.5, y as f64 + 0.5);
        // Transmittance before entry e, replayed in f64 from the reference's splats.
        let t_before: f64 = ci[..e]
            .iter()
            .map(|&id| splats[id as usize].map_or(1.0, |s| 1.0 - splat_alpha(&s, px, py).1))
            .product();
        let cand: Vec<u32> = [gi.get(e), ci.get(e)]
            .into_iter()
            .flatten()
            .copied()
            .collect();
        let depth = |id: u32| splats[id as usize].map(|s| s.depth);
        let tie = cand.len() == 2
            && matches!((depth(cand[0]), depth(cand[1])), (Some(d0), Some(d1)) if (d0 - d1).abs() <= 1e-6 * d0.abs().max(1.0));
        let border = cand
            .iter()
            .find_map(|&id| borderline(splats[id as usize].as_ref(), px, py, t_before));
        assert!(
            tie || border.is_some(),
            "{label}: pixel ({x},{y}) differs at entry {e}: gpu {:?} vs cpu {:?} (weights {:?} vs {:?}); splats {:?}",
            &gi[e..gi.len().min(e + 3)],
            &ci[e..ci.len().min(e + 3)],
            &gw[e..gw.len().min(e + 3)],
            &cw[e..cw.len().min(e + 3)],
            cand.iter()
                .map(|&id| splats[id as usize])
                .collect::<Vec<_>>()
        );
        if tie {
            "depth tie".to_string()
        } else {
            format!("{border:?}")
        }
    }
}

/// Invariants every rasterizer output must satisfy.
fn check_invariants(w: &PixelWeights, n: usize, label: &str) {
    let n_pix = (w.width * w.height) as usize;
    assert_eq!(w.offsets.len(), n_pix + 1, "{label}");
    assert_eq!(w.offsets[0], 0, "{label}");
    assert_eq!(w.offsets[n_pix] as usize, w.ids.len(), "{label}");
    assert_eq!(w.ids.len(), w.weights.len(), "{label}");
    for p in 0..n_pix {
        let (a, b) = (w.offsets[p] as usize, w.offsets[p + 1] as usize);
        assert!(a <= b, "{label}: offsets decrease at pixel {p}");
        let sum: f64 = w.weights[a..b].iter().map(|&v| v as f64).sum();
        assert!(sum <= 1.0 + 1e-5, "{label}: pixel {p} weights sum to {sum}");
        let mut seen = std::collections::HashSet::new();
        for e in a..b {
            assert!((w.ids[e] as usize) < n, "{label}: id {} >= {n}", w.ids[e]);
            assert!(
                seen.insert(w.ids[e]),
                "{label}: id {} twice in pixel {p}",
                w.ids[e]
            );
            let v = w.weights[e];
            assert!(v > 0.0 && v <= 1.0, "{label}: weight {v} outside (0, 1]");
        }
    }
}

// ---------------------------------------------------------------------------------------------
// tests

#[test]
fn gpu_matches_cpu_on_random_scenes() {
    for seed in 0..5u64 {
        let g = random_scene(seed, 400 + seed as usize * 300);
        let (k, w2c) = test_camera(seed);
        let mut cpu = CpuRasterizer::new(&g);
        let reference = cpu.rasterize(&k, &w2c).expect("cpu");
        check_invariants(&reference, g.len(), "cpu");
        assert!(
            reference.len() > 1000,
            "seed {seed}: scene too sparse to test ({})",
            reference.len()
        );
        let Some(mut gpu) = gpu(&g) else { continue };
        let out = gpu.rasterize(&k, &w2c).expect("gpu");
        check_invariants(&out, g.len(), "gpu");
        compare(
            &out,
            &reference,
            &cpu.project_all(&k, &w2c),
            &format!("random seed {seed}"),
        );
        // Deterministic: a second run (fresh noise) gives the same bytes.
        gpu.set_noise_fill(Some(seed + 99));
        assert_eq!(
            gpu.rasterize(&k, &w2c).expect("gpu again"),
            out,
            "seed {seed}: not deterministic"
        );
        // Banded write pass (tiny output buffers): same result.
        let row_bytes = |r: u32| {
            let px =
                |row: u32| out.offsets[((row * TILE_SIZE).min(k.height) * k.width) as usize] as u64;
            (px(r + 1) - px(r)) * 4
        };
        let max_row = (0..k.height.div_ceil(TILE_SIZE))
            .map(row_bytes)
            .max()
            .unwrap_or(4);
        gpu.set_band_limit(Some(max_row.max(out.len() as u64 * 4 / 3)));
        assert_eq!(
            gpu.rasterize(&k, &w2c).expect("gpu banded"),
            out,
            "seed {seed}: banding changed output"
        );
        gpu.set_band_limit(None);
        // Another view on the same rasterizer (its write-pass buffers are kept and reused, larger
        // or smaller than this view needs) equals a fresh rasterizer's output.
        let (k2, w2c2) = test_camera(seed + 7);
        let reused = gpu.rasterize(&k2, &w2c2).expect("gpu reused");
        let Some(mut fresh) = self::gpu(&g) else {
            continue;
        };
        assert_eq!(
            reused,
            fresh.rasterize(&k2, &w2c2).expect("gpu fresh"),
            "seed {seed}: reused write-pass buffers changed the output"
        );
    }
}

#[test]
fn empty_and_all_behind_scenes_give_empty_lists() {
    let (k, w2c) = test_camera(7);
    let empty = Gaussians::default();
    let mut behind = random_scene(3, 200);
    for m in &mut behind.means {
        m[2] = -4.0 - m[2].abs() - 0.001; // at or behind the camera centre (z = -4)
    }
    for (label, g) in [("empty", &empty), ("behind", &behind)] {
        let w = CpuRasterizer::new(g).rasterize(&k, &w2c).expect("cpu");
        check_invariants(&w, g.len(), label);
        assert!(
            w.is_empty() && w.offsets.iter().all(|&o| o == 0),
            "{label}: cpu not empty"
        );
        if let Some(mut r) = gpu(g) {
            let w = r.rasterize(&k, &w2c).expect("gpu");
            check_invariants(&w, g.len(), label);
            assert!(
                w.is_empty() && w.offsets.iter().all(|&o| o == 0),
                "{label}: gpu not empty"
            );
        }
    }
}

#[test]
fn single_gaussian_weight_matches_closed_form() {
    // One isotropic Gaussian straight ahead: w at the centre pixel = min(0.99, o·exp(-σ)).
    let g = Gaussians {
        means: vec![[0.0, 0.0, 2.0]],
        scales: vec![[0.05; 3]],
        rotations: vec![[1.0, 0.0, 0.0, 0.0]],
        opacities: vec![0.8],
        sh: None,
    };
    let k = Intrinsics {
        width: 32,
        height: 32,
        fx: 100.0,
        fy: 100.0,
        cx: 16.0,
        cy: 16.0,
    };
    let w2c = WorldToCamera {
        rotation: DMat3::IDENTITY,
        translation: DVec3::ZERO,
    };
    let var = (100.0f64 / 2.0 * 0.05).powi(2) + 0.3;
    let expected = |x: u32, y: u32| {
        let (dx, dy) = (16.0 - (x as f64 + 0.5), 16.0 - (y as f64 + 0.5));
        0.8 * (-0.5 * (dx * dx + dy * dy) / var).exp()
    };
    let mut rs: Vec<Box<dyn WeightRasterizer>> = vec![Box::new(CpuRasterizer::new(&g))];
    if let Some(r) = gpu(&g) {
        rs.push(Box::new(r));
    }
    for r in &mut rs {
        let w = r.rasterize(&k, &w2c).expect("rasterize");
        for (x, y) in [(15, 15), (16, 16), (12, 17), (20, 16)] {
            let (ids, ws) = w.pixel(x, y);
            assert_eq!(ids, &[0], "{} ({x},{y})", r.name());
            assert!(
                (ws[0] as f64 - expected(x, y)).abs() < 1e-6,
                "{}: {} vs {}",
                r.name(),
                ws[0],
                expected(x, y)
            );
        }
    }
}

#[test]
fn raster_intrinsics_checks_the_scale() {
    let k = Intrinsics {
        width: 990,
        height: 742,
        fx: 819.6,
        fy: 819.2,
        cx: 495.0,
        cy: 371.0,
    };
    let h = raster_intrinsics(&k, 0.5).expect("valid");
    assert_eq!((h.width, h.height), (495, 371));
    assert!((h.fx - 409.8).abs() < 1e-9);
    assert!(raster_intrinsics(&k, 0.0).is_err());
    assert!(raster_intrinsics(&k, f64::NAN).is_err());
}

type PosedViews = Vec<(String, Intrinsics, WorldToCamera)>;

fn snowmiku() -> Option<(Gaussians, PosedViews)> {
    let dir = snowmiku_dir();
    let ply = dir.join("point_cloud.ply");
    assert!(
        ply.exists(),
        "{} missing: the shared scene is required",
        ply.display()
    );
    Some((load_ply_for_test(&ply, true), load_views_for_test(&dir)))
}

#[test]
fn gpu_matches_cpu_on_snowmiku() {
    let Some((g, views)) = snowmiku() else { return };
    assert_eq!(g.len(), 120_000);
    let mut cpu = CpuRasterizer::new(&g);
    let mut gpu = gpu(&g);
    for (i, scale) in [(1usize, 0.25), (40, 0.3), (80, 0.25)] {
        let (name, k, w2c) = &views[i];
        let k = raster_intrinsics(k, scale).expect("scale");
        let reference = cpu.rasterize(&k, w2c).expect("cpu");
        check_invariants(&reference, g.len(), name);
        assert!(
            reference.mean_contributors() > 5.0,
            "{name}: suspiciously few contributors"
        );
        if let Some(r) = gpu.as_mut() {
            let out = r.rasterize(&k, w2c).expect("gpu");
            check_invariants(&out, g.len(), name);
            compare(
                &out,
                &reference,
                &cpu.project_all(&k, w2c),
                &format!("snowmiku {name} @{scale}"),
            );
        }
    }
}

#[test]
fn colour_render_of_snowmiku_matches_photos() {
    let Some((g, views)) = snowmiku() else { return };
    if skip_gpu() {
        eprintln!(
            "SLAG_SKIP_GPU=1: colour render test skipped (full resolution needs the GPU path)"
        );
        return;
    }
    let mut r = gpu(&g).expect("gpu");
    let out_dir = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join("target")
        .join("raster-colour");
    std::fs::create_dir_all(&out_dir).expect("out dir");
    let mut psnrs = Vec::new();
    // Training views only: the trainer held out every 8th image (indices 0, 8, ...).
    for i in [1usize, 33, 66] {
        let (name, k, w2c) = &views[i];
        let w = r.rasterize(k, w2c).expect("gpu");
        let img = render_colour(&g, k, w2c, &w).expect("render");
        let photo_path = snowmiku_dir().join("images").join(name);
        let photo = image::open(&photo_path).expect("photo").to_rgb8();
        let p = psnr(&img, &photo).expect("psnr");
        img.save(out_dir.join(name.replace(".jpg", ".png")))
            .expect("save png");
        eprintln!(
            "snowmiku {name}: PSNR {p:.2} dB, {:.1} contributors/pixel",
            w.mean_contributors()
        );
        psnrs.push(p);
        assert!(
            p >= 25.0,
            "{name}: PSNR {p:.2} dB < 25 (render in {})",
            out_dir.display()
        );
    }
    // Control: the same render from a wrong pose must be much worse (the test can fail).
    let (_, k, w2c) = &views[1];
    let (name1, ..) = &views[33];
    let w = r.rasterize(k, w2c).expect("gpu");
    let img = render_colour(&g, k, w2c, &w).expect("render");
    let other = image::open(snowmiku_dir().join("images").join(name1))
        .expect("photo")
        .to_rgb8();
    let p_wrong = psnr(&img, &other).expect("psnr");
    assert!(
        p_wrong < psnrs[0] - 5.0,
        "wrong-pose control PSNR {p_wrong:.2} too high"
    );
}

/// `n` random overlapping masks (discs and boxes) of a `width × height` image; some pixels in
/// none of them.
fn random_masks(seed: u64, width: u32, height: u32, n: usize) -> Vec<crate::masks::Mask> {
    let mut r = SplitMix64::new(seed ^ 0x3A5C);
    (0..n)
        .filter_map(|i| {
            let (cx, cy) = (r.range(0.0, width as f64), r.range(0.0, height as f64));
            let (rx, ry) = (
                r.range(0.08, 0.45) * width as f64,
                r.range(0.08, 0.45) * height as f64,
            );
            let disc = i % 2 == 0;
            let pixels = (0..height)
                .flat_map(|y| (0..width).map(move |x| (x, y)))
                .map(|(x, y)| {
                    let (dx, dy) = ((x as f64 + 0.5 - cx) / rx, (y as f64 + 0.5 - cy) / ry);
                    let inside = if disc {
                        dx * dx + dy * dy <= 1.0
                    } else {
                        dx.abs() <= 1.0 && dy.abs() <= 1.0
                    };
                    u8::from(inside)
                })
                .collect();
            crate::masks::Mask::from_pixels(width, height, pixels)
        })
        .collect()
}

#[test]
fn gpu_label_sums_equal_the_host_image_stage() {
    use crate::aggregate::{ImageStageParams, image_contribution};
    use crate::pipeline::view_contribution;
    for seed in 0..4u64 {
        let g = random_scene(seed, 600 + seed as usize * 250);
        let (k, w2c) = test_camera(seed);
        let Some(mut gpu) = gpu(&g) else { return };
        // Masks at 2x the raster size: the labels resample them like the host stage does.
        let masks = random_masks(seed, k.width * 2, k.height * 2, 7);
        assert!(masks.len() >= 5, "seed {seed}: too few masks");
        let dim = 3;
        let emb: Vec<f32> = (0..masks.len() * dim).map(|i| i as f32).collect();
        let params = ImageStageParams::default();
        let weights = gpu.rasterize(&k, &w2c).expect("gpu lists");
        let host = image_contribution(&weights, &masks, emb.clone(), dim, params).expect("host");
        assert!(
            host.entries.len() > 100,
            "seed {seed}: too few a_kj to test"
        );
        // Seed 0 starts from a 4-record buffer: the view does not fit and is re-run with room
        // for its count. Seed 2 caps one binding at half the view's records: the view is
        // split into bands of tile rows.
        gpu.set_label_records(4, None);
        let (dev, stats) =
            view_contribution(&mut gpu, &k, &w2c, &masks, emb.clone(), dim, params).expect("dev");
        assert!(stats.device_sums, "the GPU rasterizer sums per label");
        assert!(
            gpu.last_label_retries() > 0,
            "seed {seed}: 4 records cannot hold the view"
        );
        let records = gpu.last_label_records();
        assert!(records > 0, "seed {seed}: no records");
        if seed == 2 {
            gpu.set_label_records(4, Some(records / 2));
            let (banded, _) =
                view_contribution(&mut gpu, &k, &w2c, &masks, emb.clone(), dim, params)
                    .expect("banded");
            // The whole view exceeds one binding, so it was split (at least one re-run).
            assert!(gpu.last_label_retries() >= 1, "seed {seed}: bands split");
            assert_eq!(banded, dev, "seed {seed}: banded label sums differ");
        }
        assert_eq!(dev.mask_embeddings, host.mask_embeddings);
        assert_eq!(
            dev.entries.len(),
            host.entries.len(),
            "seed {seed}: a_kj key sets differ"
        );
        // Contributions counted on the device = list entries of labelled pixels.
        let labels = crate::aggregate::pixel_labels(&masks, k.width, k.height);
        let labelled: u64 = (0..labels.labels.len())
            .filter(|&p| labels.labels[p] != 0)
            .map(|p| u64::from(weights.offsets[p + 1] - weights.offsets[p]))
            .sum();
        assert_eq!(stats.contributions, labelled, "seed {seed}");
        for (d, h) in dev.entries.iter().zip(&host.entries) {
            assert_eq!((d.gaussian, d.mask), (h.gaussian, h.mask), "seed {seed}");
            // Fixed point truncates each weight by < 2^-32; f32 storage rounds both.
            let tol = 1e-6 * h.weight.abs().max(1.0) as f64;
            assert!(
                (d.weight as f64 - h.weight as f64).abs() <= tol,
                "seed {seed}: a_kj({}, {}) {} vs host {}",
                d.gaussian,
                d.mask,
                d.weight,
                h.weight
            );
        }
        // The finest covering mask only, and per-mask weighting, with whole and eroded masks:
        // the same labels, expanded and weighted on the host like the list path's.
        for mask_erode in [0, 2].into_iter().filter(|_| seed == 1) {
            let fine = ImageStageParams {
                overlap: crate::aggregate::MaskOverlap::Finest,
                mask_weighting: crate::aggregate::MaskWeighting::Area,
                mask_erode,
                ..params
            };
            let host = image_contribution(&weights, &masks, emb.clone(), dim, fine).expect("host");
            let (dev, stats) =
                view_contribution(&mut gpu, &k, &w2c, &masks, emb.clone(), dim, fine).expect("d");
            assert!(stats.device_sums);
            assert_eq!(
                dev.entries.len(),
                host.entries.len(),
                "finest: key sets differ"
            );
            for (d, h) in dev.entries.iter().zip(&host.entries) {
                assert_eq!((d.gaussian, d.mask), (h.gaussian, h.mask));
                // The unweighted tolerance, scaled by the mask's factor g (a_kj · g).
                let g = crate::aggregate::MaskWeighting::Area.factor(&masks[h.mask as usize]);
                let tol = 1e-6 * h.weight.abs().max(g) as f64;
                assert!(
                    (d.weight as f64 - h.weight as f64).abs() <= tol,
                    "{d:?} vs {h:?}"
                );
            }
        }
        // Deterministic: integer sums do not depend on the threads' order.
        let (again, _) =
            view_contribution(&mut gpu, &k, &w2c, &masks, emb, dim, params).expect("dev again");
        assert_eq!(again, dev, "seed {seed}: label sums not deterministic");
    }
}

#[test]
fn top_k_and_mask_free_views_take_the_list_path() {
    use crate::aggregate::{ImageStageParams, image_contribution};
    use crate::pipeline::view_contribution;
    let g = random_scene(11, 500);
    let (k, w2c) = test_camera(11);
    let Some(mut gpu) = gpu(&g) else { return };
    let masks = random_masks(11, k.width, k.height, 4);
    let emb = vec![0.5f32; masks.len() * 2];
    let params = ImageStageParams {
        top_k_per_pixel: Some(2),
        ..ImageStageParams::default()
    };
    let (c, stats) =
        view_contribution(&mut gpu, &k, &w2c, &masks, emb.clone(), 2, params).expect("top-k");
    assert!(!stats.device_sums, "top-K needs the per-pixel lists");
    let weights = gpu.rasterize(&k, &w2c).expect("lists");
    assert_eq!(
        c,
        image_contribution(&weights, &masks, emb.clone(), 2, params).expect("host")
    );
    let (empty, stats) = view_contribution(
        &mut gpu,
        &k,
        &w2c,
        &[],
        Vec::new(),
        2,
        ImageStageParams::default(),
    )
    .expect("no masks");
    assert!(empty.entries.is_empty() && !stats.device_sums);
    // More visible Gaussians than raster pixels: the GPU still sums per label, same a_kj.
    let tiny = Intrinsics {
        width: 12,
        height: 9,
        fx: k.fx * 12.0 / f64::from(k.width),
        fy: k.fy * 9.0 / f64::from(k.height),
        cx: k.cx * 12.0 / f64::from(k.width),
        cy: k.cy * 9.0 / f64::from(k.height),
    };
    let (c, stats) = view_contribution(
        &mut gpu,
        &tiny,
        &w2c,
        &masks,
        emb.clone(),
        2,
        ImageStageParams::default(),
    )
    .expect("tiny raster");
    assert!(
        stats.device_sums,
        "500 Gaussians on 108 pixels take the GPU sums"
    );
    let weights = gpu.rasterize(&tiny, &w2c).expect("tiny lists");
    assert!(!c.entries.is_empty());
    let host =
        image_contribution(&weights, &masks, emb, 2, ImageStageParams::default()).expect("host");
    assert_eq!(c.entries.len(), host.entries.len());
    for (d, h) in c.entries.iter().zip(&host.entries) {
        assert_eq!((d.gaussian, d.mask), (h.gaussian, h.mask));
        assert!((d.weight as f64 - h.weight as f64).abs() <= 1e-6 * h.weight.max(1.0) as f64);
    }
    // Labels of the wrong size are refused with a typed error.
    let err = gpu
        .label_sums(&k, &w2c, &[1, 2, 3])
        .expect_err("wrong label count");
    assert!(err.to_string().contains("labels"), "{err}");
}

/// The GPU's binning and depth sort of one view against the host reference
/// ([`gpu::project::bin_and_sort`]) on the GPU's own tile rects: every key's depth is the host's
/// f64 depth rounded to f32, the keys are sorted by (tile, depth), the ids equal the host's list
/// sorted by (tile, f32 depth, id) and the host's list itself; the tile ranges are the host's.
/// Returns the intersections and the number of adjacent pairs of a tile with equal f32 depths
/// whose f64 depths are not in id order (where an f64 order would differ).
fn check_gpu_sort(
    r: &mut GpuRasterizer,
    g: &Gaussians,
    k: &Intrinsics,
    w2c: &WorldToCamera,
    label: &str,
) -> (usize, usize) {
    let out = r.sorted_intersections(k, w2c).expect("gpu sort");
    let (tiles_x, tiles_y) = super::project::tile_grid(k.width, k.height);
    let n_tiles = tiles_x * tiles_y;
    let (ranges, ids) = gpu::project::bin_and_sort(&out.rects, &g.means, w2c, tiles_x, n_tiles)
        .expect("host binning");
    assert_eq!(out.ranges, ranges, "{label}: tile ranges");
    assert_eq!(out.ids.len(), ids.len(), "{label}: intersections");
    let depth32 = |id: u32| {
        let d = super::project::camera_point(g.means[id as usize].map(f64::from), w2c).z;
        (d.max(0.0) as f32).to_bits()
    };
    // Keys: the host's tile of each slot, the host's depth rounded to f32, sorted.
    for (t, r) in ranges.iter().enumerate() {
        for e in r[0] as usize..r[1] as usize {
            assert_eq!(out.keys[e][1], t as u32, "{label}: key {e} tile");
        }
    }
    for (e, (key, &id)) in out.keys.iter().zip(&out.ids).enumerate() {
        assert_eq!(
            key[0],
            depth32(id),
            "{label}: key {e} (Gaussian {id}) depth bits"
        );
    }
    assert!(
        out.keys
            .windows(2)
            .all(|w| (w[0][1], w[0][0]) <= (w[1][1], w[1][0])),
        "{label}: keys not sorted"
    );
    // Ids: the host's list with f32 depths, ties by id.
    let mut host32: Vec<(u32, u32, u32)> = ranges
        .iter()
        .enumerate()
        .flat_map(|(t, r)| {
            ids[r[0] as usize..r[1] as usize]
                .iter()
                .map(move |&id| (t as u32, id))
        })
        .map(|(t, id)| (t, depth32(id), id))
        .collect();
    let depth64 =
        |id: u32| super::project::camera_point(g.means[id as usize].map(f64::from), w2c).z;
    let unsorted_ties = host32
        .windows(2)
        .filter(|w| (w[0].0, w[0].1) == (w[1].0, w[1].1) && depth64(w[0].2) > depth64(w[1].2))
        .count();
    host32.sort_unstable();
    let gpu_keys: Vec<(u32, u32, u32)> = out
        .keys
        .iter()
        .zip(&out.ids)
        .map(|(k, &id)| (k[1], k[0], id))
        .collect();
    assert_eq!(gpu_keys, host32, "{label}: sorted (tile, depth, id)");
    assert_eq!(out.ids, ids, "{label}: sorted ids differ from the host's");
    (out.ids.len(), unsorted_ties)
}

#[test]
fn gpu_binning_and_sort_equal_the_host_reference() {
    for seed in 0..4u64 {
        let mut g = random_scene(seed + 40, 1500 + seed as usize * 700);
        // Exact depth ties (copies of one Gaussian): ordered by id on both sides.
        for i in 0..40 {
            g.means[i + 100] = g.means[i];
        }
        let Some(mut r) = gpu(&g) else { return };
        for view in 0..3 {
            let (k, w2c) = test_camera(seed * 10 + view);
            let label = format!("seed {seed} view {view}");
            let (n, _) = check_gpu_sort(&mut r, &g, &k, &w2c, &label);
            assert!(n > 2000, "{label}: too few intersections to test ({n})");
        }
    }
}

#[test]
fn gpu_sort_handles_many_gaussians_per_tile() {
    // 6000 small Gaussians in front of the camera's centre (thousands per tile: several radix
    // blocks per tile and digit) and 30 large ones covering the whole raster (every tile).
    let mut g = random_scene(77, 6030);
    let mut rng = SplitMix64::new(5);
    for i in 0..6030 {
        let big = i % 201 == 0;
        g.means[i] = [
            rng.range(-0.05, 0.05) as f32,
            rng.range(-0.05, 0.05) as f32,
            rng.range(-1.0, 1.0) as f32,
        ];
        let s = if big { 3.0 } else { 0.02 };
        g.scales[i] = [s, s, s];
        g.opacities[i] = 0.3;
    }
    let Some(mut r) = gpu(&g) else { return };
    let (k, w2c) = test_camera(3);
    let (n, _) = check_gpu_sort(&mut r, &g, &k, &w2c, "crowded");
    let out = r.sorted_intersections(&k, &w2c).expect("gpu sort");
    let most = out.ranges.iter().map(|r| r[1] - r[0]).max().unwrap_or(0);
    assert!(
        most > 3000 && n > 10_000,
        "{most} in the fullest tile, {n} in all"
    );
    // And the weights rasterized from that order match the CPU reference.
    let mut cpu = CpuRasterizer::new(&g);
    let reference = cpu.rasterize(&k, &w2c).expect("cpu");
    let w = r.rasterize(&k, &w2c).expect("gpu");
    compare(&w, &reference, &cpu.project_all(&k, &w2c), "crowded");
}

#[test]
fn gpu_sort_of_empty_views_has_no_intersections() {
    let (k, w2c) = test_camera(7);
    let mut behind = random_scene(3, 300);
    for m in &mut behind.means {
        m[2] = -4.0 - m[2].abs() - 0.001;
    }
    for (label, g) in [("empty", Gaussians::default()), ("behind", behind)] {
        let Some(mut r) = gpu(&g) else { return };
        let out = r.sorted_intersections(&k, &w2c).expect("gpu sort");
        assert!(out.keys.is_empty() && out.ids.is_empty(), "{label}: keys");
        assert!(out.ranges.iter().all(|r| *r == [0, 0]), "{label}: ranges");
        let (tx, ty) = super::project::tile_grid(k.width, k.height);
        assert_eq!(
            out.ranges.len(),
            (tx * ty) as usize,
            "{label}: one range per tile"
        );
    }
}

/// Sort depths made ahead on another thread ([`WeightRasterizer::view_precompute`]) give the
/// same label sums as depths made by the rasterizer itself; depths made for another view are
/// not used (the sums stay this view's); the CPU rasterizer has none to offer.
#[test]
fn precomputed_sort_depths_give_the_same_label_sums() {
    let g = random_scene(23, 800);
    let (k, w2c) = test_camera(23);
    let (_, other) = test_camera(24);
    assert!(CpuRasterizer::new(&g).view_precompute().is_none());
    let Some(mut gpu) = gpu(&g) else { return };
    let labels: Vec<u32> = (0..k.width * k.height).map(|p| 1 + p % 3).collect();
    let own = gpu
        .label_sums(&k, &w2c, &labels)
        .expect("own depths")
        .expect("gpu sums")
        .reduced();
    assert!(!own.is_empty());
    let pre = gpu
        .view_precompute()
        .expect("the GPU rasterizer precomputes");
    let ahead = pre.precompute(&w2c);
    assert_eq!(ahead.sort_depths.len(), g.len());
    for p in [ahead, pre.precompute(&other)] {
        let sums = gpu
            .label_sums_precomputed(&k, &w2c, &labels, Some(p))
            .expect("precomputed depths")
            .expect("gpu sums")
            .reduced();
        assert_eq!(sums, own);
    }
}

/// The label-sum records reduced on the device equal the host's reduction of the records as
/// the kernel wrote them, bit for bit and in the same (Gaussian, label) order: over a view in
/// one band (returned as sorted) and split into bands (merged on the host), with label counts
/// that take one to three radix passes over the label bits, and a repeated view reusing the
/// kept buffers.
#[test]
fn device_reduced_label_sums_equal_the_host_reduction() {
    let g = random_scene(31, 1500);
    let (k, w2c) = test_camera(31);
    let Some(mut gpu) = gpu(&g) else { return };
    for labels_in_use in [3u32, 40, 700] {
        // Stripes and a checkerboard of labels: many labels per tile, some pixels unlabelled.
        let labels: Vec<u32> = (0..k.width * k.height)
            .map(|p| {
                let (x, y) = (p % k.width, p / k.width);
                if (x + 3 * y) % 11 == 0 {
                    0
                } else {
                    1 + (x / 3 + y * 7) % labels_in_use
                }
            })
            .collect();
        gpu.set_label_reduce_on_device(false);
        let raw = gpu
            .label_sums(&k, &w2c, &labels)
            .expect("raw records")
            .expect("gpu sums");
        assert!(!raw.sorted, "raw records are not reduced");
        let written = gpu.last_label_records();
        let reference = raw.clone().reduced();
        assert!(
            (reference.len() as u64) < written,
            "{labels_in_use} labels: some keys span several tiles"
        );
        gpu.set_label_reduce_on_device(true);
        for _ in 0..2 {
            let dev = gpu
                .label_sums(&k, &w2c, &labels)
                .expect("device reduce")
                .expect("gpu sums");
            assert!(
                dev.sorted,
                "{labels_in_use} labels: one band is returned reduced"
            );
            assert_eq!(dev.contributions, raw.contributions);
            assert_eq!(dev.records, reference, "{labels_in_use} labels");
        }
        // Bands of tile rows: each reduced on the device, their keys merged on the host.
        gpu.set_label_records(16, Some(written / 3));
        let banded = gpu
            .label_sums(&k, &w2c, &labels)
            .expect("banded")
            .expect("gpu sums");
        assert!(!banded.sorted, "{labels_in_use} labels: several bands");
        assert_eq!(
            banded.reduced(),
            reference,
            "{labels_in_use} labels: banded"
        );
        gpu.set_label_records(1 << 16, None);
    }
}

// ---------------------------------------------------------------------------------------------
// the device reduction

/// A random view as the device reduction keeps it: camera `seed`, 9 random masks, their overlap
/// labels and weighting factors (`params`), and random mask embeddings of width `dim` drawn
/// from `salt`.
pub(super) struct RandomKeptView {
    seed: u64,
    pub(super) intrinsics: Intrinsics,
    pub(super) world_to_camera: WorldToCamera,
    pub(super) masks: Vec<crate::masks::Mask>,
    pub(super) embeddings: Vec<f32>,
    labels: crate::aggregate::image::PixelLabels,
    factors: Vec<f32>,
}

impl RandomKeptView {
    pub(super) fn new(seed: u64, salt: u64, dim: usize, params: crate::aggregate::ImageStageParams) -> Self {
        let (k, w2c) = test_camera(seed);
        let masks = random_masks(seed, k.width * 2, k.height * 2, 9);
        let mut r = SplitMix64::new(salt);
        let embeddings = (0..masks.len() * dim)
            .map(|_| r.range(-1.0, 1.0) as f32)
            .collect();
        let overlap = params.overlap;
        let labels = crate::aggregate::overlap_labels(&masks, k.width, k.height, overlap).merged();
        let factors = crate::aggregate::image::mask_factors(&masks, params.mask_weighting);
        Self {
            seed,
            intrinsics: k,
            world_to_camera: w2c,
            masks,
            embeddings,
            labels,
            factors,
        }
    }

    /// The view kept on `r` ([`WeightRasterizer::label_sums_kept`], with its dominant masks when
    /// `dominant`); `None` where `r` does not keep.
    pub(super) fn keep_on(&self, r: &mut GpuRasterizer, dominant: bool) -> Option<KeptView> {
        let kept = KeptMasks {
            masks_of: &self.labels.masks_of,
            factors: &self.factors,
            embeddings: &self.embeddings,
            dominant,
            view: self.seed as usize,
        };
        let (k, w2c) = (&self.intrinsics, &self.world_to_camera);
        r.label_sums_kept(k, w2c, &self.labels.labels, None, kept)
            .unwrap()
    }
}

/// The device reduction (label sums kept on the device, reduced there in tiles) gives the host
/// pipeline's results: the same observed Gaussians, `Σ a_kj`, unit `E_k` within f64 round-off,
/// the same kept mixture pairs and the same dominant masks, with overlapping masks, area
/// weighting, several views and tiles of a few blocks of Gaussians, and with the last views kept
/// on a second device whose views the first imports (a run on several GPUs). The views are kept
/// out of order, as the fronts finish them: the codebook still comes in view order.
#[test]
fn device_reduction_equals_the_host_reduction() {
    use crate::aggregate::{
        ContributionStore, ImageStageParams, MaskWeighting, ReduceParams, StoredImage, reduce,
        reduce_mixture_chunks,
    };
    use crate::pipeline::view_contribution;
    let n = 20_000;
    let g = random_scene(11, n);
    let Some(mut host_gpu) = gpu(&g) else { return };
    let Some(mut dev) = gpu(&g) else { return };
    let Some(mut second) = gpu(&g) else { return };
    let dim = 70; // two values per thread for some threads of the 64-wide workgroup
    assert!(
        dev.keep_on_device(dim, 1 << 30, true),
        "the device (lavapipe in CI) has f64: it keeps the label sums"
    );
    assert!(second.keep_on_device(dim, 1 << 30, true));
    dev.set_reduce_tile_bytes(Some(100_000));
    let params = ImageStageParams {
        mask_weighting: MaskWeighting::Area,
        ..Default::default()
    };
    let mut store = ContributionStore::new(1 << 30, std::env::temp_dir());
    let mut dominants = Vec::new();
    let mut first_view_rows = Vec::new();
    for seed in [2u64, 0, 4, 1, 3] {
        let v = RandomKeptView::new(seed, seed ^ 0xE3B, dim, params);
        let (k, w2c, emb) = (&v.intrinsics, &v.world_to_camera, &v.embeddings);
        let (c, _) =
            view_contribution(&mut host_gpu, k, w2c, &v.masks, emb.clone(), dim, params).unwrap();
        let keeper = if seed < 3 { &mut dev } else { &mut second };
        let view = v.keep_on(keeper, true).expect("kept");
        assert_eq!(
            view.dominant,
            crate::pipeline::pool::dominant_masks(&c.entries),
            "view {seed}"
        );
        dominants.push(view.dominant);
        if seed == 0 {
            first_view_rows = v.embeddings.clone();
        }
        let stored = StoredImage::from_contribution(c);
        store.push_stored_as(seed as usize, stored).unwrap();
    }
    let rp = ReduceParams::default();
    let host = reduce(&store, n, dim, rp).unwrap();
    let keep = 3;
    let means = g.means.clone();
    let (sparse, _) = reduce_mixture_chunks(&store, &means, dim, rp, keep, "m").unwrap();
    let p = DeviceReduce {
        min_total_weight: rp.min_total_weight,
        keep,
        dense: true,
        gaussians: None,
    };
    // One band per batch: the batches after the first continue its views.
    let mut batches = 0;
    while let Some(batch) = second.export_kept_batch(1).unwrap() {
        assert_eq!(batch.continues, batches > 0, "batch {batches}");
        assert_eq!(batch.views.is_empty(), batches > 0, "batch {batches}");
        dev.import_kept(batch).unwrap();
        batches += 1;
    }
    assert!(
        batches >= 2,
        "{batches} batches: a band per batch, two views"
    );
    assert!(second.export_kept().unwrap().is_none(), "keeping stopped");
    let mut tiles = Vec::new();
    let out = dev.reduce_kept(&p, &mut |t| {
        tiles.push(t);
        Ok(())
    });
    let out = out.unwrap();
    assert!(
        out.tiles >= 2,
        "{} tiles: the small tile budget splits the scene",
        out.tiles
    );
    assert_eq!(
        out.codebook[..first_view_rows.len()],
        first_view_rows[..],
        "view 0's masks first, though kept second"
    );
    assert_eq!(
        out.codebook, sparse.codebook,
        "the codebook rows in view order"
    );
    let ids: Vec<u32> = tiles.iter().flat_map(|t| t.ids.clone()).collect();
    assert!(
        host.ids.len() > 100,
        "{} observed Gaussians: too few to test",
        host.ids.len()
    );
    let missing: Vec<&u32> = host
        .ids
        .iter()
        .filter(|k| !ids.contains(k))
        .take(10)
        .collect();
    assert_eq!(
        ids.len(),
        host.ids.len(),
        "observed Gaussians; first missing {missing:?}"
    );
    assert_eq!(ids, host.ids, "observed Gaussians");
    let totals: Vec<f32> = tiles.iter().flat_map(|t| t.total_weights.clone()).collect();
    for (d, h) in totals.iter().zip(&host.total_weights) {
        assert!((d - h).abs() <= 1e-6 * h.abs(), "Σ a {d} vs host {h}");
    }
    let rows: Vec<f32> = tiles.iter().flat_map(|t| t.rows.clone()).collect();
    for (d, h) in rows.iter().zip(&host.vectors) {
        assert!((d - h).abs() <= 2e-7, "E_k value {d} vs host {h}");
    }
    let kept: Vec<Vec<(f32, u32)>> = tiles
        .iter()
        .flat_map(|t| (0..t.ids.len()).map(|i| t.kept_of(i).to_vec()))
        .collect();
    for (i, row) in kept.iter().enumerate() {
        let (a, b) = (sparse.offsets[i], sparse.offsets[i + 1]);
        let mut dev_row: Vec<(u32, f32)> = row.iter().map(|&(w, j)| (j, w)).collect();
        let mut host_row: Vec<(u32, f32)> = sparse.atoms[a..b]
            .iter()
            .copied()
            .zip(sparse.weights[a..b].iter().copied())
            .collect();
        dev_row.sort_by_key(|x| x.0);
        host_row.sort_by_key(|x| x.0);
        assert_eq!(dev_row, host_row, "kept pairs of Gaussian {}", ids[i]);
    }
    assert!(dominants.iter().all(|d| !d.is_empty()));
}

/// The device reduction split by Gaussians over three devices gives what one device gives with
/// every view, bit for bit: each device keeps some of the views, the ranges follow the kept
/// records, every device sends the others their ranges' records a band per batch (so a device
/// takes in batches of two sources interleaved), and each reduces its own range; the same
/// observed Gaussians, `Σ a_kj`, rows and kept pairs, and the same codebook on every device.
#[test]
fn device_reduction_split_over_devices_equals_one_device() {
    use crate::pipeline::devices::{exchange_kept, split_by_records};
    let n = 20_000;
    let g = random_scene(11, n);
    let Some(mut one) = gpu(&g) else { return };
    let mut devices: Vec<GpuRasterizer> = (0..3).filter_map(|_| gpu(&g)).collect();
    let dim = 6;
    for r in devices.iter_mut().chain([&mut one]) {
        assert!(r.keep_on_device(dim, 1 << 30, true), "lavapipe has f64");
        r.set_reduce_tile_bytes(Some(100_000));
    }
    let params = crate::aggregate::ImageStageParams {
        mask_weighting: crate::aggregate::MaskWeighting::Area,
        ..Default::default()
    };
    for seed in [2u64, 0, 4, 1, 5, 3] {
        let v = RandomKeptView::new(seed, seed ^ 0x5B1, dim, params);
        for r in [&mut one, &mut devices[seed as usize % 3]] {
            v.keep_on(r, false).expect("kept");
        }
    }
    let p = DeviceReduce {
        min_total_weight: crate::aggregate::ReduceParams::default().min_total_weight,
        keep: 3,
        dense: true,
        gaussians: None,
    };
    let reduce = |r: &mut dyn WeightRasterizer, p: &DeviceReduce| {
        let mut tiles = Vec::new();
        let out = r.reduce_kept(p, &mut |t| {
            tiles.push(t);
            Ok(())
        });
        (out.unwrap(), tiles)
    };
    let (whole, whole_tiles) = reduce(&mut one, &p);
    let boxed: Vec<Box<dyn WeightRasterizer>> = devices
        .into_iter()
        .map(|r| Box::new(r) as Box<dyn WeightRasterizer>)
        .collect();
    let ranges = split_by_records(&boxed, n).unwrap();
    assert_eq!(ranges.len(), 3);
    assert!(ranges.windows(2).all(|w| w[0].end == w[1].start));
    assert_eq!((ranges[0].start, ranges[2].end), (0, n as u32));
    assert!(
        ranges.iter().all(|r| !r.is_empty()),
        "{ranges:?}: every device reduces some"
    );
    let boxed: Vec<_> = boxed.into_iter().map(std::sync::Mutex::new).collect();
    exchange_kept(&boxed, &ranges, 1).unwrap();
    let mut split_tiles = Vec::new();
    for (r, range) in boxed.into_iter().zip(&ranges) {
        let p = DeviceReduce {
            gaussians: Some((range.start, range.end)),
            ..p
        };
        let (out, tiles) = reduce(&mut **r.lock().unwrap(), &p);
        assert!(
            out.codebook == whole.codebook,
            "every device holds every view"
        );
        assert!(tiles.iter().flat_map(|t| &t.ids).all(|k| range.contains(k)));
        split_tiles.extend(tiles);
    }
    let flat = |tiles: &[KeptTile]| {
        let ids: Vec<u32> = tiles.iter().flat_map(|t| t.ids.clone()).collect();
        let totals: Vec<f32> = tiles.iter().flat_map(|t| t.total_weights.clone()).collect();
        let rows: Vec<f32> = tiles.iter().flat_map(|t| t.rows.clone()).collect();
        let kept: Vec<Vec<(f32, u32)>> = tiles
            .iter()
            .flat_map(|t| (0..t.ids.len()).map(|i| t.kept_of(i).to_vec()))
            .collect();
        (ids, totals, rows, kept)
    };
    let (whole, split) = (flat(&whole_tiles), flat(&split_tiles));
    assert!(whole.0.len() > 100, "{} observed: too few", whole.0.len());
    assert_eq!(split.0, whole.0, "observed Gaussians");
    assert!(split == whole, "Σ a_kj, rows or kept pairs differ");
}

/// The masks' record kept on the device equals the host's record fed with the same views'
/// dominant masks: the same slots in the same order, with more views than slots, views split
/// into several bands of tile rows, views arriving out of order, and the views split over two
/// devices whose records merge (a run on several GPUs).
#[test]
fn device_mask_record_equals_the_host_record() {
    use slag_common::mask_record::MaskRecord;
    let n = 6_000;
    let g = random_scene(12, n);
    let Some(mut heads) = gpu(&g) else { return };
    let Some(mut first) = gpu(&g) else { return };
    let Some(mut second) = gpu(&g) else { return };
    let (dim, slots, views) = (4, 2, 7);
    for r in [&mut heads, &mut first, &mut second] {
        assert!(r.keep_on_device(dim, 1 << 30, true));
    }
    assert!(first.keep_mask_record(slots, views));
    assert!(second.keep_mask_record(slots, views));
    let mut host = MaskRecord::new(n, slots, views).unwrap();
    // Every view of each Gaussian, to count those seen in more views than slots.
    let mut every = MaskRecord::new(n, views, views).unwrap();
    for view in [3usize, 0, 6, 1, 5, 2, 4] {
        let (k, w2c) = test_camera(view as u64);
        let masks = random_masks(view as u64, k.width * 2, k.height * 2, 7);
        let overlap = crate::aggregate::ImageStageParams::default().overlap;
        let labels = crate::aggregate::overlap_labels(&masks, k.width, k.height, overlap).merged();
        let area = crate::aggregate::MaskWeighting::Area;
        let factors = crate::aggregate::image::mask_factors(&masks, area);
        let emb = vec![0.5f32; masks.len() * dim];
        // Odd views in bands of a few tile rows: the same bands on both sides.
        let band_limit = (view % 2 == 1).then_some(2_000);
        let keeper = if view < 4 { &mut first } else { &mut second };
        let on = |r: &mut GpuRasterizer, dominant: bool| {
            r.set_label_records(16, band_limit);
            let kept = KeptMasks {
                masks_of: &labels.masks_of,
                factors: &factors,
                embeddings: &emb,
                dominant,
                view,
            };
            let out = r.label_sums_kept(&k, &w2c, &labels.labels, None, kept);
            out.unwrap().expect("kept").dominant
        };
        let dominant = on(&mut heads, true);
        assert!(!dominant.is_empty(), "view {view} sees Gaussians");
        every.add_view(view, dominant.iter().copied());
        host.add_view(view, dominant);
        assert!(
            on(keeper, false).is_empty(),
            "the record on the device returns none"
        );
    }
    let mut merged = first
        .take_mask_record()
        .unwrap()
        .expect("kept on the device");
    assert!(first.take_mask_record().unwrap().is_none(), "taken once");
    merged
        .merge(&second.take_mask_record().unwrap().expect("kept"))
        .unwrap();
    assert_eq!(merged, host);
    let evicted = (0..n).filter(|&k| every.of(k).count() > slots).count();
    assert!(
        evicted >= 10,
        "{evicted} Gaussians seen in more views than slots: too few"
    );
}

/// A view whose keeping fails on the kept sums' budget (met in a later band of the view) is not
/// kept at all: the views kept before it come back alone, as the host has them
/// ([`KeptExport::into_host_views`]: the same records, label table, factors and embeddings).
#[test]
fn a_view_past_the_kept_budget_is_not_kept_and_the_others_come_back() {
    use crate::aggregate::image::mask_factors;
    use crate::aggregate::{MaskWeighting, overlap_labels};
    let g = random_scene(41, 6000);
    let Some(mut host) = gpu(&g) else { return };
    let Some(mut dev) = gpu(&g) else { return };
    let (k, w2c) = test_camera(41);
    let masks = random_masks(41, k.width * 2, k.height * 2, 7);
    let labels = overlap_labels(&masks, k.width, k.height, Default::default()).merged();
    let factors = mask_factors(&masks, MaskWeighting::Area);
    let dim = 5;
    let emb: Vec<f32> = (0..masks.len() * dim).map(|i| i as f32 * 0.25).collect();
    host.set_label_reduce_on_device(false);
    let raw = host
        .label_sums(&k, &w2c, &labels.labels)
        .unwrap()
        .expect("gpu sums");
    let written = host.last_label_records();
    let reference = raw.reduced();
    host.set_label_reduce_on_device(true);
    let kept = KeptMasks {
        masks_of: &labels.masks_of,
        factors: &factors,
        embeddings: &emb,
        dominant: false,
        view: 0,
    };
    // Bands of about a third of the view: what one view keeps, measured on `host`.
    for r in [&mut host, &mut dev] {
        r.set_label_records(16, Some(written / 3));
    }
    assert!(host.keep_on_device(dim, 1 << 30, true), "lavapipe has f64");
    host.label_sums_kept(&k, &w2c, &labels.labels, None, kept)
        .unwrap()
        .expect("kept");
    // Each band read back on its own, through the one staging buffer.
    host.set_readback_bytes(Some(1));
    let one = host.export_kept().unwrap().expect("kept");
    assert!(one.parts.len() >= 3, "{} bands", one.parts.len());
    let read = one.clone().into_host_views().unwrap().remove(0);
    assert_eq!(read.sums.reduced(), reference, "bands read back one by one");
    let bytes: u64 = one.parts.iter().map(|p| p.1.len() as u64).sum();
    // Room for the view and half of it again: the second view's first band fits, a later one not.
    assert!(dev.keep_on_device(dim, bytes + bytes / 2, true));
    let mut keep = || dev.label_sums_kept(&k, &w2c, &labels.labels, None, kept);
    keep().unwrap().expect("the first view is kept");
    let err = keep().unwrap_err();
    assert!(
        matches!(
            err,
            Error::Limit {
                resource: slag_common::Resource::GpuMemory,
                ..
            }
        ),
        "{err}"
    );
    let views = dev
        .export_kept()
        .unwrap()
        .expect("kept")
        .into_host_views()
        .unwrap();
    assert_eq!(views.len(), 1, "the failed view is not kept");
    let v = views.into_iter().next().unwrap();
    assert!(!v.sums.sorted, "bands of a view come back as records");
    assert_eq!(v.sums.reduced(), reference);
    assert_eq!(
        (v.masks_of, v.factors, v.embeddings),
        (labels.masks_of, factors, emb)
    );
}
