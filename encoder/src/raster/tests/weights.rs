//! The weights per pixel: the GPU against the f64 CPU reference on random scenes and the real
//! snowmiku scene (identical contributor lists, weights within 1e-4, differences only where a
//! value sits within f32 error of a threshold), closed forms, and a colour render of snowmiku
//! against its training photos.

use super::*;

#[derive(Debug, Default)]
pub(super) struct Agreement {
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
pub(super) fn compare(
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
