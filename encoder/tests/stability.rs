//! Numerical stability of the weight rasterizer and the aggregation at the extremes.
//! Every case asserts an expected behaviour (finite weights in (0, 1] summing to ≤ 1 per
//! pixel, a closed-form value, "not drawn", or "unobserved"), and the GPU path (wgpu; Mesa
//! lavapipe in CI) agrees with the f64 CPU reference within the rasterizer's tolerance (identical
//! contributor lists with weights within 1e-4, except ≤ 0.1 % of pixels + 2 where an f32 value sits
//! on a decision threshold). The measured figures are printed (`--nocapture`) and tabulated in
//! `docs/results/stability.md`.
//!
//! GPU parts need a Vulkan adapter; `SLAG_SKIP_GPU=1` skips them (as in `raster::tests`).
//!
//! Run: `cargo test --workspace --test stability -- --nocapture`.

#![allow(clippy::unwrap_used, clippy::expect_used)]

#[path = "../src/raster/testdata.rs"]
mod testdata;

use glam::{DMat3, DQuat, DVec3};
use proptest::prelude::*;
use slag_common::camera::{Intrinsics, WorldToCamera};
use slag_common::rng::SplitMix64;
use slag_common::scene::Gaussians;
use slag_encoder::aggregate::{ContributionStore, Entry, ImageContribution, ReduceParams, reduce};
use slag_encoder::raster::project::{ALPHA_MAX, ALPHA_MIN, LOW_PASS, project_gaussian};
use slag_encoder::raster::{CpuRasterizer, GpuRasterizer, PixelWeights, WeightRasterizer};
use testdata::gpu_unless_skipped;

// ---------------------------------------------------------------------------------------------
// helpers

/// A random unit quaternion (wxyz, f32): four components uniform in [-1, 1), normalised.
fn unit_quat(r: &mut SplitMix64) -> [f32; 4] {
    let q = [0; 4].map(|_| r.range(-1.0, 1.0));
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt().max(1e-9);
    q.map(|v| (v / n) as f32)
}

/// The GPU rasterizer with noise-filled scratch buffers; `None` only under `SLAG_SKIP_GPU=1`.
fn gpu(g: &Gaussians) -> Option<GpuRasterizer> {
    let mut r = gpu_unless_skipped(|| GpuRasterizer::new(g))?;
    r.set_noise_fill(Some(0x57ab));
    Some(r)
}

/// Scene extent used to express scales: means lie in a cube of this edge, metres.
const EXTENT: f64 = 4.0;

fn intrinsics() -> Intrinsics {
    Intrinsics {
        width: 96,
        height: 72,
        fx: 80.0,
        fy: 84.0,
        cx: 47.0,
        cy: 36.5,
    }
}

/// A camera at `centre` looking down +z with a small fixed tilt.
fn camera_at(centre: DVec3) -> WorldToCamera {
    let rot = DMat3::from_quat(DQuat::from_euler(glam::EulerRot::XYZ, 0.07, -0.05, 0.11));
    WorldToCamera {
        rotation: rot,
        translation: -(rot * centre),
    }
}

/// The camera at the world origin with the world's axes (OpenCV: looking down +z).
fn camera_at_origin() -> WorldToCamera {
    WorldToCamera {
        rotation: DMat3::IDENTITY,
        translation: DVec3::ZERO,
    }
}

fn default_camera() -> WorldToCamera {
    camera_at(DVec3::new(0.1, -0.2, -EXTENT))
}

fn push(g: &mut Gaussians, mean: [f32; 3], scale: [f32; 3], q: [f32; 4], o: f32) {
    g.means.push(mean);
    g.scales.push(scale);
    g.rotations.push(q);
    g.opacities.push(o);
}

/// Invariants of any rasterizer output: CSR shape, ids in range and unique per pixel, weights
/// finite in (0, 1], `Σ_k w_kp ≤ 1 + 1e-5` per pixel. Returns the largest pixel sum.
fn invariants(w: &PixelWeights, n: usize, label: &str) -> f64 {
    let n_pix = (w.width * w.height) as usize;
    assert_eq!(w.offsets.len(), n_pix + 1, "{label}");
    assert_eq!(w.offsets[0], 0, "{label}");
    assert_eq!(w.offsets[n_pix] as usize, w.ids.len(), "{label}");
    assert_eq!(w.ids.len(), w.weights.len(), "{label}");
    let mut max_sum = 0f64;
    for p in 0..n_pix {
        let (a, b) = (w.offsets[p] as usize, w.offsets[p + 1] as usize);
        assert!(a <= b, "{label}: offsets decrease at pixel {p}");
        let mut seen = std::collections::HashSet::new();
        let mut sum = 0f64;
        for e in a..b {
            let v = w.weights[e];
            assert!(
                v.is_finite() && v > 0.0 && v <= 1.0,
                "{label}: pixel {p}: weight {v} not finite in (0, 1]"
            );
            assert!((w.ids[e] as usize) < n, "{label}: id {} ≥ {n}", w.ids[e]);
            assert!(seen.insert(w.ids[e]), "{label}: id {} twice", w.ids[e]);
            sum += v as f64;
        }
        assert!(sum <= 1.0 + 1e-5, "{label}: pixel {p}: Σw = {sum}");
        max_sum = max_sum.max(sum);
    }
    max_sum
}

/// Per-pixel agreement of two rasters.
#[derive(Debug, Default, Clone, Copy)]
struct Agreement {
    /// Largest `|w_a - w_b|` over pixels whose contributor lists are identical.
    same_list_max_diff: f64,
    /// Pixels whose contributor lists differ (an f32 value on a threshold: α = 1/255, T = 1e-4,
    /// a tile edge, or an exact depth tie).
    differing_pixels: usize,
    /// Largest `|w_a - w_b|` over all (pixel, Gaussian), a missing entry counting as 0.
    dense_max_diff: f64,
    pixels: usize,
    /// Entries of the second raster (the reference), for the printout.
    _entries: usize,
}

fn compare(a: &PixelWeights, b: &PixelWeights) -> Agreement {
    assert_eq!((a.width, a.height), (b.width, b.height));
    let mut r = Agreement {
        pixels: (a.width * a.height) as usize,
        _entries: b.ids.len(),
        ..Default::default()
    };
    for y in 0..a.height {
        for x in 0..a.width {
            let (ai, aw) = a.pixel(x, y);
            let (bi, bw) = b.pixel(x, y);
            if ai == bi {
                for (u, v) in aw.iter().zip(bw) {
                    let d = (*u as f64 - *v as f64).abs();
                    r.same_list_max_diff = r.same_list_max_diff.max(d);
                    r.dense_max_diff = r.dense_max_diff.max(d);
                }
                continue;
            }
            r.differing_pixels += 1;
            let get = |ids: &[u32], ws: &[f32], k: u32| {
                ids.iter()
                    .position(|&i| i == k)
                    .map_or(0.0, |e| ws[e] as f64)
            };
            for &k in ai.iter().chain(bi) {
                let d = (get(ai, aw, k) - get(bi, bw, k)).abs();
                r.dense_max_diff = r.dense_max_diff.max(d);
            }
        }
    }
    r
}

/// The rasterizer's GPU-vs-reference tolerance (`raster::tests::compare`): identical lists agree
/// within 1e-4; at most 0.1 % of pixels + 2 differ (threshold cases).
fn assert_agree(a: &Agreement, label: &str) {
    assert_agree_within(a, 1e-4, label)
}

/// [`assert_agree`] with another weight tolerance on identical lists.
fn assert_agree_within(a: &Agreement, tol: f64, label: &str) {
    assert!(
        a.same_list_max_diff <= tol,
        "{label}: weights differ by {} on identical lists ({a:?})",
        a.same_list_max_diff
    );
    assert!(
        a.differing_pixels as f64 <= 1e-3 * a.pixels as f64 + 2.0,
        "{label}: {} of {} pixels have different contributor lists ({a:?})",
        a.differing_pixels,
        a.pixels
    );
}

/// CPU reference and (unless skipped) GPU rasters of `g`, with invariants checked and the
/// GPU/CPU agreement asserted. Returns the reference and the agreement (None without a GPU).
fn render_both(
    g: &Gaussians,
    k: &Intrinsics,
    w2c: &WorldToCamera,
    label: &str,
) -> (PixelWeights, Option<(PixelWeights, Agreement)>) {
    render_both_within(g, k, w2c, 1e-4, label)
}

/// [`render_both`] with another weight tolerance (see [`assert_agree_within`]).
fn render_both_within(
    g: &Gaussians,
    k: &Intrinsics,
    w2c: &WorldToCamera,
    tol: f64,
    label: &str,
) -> (PixelWeights, Option<(PixelWeights, Agreement)>) {
    let cpu = CpuRasterizer::new(g).rasterize(k, w2c).expect("cpu raster");
    invariants(&cpu, g.len(), &format!("{label} cpu"));
    let gpu_out = gpu(g).map(|mut r| {
        let out = r.rasterize(k, w2c).expect("gpu raster");
        invariants(&out, g.len(), &format!("{label} gpu"));
        let a = compare(&out, &cpu);
        assert_agree_within(&a, tol, label);
        (out, a)
    });
    (cpu, gpu_out)
}

/// The CPU raster and (unless the GPU part is skipped) the GPU one, by name, after
/// [`render_both`]'s checks; prints the two's agreement.
fn rasters(
    g: &Gaussians,
    k: &Intrinsics,
    w2c: &WorldToCamera,
    label: &str,
) -> Vec<(&'static str, PixelWeights)> {
    let (cpu, gpu_out) = render_both(g, k, w2c, label);
    let mut rasters = vec![("cpu", cpu)];
    if let Some((w, a)) = gpu_out {
        eprintln!("{label}: {a:?}");
        rasters.push(("gpu", w));
    }
    rasters
}

/// Ids that appear anywhere in a raster.
fn drawn(w: &PixelWeights) -> std::collections::BTreeSet<u32> {
    w.ids.iter().copied().collect()
}

/// The largest weight of Gaussian `id` over all pixels (0 if not drawn).
fn max_weight(w: &PixelWeights, id: u32) -> f64 {
    w.ids
        .iter()
        .zip(&w.weights)
        .filter(|(i, _)| **i == id)
        .map(|(_, &v)| v as f64)
        .fold(0.0, f64::max)
}

// ---------------------------------------------------------------------------------------------
// 1. scales from 1e-6 to 1e4 of the scene extent

/// `n` Gaussians in the extent cube, per-axis scales `EXTENT · 10^u`, `u` uniform in
/// `[lo, hi]` independently per axis (so up to 10 decades of anisotropy), random rotations and
/// opacities in (0.02, 1).
fn scale_scene(seed: u64, n: usize, lo: f64, hi: f64) -> Gaussians {
    let mut r = SplitMix64::new(seed);
    let mut g = Gaussians::default();
    let h = EXTENT / 2.0;
    for _ in 0..n {
        let mean = [0; 3].map(|_| r.range(-h, h) as f32);
        let scale = [0; 3].map(|_| (EXTENT * 10f64.powf(r.range(lo, hi))) as f32);
        let q = unit_quat(&mut r);
        let o = r.range(0.02, 1.0) as f32;
        push(&mut g, mean, scale, q, o);
    }
    g
}

#[test]
fn scales_from_1e_minus6_to_1e4_of_the_extent_stay_finite_and_match_gpu() {
    let k = intrinsics();
    let w2c = default_camera();
    let mut worst = Agreement::default();
    let mut max_sum = 0f64;
    // One decade at a time (near-isotropic within ±0.3 decade), then all decades mixed.
    let mut bands: Vec<(f64, f64)> = (-6..=4)
        .map(|d| (d as f64 - 0.3, (d as f64 + 0.3).min(4.0)))
        .collect();
    bands.push((-6.0, 4.0));
    for (i, &(lo, hi)) in bands.iter().enumerate() {
        let g = scale_scene(100 + i as u64, 40, lo, hi);
        let label = format!("scales 10^[{lo:.1}, {hi:.1}] x extent");
        let (cpu, gpu_out) = render_both(&g, &k, &w2c, &label);
        max_sum = max_sum.max(invariants(&cpu, g.len(), &label));
        if let Some((_, a)) = gpu_out {
            eprintln!("{label}: {a:?}");
            worst.same_list_max_diff = worst.same_list_max_diff.max(a.same_list_max_diff);
            worst.differing_pixels = worst.differing_pixels.max(a.differing_pixels);
            worst.dense_max_diff = worst.dense_max_diff.max(a.dense_max_diff);
        }
    }
    eprintln!("scale sweep: worst {worst:?}, max pixel Σw {max_sum}");
}

#[test]
fn extreme_scales_have_their_closed_form_weights() {
    // A Gaussian of σ = 1e4 x extent in front of the camera covers every pixel with α = o
    // (σ_2D of millions of pixels: exp(-½dᵀΣ⁻¹d) = 1 to ~1e-12); one of σ = 1e-6 x extent
    // projects to the low-pass splat alone: α = o·exp(-½ d²/0.3).
    let k = intrinsics();
    let w2c = camera_at_origin();
    let q = [1.0, 0.0, 0.0, 0.0];
    for (scale, label) in [(EXTENT * 1e4, "huge"), (EXTENT * 1e-6, "tiny")] {
        let mut g = Gaussians::default();
        push(&mut g, [0.0, 0.0, 3.0], [scale as f32; 3], q, 0.6);
        let rasters = rasters(&g, &k, &w2c, label);
        for (name, w) in &rasters {
            let mut worst = 0f64;
            for y in 0..k.height {
                for x in 0..k.width {
                    let (dx, dy) = (k.cx - (x as f64 + 0.5), k.cy - (y as f64 + 0.5));
                    let s = scale * k.fx / 3.0;
                    let sy = scale * k.fy / 3.0;
                    let var_x = s * s + LOW_PASS;
                    let var_y = sy * sy + LOW_PASS;
                    let alpha =
                        (0.6 * (-0.5 * (dx * dx / var_x + dy * dy / var_y)).exp()).min(ALPHA_MAX);
                    let (ids, ws) = w.pixel(x, y);
                    if alpha < ALPHA_MIN * 0.999 {
                        assert!(
                            ids.is_empty(),
                            "{label} {name} ({x},{y}): drawn at α {alpha}"
                        );
                        continue;
                    }
                    if alpha < ALPHA_MIN * 1.001 {
                        continue; // on the skip threshold: either is right
                    }
                    assert_eq!(ids, &[0], "{label} {name} ({x},{y}) α {alpha}");
                    worst = worst.max((ws[0] as f64 - alpha).abs());
                }
            }
            eprintln!("{label} Gaussian, {name}: max |w - closed form| = {worst:.2e}");
            assert!(worst < 1e-6, "{label} {name}: {worst}");
        }
    }
}

/// Worst GPU-vs-CPU weight difference on identical lists seen by the proptest, per anisotropy
/// spread in decades (0..=10), for the printout.
static WORST_BY_SPREAD: std::sync::Mutex<[f64; 11]> = std::sync::Mutex::new([0.0; 11]);

/// Identical-list tolerance for a scene whose per-axis scales spread over `spread` decades: the
/// rasterizer's 1e-4 at every spread. (Before the GPU kernel evaluated `½dᵀΣ⁻¹d` in eigen form,
/// needles and sheets — nearly singular conics — exceeded it from 3 decades on: up to 7.9e-4
/// at 10 decades, 2.0e-4 at 3; see docs/results/stability.md.)
fn spread_tolerance(_spread: u32) -> f64 {
    1e-4
}

proptest! {
    // 16 cases in CI; `SLAG_STABILITY_CASES=500` for a deeper run.
    #![proptest_config(ProptestConfig {
        cases: std::env::var("SLAG_STABILITY_CASES").ok().and_then(|v| v.parse().ok()).unwrap_or(16),
        max_shrink_iters: 8,
        ..ProptestConfig::default()
    })]

    /// Random mixtures of scales from 1e-6 to 1e4 x the extent, independently per axis over a
    /// `spread` of decades (needles, discs, blobs bigger than the world): finite weights, Σw ≤ 1,
    /// GPU == CPU within [`spread_tolerance`].
    #[test]
    fn prop_mixed_extreme_scales_match(
        seed in any::<u64>(),
        n in 1usize..60,
        spread in 0u32..=10,
        at in 0.0f64..1.0,
    ) {
        let lo = -6.0 + (10.0 - spread as f64) * at;
        let g = scale_scene(seed, n, lo, lo + spread as f64);
        let tol = spread_tolerance(spread);
        let (_cpu, gpu_out) = render_both_within(&g, &intrinsics(), &default_camera(), tol, "prop scales");
        if let Some((_, a)) = gpu_out {
            let mut w = WORST_BY_SPREAD.lock().unwrap();
            w[spread as usize] = w[spread as usize].max(a.same_list_max_diff);
            eprintln!("worst identical-list |w_gpu - w_cpu| by spread (decades 0..=10): {:?}", *w);
            prop_assert!(a.same_list_max_diff <= tol);
        }
    }
}

// ---------------------------------------------------------------------------------------------
// 2. opacities at 1e-7 and 1 - 1e-7 (logit ±16)

#[test]
fn opacities_near_zero_and_one_clamp_and_skip() {
    // fx = fy and a principal point on a pixel centre: the Gaussians below project exactly onto
    // pixel centres, where exp(-σ) = 1 and α = min(0.99, o).
    let k = Intrinsics {
        fx: 80.0,
        fy: 80.0,
        cx: 48.5,
        cy: 36.5,
        ..intrinsics()
    };
    let w2c = camera_at_origin();
    let q = [1.0, 0.0, 0.0, 0.0];
    let sigmoid = |x: f64| (1.0 / (1.0 + (-x).exp())) as f32;
    // Side by side, 12 px apart (no overlap): ids 0..4.
    let opacities = [1e-7f32, sigmoid(-16.0), 1.0 - 1e-7, sigmoid(16.0), 1.0];
    let mut g = Gaussians::default();
    for (i, &o) in opacities.iter().enumerate() {
        let x = -1.2 + 0.6 * i as f32;
        push(&mut g, [x, -0.6, 4.0], [0.05; 3], q, o);
    }
    // A stack on the optical axis (pixel (48, 36)): 1 - 1e-7 in front, 0.5 behind, 1 - 1e-7
    // behind that (ids 5..7).
    push(&mut g, [0.0, 0.0, 3.0], [0.05; 3], q, 1.0 - 1e-7);
    push(&mut g, [0.0, 0.0, 3.5], [0.05; 3], q, 0.5);
    push(&mut g, [0.0, 0.0, 4.0], [0.05; 3], q, 1.0 - 1e-7);
    let rasters = rasters(&g, &k, &w2c, "opacities");
    for (name, w) in &rasters {
        let ids = drawn(w);
        // α = o·exp(-σ) ≤ 1.2e-7 < 1/255: never drawn.
        assert!(!ids.contains(&0) && !ids.contains(&1), "{name}: {ids:?}");
        // Clamped at 0.99 (to f32 rounding), never above.
        for id in [2, 3, 4, 5] {
            let m = max_weight(w, id);
            assert!(
                (m - ALPHA_MAX).abs() < 1e-7,
                "{name}: Gaussian {id} max weight {m}"
            );
        }
        // The stack's pixel: 0.99, then 0.5·0.01; the third would take T to 0.005·0.01 = 5e-5
        // < 1e-4, so the pixel stops before it.
        let (pi, pw) = w.pixel(48, 36);
        assert_eq!(pi, &[5, 6], "{name}: stack: {pi:?} {pw:?}");
        assert!((pw[0] as f64 - 0.99).abs() < 1e-7, "{name}: {pw:?}");
        assert!((pw[1] as f64 - 0.005).abs() < 1e-8, "{name}: {pw:?}");
    }
}

// ---------------------------------------------------------------------------------------------
// 3. degenerate covariances and quaternions

#[test]
fn degenerate_covariances_are_low_pass_regularised_and_bad_quaternions_culled() {
    let k = intrinsics();
    let w2c = camera_at_origin();
    let u = [0.9238795f32, 0.0, 0.3826834, 0.0]; // 45° about y, unit
    // (scale, quaternion, opacity, expected drawn, what)
    type Case = ([f32; 3], [f32; 4], f32, bool, &'static str);
    let cases: Vec<Case> = vec![
        ([0.0; 3], u, 0.7, true, "all scales zero"),
        ([0.2, 0.0, 0.0], u, 0.7, true, "two scales zero (a needle)"),
        ([0.2, 0.2, 0.0], u, 0.7, true, "one scale zero (a disc)"),
        ([1e-40, 1e-40, 1e-40], u, 0.7, true, "subnormal scales"),
        ([0.05; 3], [0.0; 4], 0.7, false, "zero quaternion"),
        (
            [0.05; 3],
            [f32::NAN, 0.0, 0.0, 1.0],
            0.7,
            false,
            "NaN quaternion",
        ),
        (
            [0.05; 3],
            [f32::INFINITY, 0.0, 0.0, 0.0],
            0.7,
            false,
            "infinite quaternion",
        ),
        ([f32::NAN, 0.1, 0.1], u, 0.7, false, "NaN scale"),
        ([f32::INFINITY, 0.1, 0.1], u, 0.7, false, "infinite scale"),
        ([0.05; 3], u, f32::NAN, false, "NaN opacity"),
        ([0.05; 3], u, f32::INFINITY, false, "infinite opacity"),
        ([0.05; 3], u, 0.0, false, "zero opacity"),
        ([0.05; 3], u, -0.5, false, "negative opacity"),
        (
            [0.05; 3],
            u,
            7.0,
            true,
            "opacity above 1 (α clamps at 0.99)",
        ),
    ];
    // A 4x4 grid 1 m apart at depth 5 (16 px apart: no overlap).
    let pos = |i: usize| [(i % 4) as f32 - 1.5, (i / 4) as f32 - 1.5, 5.0f32];
    let mut g = Gaussians::default();
    for (i, (s, q, o, _, _)) in cases.iter().enumerate() {
        push(&mut g, pos(i), *s, *q, *o);
    }
    let rasters = rasters(&g, &k, &w2c, "degenerate");
    for (name, w) in &rasters {
        let ids = drawn(w);
        for (i, (_, _, _, expect, what)) in cases.iter().enumerate() {
            assert_eq!(ids.contains(&(i as u32)), *expect, "{name}: {what}");
        }
        assert!(
            (max_weight(w, 13) - ALPHA_MAX).abs() < 1e-7,
            "{name}: opacity 7"
        );
        // Zero scales: Σ2D = 0.3·I exactly, so every pixel has the closed form.
        let p = pos(0).map(f64::from);
        let (mx, my) = (k.fx * p[0] / p[2] + k.cx, k.fy * p[1] / p[2] + k.cy);
        let mut worst = 0f64;
        for py in (my as u32 - 3)..(my as u32 + 4) {
            for px in (mx as u32 - 3)..(mx as u32 + 4) {
                let (pi, pw) = w.pixel(px, py);
                let d2 = (mx - (px as f64 + 0.5)).powi(2) + (my - (py as f64 + 0.5)).powi(2);
                let alpha = 0.7 * (-0.5 * d2 / LOW_PASS).exp();
                if alpha < ALPHA_MIN {
                    assert!(pi.is_empty(), "{name} ({px},{py}): {pi:?}");
                    continue;
                }
                assert_eq!(pi, &[0], "{name} ({px},{py})");
                worst = worst.max((pw[0] as f64 - alpha).abs());
            }
        }
        eprintln!("zero-scale Gaussian, {name}: max |w - 0.7·exp(-d²/0.6)| = {worst:.2e}");
        assert!(worst < 1e-6, "{name}: {worst}");
    }
}

#[test]
fn non_unit_quaternions_give_the_unit_quaternions_weights() {
    // Scaling q by any positive factor must not change the render: the rasterizers normalise.
    let k = intrinsics();
    let w2c = default_camera();
    let base = scale_scene(7, 50, -2.5, -1.0);
    let mut reference = None;
    for f in [1.0f32, 7.3, 1e-20, 1e20, 1e-30, 1e30] {
        let mut g = base.clone();
        for q in &mut g.rotations {
            *q = q.map(|v| v * f);
        }
        let (cpu, gpu_out) = render_both(&g, &k, &w2c, &format!("quaternion x {f:e}"));
        let reference = reference.get_or_insert_with(|| cpu.clone());
        let a = compare(&cpu, reference);
        assert_eq!(a.differing_pixels, 0, "cpu, q x {f:e}: {a:?}");
        assert!(a.same_list_max_diff <= 1e-6, "cpu, q x {f:e}: {a:?}");
        if let Some((w, _)) = gpu_out {
            let a = compare(&w, reference);
            eprintln!("quaternion x {f:e}, gpu vs unit-q cpu: {a:?}");
            assert_agree(&a, &format!("gpu, q x {f:e}"));
        }
    }
}

// ---------------------------------------------------------------------------------------------
// 4. behind the camera and on the camera plane

#[test]
fn gaussians_behind_or_on_the_camera_plane_are_not_drawn() {
    let k = intrinsics();
    let w2c = camera_at_origin();
    let q = [1.0, 0.0, 0.0, 0.0];
    let mut g = Gaussians::default();
    // Camera-frame depths: behind, on the plane, between the plane and the near plane 0.01.
    let culled = [-1e6f32, -1.0, -1e-3, -0.0, 0.0, 1e-30, 1e-3, 0.005, 0.0099];
    for &z in &culled {
        // Large enough to cover the whole image if it were drawn.
        push(&mut g, [0.0, 0.0, z], [1.0; 3], q, 0.9);
        push(&mut g, [0.3, -0.2, z], [1e-4; 3], q, 0.9);
    }
    let control = g.len() as u32;
    push(&mut g, [0.0, 0.0, 0.5], [0.01; 3], q, 0.9); // in front: drawn (the test can fail)
    let rasters = rasters(&g, &k, &w2c, "behind");
    for (name, w) in &rasters {
        assert_eq!(
            drawn(w).into_iter().collect::<Vec<_>>(),
            vec![control],
            "{name}"
        );
    }
    // And the projection says so directly.
    for &z in &culled {
        assert!(
            project_gaussian(
                [0.0, 0.0, z as f64],
                [1.0; 3],
                [1.0, 0.0, 0.0, 0.0],
                0.9,
                &k,
                &w2c
            )
            .is_none()
        );
    }
}

// ---------------------------------------------------------------------------------------------
// 5. coordinates 1e6 m from the origin (UTM)

/// A scene whose means are multiples of 1/16 m, so that they are exact in f32 both here and
/// after a translation by (1e6, 1e6, 100) (the f32 spacing at 1e6 is 1/16): the two scenes are
/// the same scene, not a re-rounded one.
fn utm_scene(seed: u64, n: usize) -> Gaussians {
    let mut g = scale_scene(seed, n, -3.0, -0.7);
    for m in &mut g.means {
        *m = m.map(|v| (v * 16.0).round() / 16.0);
    }
    g
}

#[test]
fn a_scene_1e6_m_from_the_origin_renders_like_the_same_scene_at_the_origin() {
    let shift = DVec3::new(1e6, 1e6, 100.0);
    let k = intrinsics();
    let g = utm_scene(42, 400);
    let mut far = g.clone();
    for m in &mut far.means {
        let p = DVec3::new(m[0] as f64, m[1] as f64, m[2] as f64) + shift;
        let back = [p.x as f32, p.y as f32, p.z as f32];
        assert_eq!(
            DVec3::new(back[0] as f64, back[1] as f64, back[2] as f64),
            p,
            "test scene not exact in f32"
        );
        *m = back;
    }
    let mut worst_cpu = Agreement::default();
    let mut worst_gpu = Agreement::default();
    let mut worst_gpu_vs_cpu = Agreement::default();
    for (i, centre) in [
        DVec3::new(0.1, -0.2, -EXTENT),
        DVec3::new(-0.7, 0.4, -3.0),
        DVec3::new(0.0, 0.0, -6.0),
    ]
    .into_iter()
    .enumerate()
    {
        let near = camera_at(centre);
        let far_cam = WorldToCamera {
            rotation: near.rotation,
            translation: near.translation - near.rotation * shift,
        };
        let cpu_near = CpuRasterizer::new(&g).rasterize(&k, &near).expect("cpu");
        let cpu_far = CpuRasterizer::new(&far)
            .rasterize(&k, &far_cam)
            .expect("cpu");
        invariants(&cpu_far, far.len(), "cpu far");
        assert!(
            cpu_near.len() > 2000,
            "view {i}: scene too sparse ({})",
            cpu_near.len()
        );
        let a = compare(&cpu_far, &cpu_near);
        eprintln!("view {i}: cpu at 1e6 m vs cpu at origin: {a:?}");
        assert_eq!(a.differing_pixels, 0, "view {i}: {a:?}");
        assert!(a.same_list_max_diff <= 1e-6, "view {i}: {a:?}");
        worst_cpu.same_list_max_diff = worst_cpu.same_list_max_diff.max(a.same_list_max_diff);
        let (Some(mut gn), Some(mut gf)) = (gpu(&g), gpu(&far)) else {
            continue;
        };
        let gpu_near = gn.rasterize(&k, &near).expect("gpu");
        let gpu_far = gf.rasterize(&k, &far_cam).expect("gpu");
        invariants(&gpu_far, far.len(), "gpu far");
        let a = compare(&gpu_far, &gpu_near);
        eprintln!("view {i}: gpu at 1e6 m vs gpu at origin: {a:?}");
        for (w, v) in [
            (&mut worst_gpu, a),
            (&mut worst_gpu_vs_cpu, compare(&gpu_far, &cpu_far)),
        ] {
            w.same_list_max_diff = w.same_list_max_diff.max(v.same_list_max_diff);
            w.dense_max_diff = w.dense_max_diff.max(v.dense_max_diff);
            w.differing_pixels = w.differing_pixels.max(v.differing_pixels);
        }
        assert_agree(&a, &format!("view {i}: gpu at 1e6 m vs gpu at origin"));
        assert_agree(
            &compare(&gpu_far, &cpu_far),
            &format!("view {i}: gpu at 1e6 m vs cpu"),
        );
    }
    eprintln!(
        "1e6 m: cpu far vs near {worst_cpu:?}\n gpu far vs gpu near {worst_gpu:?}\n gpu far vs cpu far {worst_gpu_vs_cpu:?}"
    );
}

// ---------------------------------------------------------------------------------------------
// 6. aggregation: a million tiny contributions, vanishing weights, cancelling masks

/// Neumaier-compensated sum (an independent, more precise reference than plain f64 summation).
#[derive(Default, Clone, Copy)]
struct Neumaier {
    sum: f64,
    c: f64,
}
impl Neumaier {
    fn add(&mut self, x: f64) {
        let t = self.sum + x;
        if self.sum.abs() >= x.abs() {
            self.c += (self.sum - t) + x;
        } else {
            self.c += (x - t) + self.sum;
        }
        self.sum = t;
    }
    fn value(&self) -> f64 {
        self.sum + self.c
    }
}

fn unit(v: Vec<f32>) -> Vec<f32> {
    let n = v.iter().map(|x| (*x as f64).powi(2)).sum::<f64>().sqrt();
    v.into_iter().map(|x| (x as f64 / n) as f32).collect()
}

#[test]
fn a_million_tiny_contributions_reduce_to_the_compensated_reference() {
    // 100 images x 10,000 masks = 1e6 contributions a_kj in [1e-6, 1e-3] to Gaussian 3 (of 5),
    // each with its own embedding E_j; Gaussian 1 gets the same but in f32-hostile order
    // (increasing), Gaussians 0, 2, 4 nothing.
    let dim = 8;
    let (images, masks) = (100usize, 10_000usize);
    let tmp = std::env::temp_dir().join(format!("slag-stability-{}", std::process::id()));
    let mut store = ContributionStore::new(usize::MAX, tmp);
    let mut rng = SplitMix64::new(0xA66);
    let mut num = vec![Neumaier::default(); 2 * dim];
    let mut den = [Neumaier::default(); 2];
    let mut naive_f32_den = 0f32;
    for _ in 0..images {
        let mut emb = Vec::with_capacity(masks * dim);
        let mut entries = Vec::with_capacity(masks * 2);
        for j in 0..masks {
            let e = unit((0..dim).map(|_| rng.range(-1.0, 1.0) as f32).collect());
            // log-uniform in [1e-6, 1e-3]
            let a = 10f64.powf(rng.range(-6.0, -3.0)) as f32;
            let a1 = (1e-6 * (1.0 + j as f64 / masks as f64)) as f32;
            for (slot, (g, w)) in [(1u32, a1), (3u32, a)].into_iter().enumerate() {
                entries.push(Entry {
                    gaussian: g,
                    mask: j as u32,
                    weight: w,
                });
                den[slot].add(w as f64);
                for d in 0..dim {
                    num[slot * dim + d].add(w as f64 * e[d] as f64);
                }
            }
            naive_f32_den += a;
            emb.extend_from_slice(&e);
        }
        entries.sort_by_key(|e| (e.gaussian, e.mask));
        store
            .push(ImageContribution {
                dim,
                mask_embeddings: emb,
                entries,
            })
            .expect("push");
    }
    let r = reduce(&store, 5, dim, ReduceParams::default()).expect("reduce");
    assert_eq!(r.ids, vec![1, 3], "observed set");
    let mut worst_vec = 0f64;
    let mut worst_w = 0f64;
    for (slot, &id) in r.ids.iter().enumerate() {
        let reference: Vec<f64> = (0..dim).map(|d| num[slot * dim + d].value()).collect();
        let n = reference.iter().map(|v| v * v).sum::<f64>().sqrt();
        let got = &r.vectors[slot * dim..(slot + 1) * dim];
        for d in 0..dim {
            worst_vec = worst_vec.max((got[d] as f64 - reference[d] / n).abs());
        }
        let w_rel = (r.total_weights[slot] as f64 - den[slot].value()).abs() / den[slot].value();
        worst_w = worst_w.max(w_rel);
        assert!(got.iter().all(|v| v.is_finite()), "Gaussian {id}");
    }
    let naive_rel = (naive_f32_den as f64 - den[1].value()).abs() / den[1].value();
    eprintln!(
        "1e6 contributions: max |E_k - reference| = {worst_vec:.2e} (unit vectors, f32 output), \
         Σa relative error {worst_w:.2e}; a plain f32 running sum would be off by {naive_rel:.2e}"
    );
    // f32 output rounding is 6e-8 per component; the f64 reduction adds nothing visible.
    assert!(worst_vec < 2e-7, "{worst_vec}");
    assert!(worst_w < 1.2e-7, "{worst_w}");
}

#[test]
fn vanishing_weights_and_cancelling_masks_are_unobserved_never_nan() {
    let dim = 4;
    let e = vec![
        0.5f32, 0.5, 0.5, 0.5, // mask 0
        -0.5, -0.5, -0.5, -0.5, // mask 1 = -mask 0
        1.0, 0.0, 0.0, 0.0, // mask 2
    ];
    let entries = vec![
        // Gaussian 0: Σa = 1e-30 + 1e-38 (far below min_total_weight 1e-6).
        Entry {
            gaussian: 0,
            mask: 0,
            weight: 1e-30,
        },
        Entry {
            gaussian: 0,
            mask: 2,
            weight: 1e-38,
        },
        // Gaussian 1: subnormal weights only.
        Entry {
            gaussian: 1,
            mask: 0,
            weight: 1e-44,
        },
        // Gaussian 2: two masks that cancel exactly, large weight.
        Entry {
            gaussian: 2,
            mask: 0,
            weight: 3.5,
        },
        Entry {
            gaussian: 2,
            mask: 1,
            weight: 3.5,
        },
        // Gaussian 3: a real observation (control: the test can fail).
        Entry {
            gaussian: 3,
            mask: 0,
            weight: 1e-3,
        },
        Entry {
            gaussian: 3,
            mask: 2,
            weight: 3e-3,
        },
        // Gaussian 4: a NaN weight (corrupt input) is unobserved, not a NaN vector.
        Entry {
            gaussian: 4,
            mask: 2,
            weight: f32::NAN,
        },
    ];
    let tmp = std::env::temp_dir().join(format!("slag-stability-v-{}", std::process::id()));
    let mut store = ContributionStore::new(usize::MAX, tmp);
    store
        .push(ImageContribution {
            dim,
            mask_embeddings: e,
            entries,
        })
        .expect("push");
    let r = reduce(&store, 6, dim, ReduceParams::default()).expect("reduce");
    assert_eq!(r.ids, vec![3]);
    assert!(r.vectors.iter().all(|v| v.is_finite()));
    // E_3 ∝ 1e-3·(0.5,0.5,0.5,0.5) + 3e-3·(1,0,0,0) = (3.5, 0.5, 0.5, 0.5)·1e-3.
    let want = unit(vec![3.5, 0.5, 0.5, 0.5]);
    for (a, b) in r.vectors.iter().zip(&want) {
        assert!((a - b).abs() < 1e-6, "{:?} vs {want:?}", r.vectors);
    }
    assert!((r.total_weights[0] - 4e-3).abs() < 1e-9);
}
