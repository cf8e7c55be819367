//! The GPU's binning and depth sort of a view against the host reference: keys, order, tile
//! ranges, many Gaussians per tile and empty views.

use super::weights::compare;
use super::*;

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
