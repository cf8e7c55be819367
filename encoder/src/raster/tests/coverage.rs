//! The coverage pass on the device ([`WeightRasterizer::coverage_view`]) against the label sums
//! with every pixel in one label: the same Gaussians at the floor, and the same largest totals.

use super::*;

/// Ids whose bit is set in `words` (bit `k % 64` of word `k / 64`).
fn set_bits(words: &[u64]) -> Vec<u32> {
    let mut ids = Vec::new();
    for (w, &word) in words.iter().enumerate() {
        for b in 0..64 {
            if word >> b & 1 == 1 {
                ids.push((w * 64 + b) as u32);
            }
        }
    }
    ids
}

/// For floors from "any contribution" to above most totals, and three views in turn: the
/// device's bitset holds exactly the Gaussians whose label-sum total (every pixel in label 1)
/// reaches the floor, and its kept maxima are, per Gaussian, the largest such total over the
/// views that saw it (0 for none), read once and then forgotten. Totals past one pixel (the
/// high word's carry) occur in the scene, so the 64-bit sums are exercised.
#[test]
fn the_device_pass_sees_what_the_label_sums_reach_and_keeps_their_maxima() {
    let g = random_scene(41, 2000);
    let cameras: Vec<_> = [41u64, 42, 43].iter().map(|&s| test_camera(s)).collect();
    let Some(mut gpu) = gpu(&g) else { return };
    let totals: Vec<Vec<(u32, u64)>> = cameras
        .iter()
        .map(|(k, w2c)| {
            let labels = vec![1u32; (k.width * k.height) as usize];
            let sums = gpu.label_sums(k, w2c, &labels).expect("sums").expect("gpu");
            sums.reduced()
                .into_iter()
                .map(|s| (s.gaussian, s.sum))
                .collect()
        })
        .collect();
    assert!(
        totals.iter().flatten().any(|&(_, t)| t > 1 << 32),
        "some Gaussian takes more than a pixel of weight"
    );
    let mut all: Vec<u64> = totals.iter().flatten().map(|&(_, t)| t).collect();
    all.sort_unstable();
    for floor in [0, 1, all[all.len() / 2], 1 << 32, all[all.len() - 1] + 1] {
        let mut want_max = vec![0u64; g.len()];
        for ((k, w2c), view_totals) in cameras.iter().zip(&totals) {
            let bits = gpu
                .coverage_view(k, w2c, floor, None)
                .expect("coverage view")
                .expect("the GPU rasterizer has the pass");
            assert_eq!(bits.len(), g.len().div_ceil(64));
            let want: Vec<u32> = view_totals
                .iter()
                .filter(|&&(_, t)| t >= floor.max(1))
                .map(|&(id, _)| id)
                .collect();
            assert_eq!(set_bits(&bits), want, "floor {floor}");
            for &(id, t) in view_totals.iter().filter(|&&(_, t)| t >= floor.max(1)) {
                want_max[id as usize] = want_max[id as usize].max(t);
            }
        }
        let maxima = gpu.take_coverage_maxima().expect("maxima").expect("gpu");
        assert_eq!(maxima, want_max, "floor {floor}");
        let after = gpu.take_coverage_maxima().expect("again").expect("gpu");
        assert!(after.iter().all(|&m| m == 0), "maxima are forgotten");
    }
    let mut cpu = CpuRasterizer::new(&g);
    let (k, w2c) = &cameras[0];
    assert!(cpu.coverage_view(k, w2c, 1, None).unwrap().is_none());
    assert!(cpu.take_coverage_maxima().unwrap().is_none());
}
