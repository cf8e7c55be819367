//! The streamed device reduction ([`WeightRasterizer::stream_kept`]) against the all-kept one.

use super::tests::{RandomKeptView, gpu, random_scene};
use super::*;
use crate::aggregate::{ImageStageParams, MaskWeighting, ReduceParams};
use slag_common::scene::Gaussians;

const DIM: usize = 70;
const KEEP: usize = 3;
/// Bytes of a tile of the reduction: several tiles per scene.
const TILE: u64 = 400_000;

/// What one reduction gives: per tile its outputs, and the reduction's figures.
struct Reduced {
    tiles: Vec<KeptTile>,
    out: KeptReduced,
}

/// The kept views, reduced on a fresh GPU rasterizer of `g`: kept in `order` (as fronts finish
/// them), each followed by [`WeightRasterizer::fold_kept`] with the lowest view not kept yet;
/// streamed with a budget of `stream_budget` bytes, or every view kept to the end without;
/// tiles of the reduction of `tile_bytes`.
/// `None` only where the GPU tests are skipped.
fn reduce_views(
    g: &Gaussians,
    views: &[RandomKeptView],
    order: &[usize],
    stream_budget: Option<u64>,
    tile_bytes: u64,
) -> Option<Reduced> {
    try_reduce_views(g, views, order, stream_budget, tile_bytes).map(|r| r.expect("reduced"))
}

/// [`reduce_views`], with the reduction's error.
fn try_reduce_views(
    g: &Gaussians,
    views: &[RandomKeptView],
    order: &[usize],
    stream_budget: Option<u64>,
    tile_bytes: u64,
) -> Option<slag_common::Result<Reduced>> {
    let mut r = gpu(g)?;
    assert!(r.keep_on_device(DIM, stream_budget.unwrap_or(1 << 30), true));
    r.set_reduce_tile_bytes(Some(tile_bytes));
    if stream_budget.is_some() {
        assert!(r.stream_kept(KEEP), "the state fits half the budget");
    }
    let mut done = vec![false; views.len()];
    for &v in order {
        views[v].keep_on(&mut r, false).expect("kept");
        done[v] = true;
        let below = done.iter().position(|d| !d).unwrap_or(done.len());
        r.fold_kept(below).unwrap();
    }
    let p = DeviceReduce {
        min_total_weight: ReduceParams::default().min_total_weight,
        keep: KEEP,
        dense: false,
        gaussians: None,
    };
    let mut tiles = Vec::new();
    let out = r.reduce_kept(&p, &mut |t| {
        tiles.push(t);
        Ok(())
    });
    Some(out.map(|out| Reduced { tiles, out }))
}

/// `n` random views of width [`DIM`] with overlapping, area-weighted masks.
fn random_views(n: u64) -> Vec<RandomKeptView> {
    let params = ImageStageParams {
        mask_weighting: MaskWeighting::Area,
        ..Default::default()
    };
    (0..n)
        .map(|seed| RandomKeptView::new(seed, seed ^ 0xE3B, DIM, params))
        .collect()
}

/// One observed Gaussian: its id, its `Σ a_kj` bits and its kept pairs (bits, in slot order).
type Row = (u32, u32, Vec<(u32, u32)>);

/// Every observed Gaussian of `r` ([`Row`]).
fn rows_of(r: &Reduced) -> Vec<Row> {
    r.tiles
        .iter()
        .flat_map(|t| {
            (0..t.ids.len()).map(move |i| {
                let kept = t
                    .kept_of(i)
                    .iter()
                    .map(|&(a, j)| (a.to_bits(), j))
                    .collect();
                (t.ids[i], t.total_weights[i].to_bits(), kept)
            })
        })
        .collect()
}

/// The state of `n` Gaussians with [`KEEP`] pairs each, in bytes.
fn state_bytes(n: usize) -> u64 {
    n as u64 * (8 + 8 * KEEP as u64)
}

/// Streamed, the reduction gives the all-kept reduction's bytes: the same observed Gaussians,
/// the same `Σ a_kj` bits, the same kept pairs in the same slots and the same codebook, at
/// two budgets small enough that the views go in several waves, with the views kept out of
/// order (a wave takes only the views before the first not kept yet).
#[test]
fn streamed_reduction_equals_the_all_kept_reduction() {
    let n = 20_000;
    let g = random_scene(11, n);
    let views = random_views(12);
    // Pairs finished out of order, as fronts finish them.
    let order = [1usize, 0, 3, 2, 5, 4, 7, 6, 9, 8, 11, 10];
    let Some(all) = reduce_views(&g, &views, &order, None, TILE) else {
        return;
    };
    assert_eq!(all.out.waves, 1);
    let records = all.out.peak_kept_bytes;
    let expected = rows_of(&all);
    assert!(expected.len() > 100, "{} observed: too few", expected.len());
    // The records of the views not folded may take 60 % and 45 % of every view's records: a
    // wave at half of that.
    let state = state_bytes(n);
    for share in [0.6, 0.45] {
        let budget = state + (records as f64 * share) as u64;
        let streamed = reduce_views(&g, &views, &order, Some(budget), TILE).expect("a GPU");
        assert!(
            streamed.out.waves >= 3,
            "{} waves at {share} of the records",
            streamed.out.waves
        );
        assert_eq!(streamed.out.state_bytes, state);
        assert!(
            streamed.out.peak_kept_bytes + state <= budget,
            "peak {} + state {state} within the budget {budget}",
            streamed.out.peak_kept_bytes
        );
        assert_eq!(
            streamed.out.codebook, all.out.codebook,
            "codebook at {share}"
        );
        let got = rows_of(&streamed);
        assert_eq!(got.len(), expected.len(), "observed Gaussians at {share}");
        for (s, a) in got.iter().zip(&expected) {
            assert_eq!(s, a, "Gaussian {} at {share}", a.0);
        }
    }
}

/// Streamed, the device holds no more with 64 views than with 8: with a budget that holds 8
/// views' records beside the state, 64 views go through in waves within the same budget (kept
/// at once, they take several times it), and give the bytes that waves twice as large give.
#[test]
fn streamed_memory_stays_flat_as_the_views_grow() {
    let n = 8_000;
    let g = random_scene(5, n);
    let views = random_views(64);
    let state = state_bytes(n);
    let first: Vec<usize> = (0..8).collect();
    let Some(eight) = reduce_views(&g, &views[..8], &first, None, TILE) else {
        return;
    };
    let budget = state + eight.out.peak_kept_bytes;
    let order: Vec<usize> = (0..64).collect();
    let streamed_8 = reduce_views(&g, &views[..8], &first, Some(budget), TILE).expect("a GPU");
    let streamed_64 = reduce_views(&g, &views, &order, Some(budget), TILE).expect("a GPU");
    let larger = budget + eight.out.peak_kept_bytes;
    let larger_64 = reduce_views(&g, &views, &order, Some(larger), 2 * TILE).expect("a GPU");
    assert_eq!(eight.out.records_bytes, eight.out.peak_kept_bytes);
    assert!(
        streamed_64.out.records_bytes > 4 * (budget - state),
        "64 views' records ({} B) are several times what the budget leaves them ({} B): the \
         test means something",
        streamed_64.out.records_bytes,
        budget - state
    );
    for (count, s) in [(8, &streamed_8), (64, &streamed_64)] {
        assert!(
            s.out.peak_kept_bytes + s.out.state_bytes <= budget,
            "{count} views: {} B kept + {} B state within {budget} B",
            s.out.peak_kept_bytes,
            s.out.state_bytes
        );
    }
    assert!(
        streamed_64.out.waves >= 6,
        "{} waves",
        streamed_64.out.waves
    );
    assert!(
        larger_64.out.waves < streamed_64.out.waves,
        "{} waves with the larger budget",
        larger_64.out.waves
    );
    assert_eq!(rows_of(&streamed_64), rows_of(&larger_64));
    assert_eq!(rows_of(&streamed_8), rows_of(&eight));
}

/// What two devices that stream together give ([`WeightRasterizer::stream_kept_share`]):
/// each device's reduction of its share, in share order.
struct Shared {
    shares: Vec<Reduced>,
}

impl Shared {
    /// Every observed Gaussian of both shares, in Gaussian order ([`rows_of`]).
    fn rows(&self) -> Vec<Row> {
        self.shares.iter().flat_map(rows_of).collect()
    }
}

/// The views reduced on two fresh GPU rasterizers of `g` that stream together within
/// `budget` bytes each, view `v` kept on device `v % 2`, in `order` (as fronts finish them);
/// after each view, the device that kept it folds what is due below the lowest view not kept
/// on either (a view is sent as it is kept). `None` only where the GPU tests are skipped.
fn reduce_shared(
    g: &Gaussians,
    views: &[RandomKeptView],
    order: &[usize],
    budget: u64,
) -> Option<Shared> {
    let mut devices = [gpu(g)?, gpu(g)?];
    let inboxes: Vec<_> = devices
        .iter_mut()
        .enumerate()
        .map(|(i, r)| {
            assert!(r.keep_on_device(DIM, budget, true));
            r.set_reduce_tile_bytes(Some(TILE));
            r.stream_kept_share(KEEP, i, 2)
                .expect("the share's state fits the budget")
        })
        .collect();
    for (i, r) in devices.iter_mut().enumerate() {
        let mut peers = inboxes.clone();
        peers.remove(i);
        r.share_kept_with(Some(peers));
    }
    let mut done = vec![false; views.len()];
    for &v in order {
        let r = &mut devices[v % 2];
        views[v].keep_on(r, false).expect("kept");
        done[v] = true;
        let below = done.iter().position(|d| !d).unwrap_or(done.len());
        r.fold_kept(below).unwrap();
    }
    let shares = devices
        .iter_mut()
        .map(|r| {
            let p = DeviceReduce {
                min_total_weight: ReduceParams::default().min_total_weight,
                keep: KEEP,
                dense: false,
                gaussians: r.kept_share(),
            };
            let mut tiles = Vec::new();
            let out = r
                .reduce_kept(&p, &mut |t| {
                    tiles.push(t);
                    Ok(())
                })
                .unwrap();
            Reduced { tiles, out }
        })
        .collect();
    Some(Shared { shares })
}

/// The scene, views and order both 32-view tests share: 20,000 Gaussians, 32 random views kept
/// in the order `i ^ 1`, the first 8 of them in that order, and those 8 kept to the end on one
/// device. `None` without a GPU.
struct ThirtyTwo {
    n: usize,
    g: Gaussians,
    views: Vec<RandomKeptView>,
    order: Vec<usize>,
    eight: Vec<usize>,
    all_8: Reduced,
}

fn thirty_two_views() -> Option<ThirtyTwo> {
    let n = 20_000;
    let g = random_scene(11, n);
    let views = random_views(32);
    let order: Vec<usize> = (0..32).map(|i| i ^ 1).collect();
    let eight: Vec<usize> = order.iter().copied().filter(|&v| v < 8).collect();
    let all_8 = reduce_views(&g, &views[..8], &eight, None, TILE)?;
    Some(ThirtyTwo {
        n,
        g,
        views,
        order,
        eight,
        all_8,
    })
}

/// Two devices that stream together, each folding its share of the Gaussians as the views
/// come (each view kept on one of them and sent to the other), give the bytes of one device
/// alone (with 8 views, keeping every view to the end; with 32, streaming): the same observed
/// Gaussians, `Σ a_kj` bits, kept pairs in the same slots and the same codebook on both, with
/// the views kept out of order (with 32 views, in several waves on each device). With 32 views
/// the devices hold no more than with 8: within the same budget, in more waves.
#[test]
fn two_devices_streaming_together_equal_one_device() {
    let Some(ThirtyTwo {
        n,
        g,
        views,
        order,
        eight,
        all_8,
    }) = thirty_two_views()
    else {
        return;
    };
    // Each device's state covers its half of the Gaussians; beside it, about a third of the
    // records of 8 views (half of them sent on as they come).
    let state = state_bytes(n.div_ceil(2).next_multiple_of(4096));
    let budget = state + all_8.out.peak_kept_bytes / 3;
    // 32 views against one device streaming alone, with room for 8 views' records.
    let alone = state_bytes(n) + all_8.out.peak_kept_bytes;
    let all_32 = reduce_views(&g, &views, &order, Some(alone), TILE).expect("a GPU");
    let shared_8 = reduce_shared(&g, &views[..8], &eight, budget).expect("a GPU");
    let shared_32 = reduce_shared(&g, &views, &order, budget).expect("a GPU");
    assert!(
        all_8.out.records_bytes * 4 > 8 * (budget - state),
        "32 views' records (about {} B) are many times what the budget leaves them: the test \
         means something",
        all_8.out.records_bytes * 4
    );
    for (count, all, shared) in [(8, &all_8, &shared_8), (32, &all_32, &shared_32)] {
        let expected = rows_of(all);
        assert!(expected.len() > 100, "{} observed: too few", expected.len());
        assert_eq!(shared.rows(), expected, "{count} views");
        for (d, s) in shared.shares.iter().enumerate() {
            assert_eq!(
                s.out.codebook, all.out.codebook,
                "{count} views: device {d}"
            );
            let waves = if count == 32 { 3 } else { 1 };
            assert!(
                s.out.waves >= waves,
                "{count} views: device {d}: {} waves",
                s.out.waves
            );
            assert!(
                s.out.peak_kept_bytes + s.out.state_bytes <= budget,
                "{count} views: device {d}: {} B kept + {} B state within {budget} B",
                s.out.peak_kept_bytes,
                s.out.state_bytes
            );
        }
    }
    for d in 0..2 {
        let (w8, w32) = (shared_8.shares[d].out.waves, shared_32.shares[d].out.waves);
        assert!(
            w32 > w8,
            "device {d}: {w32} waves with 32 views, {w8} with 8"
        );
    }
}

/// In one reduction, kept to the end or streamed in one wave, 32 views give the bytes they
/// give streamed in several waves, or, where the driver cuts the reduction's loops short, an
/// error that says so and names `--reduce host`: never other bytes. Lavapipe ends a shader
/// invocation's loops after 65,535 iterations in all; here one Gaussian has 831 kept label
/// sums over 23 views, more than `ek_reduce` or `ek_fold` can take there in one invocation
/// (they took 668 and wrote 1 of its 3 kept pairs), while a wave of 8 views' records stays
/// within.
#[test]
fn thirty_two_views_in_one_reduction_equal_them_in_waves_or_fail() {
    let Some(ThirtyTwo {
        n,
        g,
        views,
        order,
        all_8,
        ..
    }) = thirty_two_views()
    else {
        return;
    };
    let budget = state_bytes(n) + all_8.out.peak_kept_bytes;
    let waves = reduce_views(&g, &views, &order, Some(budget), TILE).expect("a GPU");
    assert!(waves.out.waves >= 3, "{} waves", waves.out.waves);
    let expected = rows_of(&waves);
    assert!(expected.len() > 100, "{} observed: too few", expected.len());
    let kept = try_reduce_views(&g, &views, &order, None, TILE).expect("a GPU");
    let one_wave = try_reduce_views(&g, &views, &order, Some(1 << 29), 1 << 26).expect("a GPU");
    for (what, reduced) in [
        ("kept to the end", kept),
        ("streamed in one wave", one_wave),
    ] {
        match reduced {
            Ok(one) => {
                assert_eq!(one.out.waves, 1, "{what}");
                assert_eq!(one.out.codebook, waves.out.codebook, "{what}");
                let got = rows_of(&one);
                assert_eq!(got.len(), expected.len(), "{what}: observed Gaussians");
                for (a, s) in got.iter().zip(&expected) {
                    assert_eq!(a, s, "{what}: Gaussian {}", s.0);
                }
            }
            Err(slag_common::Error::Gpu(message)) => {
                assert!(
                    message.contains("cut short") && message.contains("--reduce host"),
                    "{what}: {message}"
                );
            }
            Err(e) => panic!("{what}: {e}"),
        }
    }
}
