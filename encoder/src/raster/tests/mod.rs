//! Tests of the weight rasterizers: GPU vs the f64 CPU reference (random scenes and the real
//! snowmiku scene), invariants, and a colour render of snowmiku against its training photos.
//!
//! GPU tests run on whatever Vulkan adapter [`GpuRasterizer::new`] picks (lavapipe in CI). Without
//! one they fail, unless `SLAG_SKIP_GPU=1` is set.
//!
//! The files: [`weights`] compares the per-pixel weights with the CPU reference; [`label_sums`]
//! checks the label sums and their device reduction against the host's image stage; [`sort`]
//! the GPU's binning and depth sort; [`device_reduction`] the reduction kept on the device. This
//! file holds the scenes, cameras and masks they share.

mod coverage;
mod device_reduction;
mod label_sums;
mod sort;
mod weights;

use std::path::PathBuf;

use glam::{DMat3, DQuat, DVec3};
use slag_common::camera::{Intrinsics, WorldToCamera};
use slag_common::rng::SplitMix64;
use slag_common::scene::Gaussians;

use crate::raster::project::{ALPHA_MIN, Splat2d, T_MIN, TILE_SIZE, splat_alpha};
use crate::raster::testdata::{
    gpu_unless_skipped, load_ply_for_test, load_views_for_test, skip_gpu, snowmiku_dir,
};
use crate::raster::*;

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
    pub(super) fn new(
        seed: u64,
        salt: u64,
        dim: usize,
        params: crate::aggregate::ImageStageParams,
    ) -> Self {
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
