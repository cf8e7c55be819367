#![allow(clippy::unwrap_used)]

use super::forest::Forest;
use super::neighbours::NO_NEIGHBOUR;
use super::reference;
use super::regions::{PROFILE_CAP, merge_profiles, region_disagreement};
use super::weights::Edge;
use super::*;

/// The next value in `[0, 1)` of a 64-bit linear congruential sequence with state `s` (its top
/// 24 bits): deterministic test data.
fn unit_lcg(s: &mut u64) -> f32 {
    *s = s
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    (*s >> 40) as f32 / (1u64 << 24) as f32
}

/// A scene of flat Gaussians on planes: the floor z = 0 over `[0, 4]²`, a wall x = 0 over
/// `y, z ∈ [0, 2]`, and a box (its top face at z = 1 over `[2.5, 3.5]²`) floating apart,
/// on a grid of spacing 0.1 with a little deterministic jitter. Returns the Gaussians and
/// each one's surface (0 floor, 1 wall, 2 box top).
fn planes() -> (Gaussians, Vec<u8>) {
    let mut g = Gaussians::default();
    let mut label = Vec::new();
    let mut s = 7u64;
    let mut jitter = || (unit_lcg(&mut s) - 0.5) * 0.01;
    // Rotations taking the local z axis (smallest scale) to the plane's normal.
    let z_up = [1.0, 0.0, 0.0, 0.0];
    let x_normal = [0.5f32.sqrt(), 0.0, 0.5f32.sqrt(), 0.0]; // z → x
    let mut push = |m: [f32; 3], q: [f32; 4], l: u8, g: &mut Gaussians| {
        g.means.push(m);
        g.scales.push([0.05, 0.05, 0.002]);
        g.rotations.push(q);
        g.opacities.push(0.9);
        label.push(l);
    };
    for a in 0..40 {
        for b in 0..40 {
            let m = [
                a as f32 * 0.1 + 0.05 + jitter(),
                b as f32 * 0.1 + 0.05 + jitter(),
                jitter(),
            ];
            push(m, z_up, 0, &mut g);
        }
    }
    for a in 0..20 {
        for b in 0..20 {
            let m = [
                jitter(),
                a as f32 * 0.1 + 0.05 + jitter(),
                b as f32 * 0.1 + 0.15 + jitter(),
            ];
            push(m, x_normal, 1, &mut g);
        }
    }
    for a in 0..10 {
        for b in 0..10 {
            let m = [
                2.5 + a as f32 * 0.1 + jitter(),
                2.5 + b as f32 * 0.1 + jitter(),
                1.0 + jitter(),
            ];
            push(m, z_up, 2, &mut g);
        }
    }
    (g, label)
}

fn params() -> SegmentParams {
    SegmentParams {
        max_edge: Some(0.5),
        ..SegmentParams::default()
    }
}

/// [`params`] in tiles of `tile_gaussians`.
fn params_in_tiles(tile_gaussians: usize) -> SegmentParams {
    SegmentParams {
        tile_gaussians,
        ..params()
    }
}

#[test]
fn planes_become_their_own_segments() {
    let (g, label) = planes();
    let (s, stats) = segment(&g, &params(), "planes", None).unwrap();
    assert_eq!(stats.tiles, 1);
    // Each surface is one segment, and no segment mixes surfaces.
    for l in 0..3u8 {
        let ids: std::collections::BTreeSet<u32> = (0..g.len())
            .filter(|&i| label[i] == l)
            .map(|i| s.segments[i])
            .collect();
        assert_eq!(ids.len(), 1, "surface {l} split into {ids:?}");
    }
    assert_eq!(s.segment_count, 3, "{stats:?}");
    s.validate().unwrap();
}

#[test]
fn deterministic_over_thread_counts() {
    let (g, _) = planes();
    let p = params_in_tiles(500);
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let a = one.install(|| segment(&g, &p, "x", None).unwrap().0);
    let b = segment(&g, &p, "x", None).unwrap().0;
    assert_eq!(a, b);
}

/// The tiled result equals, over the whole graph: each tile's criterion pass over its inner
/// edges, then the border pass over the border edges in order, given the components their
/// ends met in their own tile where each edge falls in the order, then
/// the minimum-size pass in tile-grouped order (every tile's inner edges, then the border
/// edges): the statement of the module doc, checked here by brute force (a fresh pass per
/// border end). One tile equals the untiled algorithm.
#[test]
fn tiles_equal_the_tile_grouped_order() {
    let (mut g, _) = planes();
    // Rough normals so that segments straddle tile borders.
    for (i, q) in g.rotations.iter_mut().enumerate() {
        let t = (i % 7) as f32 * 0.15;
        *q = [t.cos(), t.sin(), 0.0, 0.0];
    }
    let p = SegmentParams {
        tile_gaussians: 400,
        threshold: 0.2,
        ..params()
    };
    let (tiled, stats) = segment(&g, &p, "x", None).unwrap();
    assert!(stats.tiles > 4 && stats.border_edges > 0, "{stats:?}");
    // Reference: the whole graph from one tile, reordered by the tiling.
    let all = reference::all_edges(&g, &p);
    let (_, tile_of, rects) = plan_tiles(&g.means, p.tile_gaussians);
    let tile = |x: u32| tile_of[x as usize];
    let inner_of = |t: u32| -> Vec<Edge> {
        all.iter()
            .filter(|e| tile(e.i) == t && tile(e.j) == t)
            .copied()
            .collect()
    };
    let border: Vec<Edge> = all
        .iter()
        .filter(|e| tile(e.i) != tile(e.j))
        .copied()
        .collect();
    let met_at = |b: &Edge, x: u32| {
        let before: Vec<Edge> = inner_of(tile(x)).into_iter().filter(|e| e < b).collect();
        let mut f = Forest::singletons(g.len());
        f.criterion_pass(&before, p.threshold);
        f.component_of(x)
    };
    let met: Vec<_> = border
        .iter()
        .map(|b| [met_at(b, b.i), met_at(b, b.j)])
        .collect();
    let mut order: Vec<Edge> = Vec::new();
    let mut f = Forest::singletons(g.len());
    for t in 0..rects.len() as u32 {
        let inner = inner_of(t);
        f.criterion_pass(&inner, p.threshold);
        order.extend(inner);
    }
    f.border_pass_in(&border, &met, p.threshold, None);
    order.extend(&border);
    assert_eq!(order.len() as u64, stats.edges);
    f.min_size_pass(&order, p.min_size, |_| true);
    let roots: Vec<u32> = (0..g.len() as u32).map(|i| f.find(i)).collect();
    assert_eq!(canonical_ids(&roots).0, tiled.segments);
    // The border edges judged by their components after every tile's pass instead (the
    // rule the border pass replaces) join other segments on this scene.
    let mut late = Forest::singletons(g.len());
    late.criterion_pass(&order, p.threshold);
    late.min_size_pass(&order, p.min_size, |_| true);
    let roots: Vec<u32> = (0..g.len() as u32).map(|i| late.find(i)).collect();
    assert_ne!(canonical_ids(&roots).0, tiled.segments);
    // One tile: the ascending order itself.
    let single = SegmentParams {
        tile_gaussians: usize::MAX,
        ..p
    };
    let (untiled, _) = segment(&g, &single, "x", None).unwrap();
    let mut f = Forest::singletons(g.len());
    f.criterion_pass(&all, p.threshold);
    f.min_size_pass(&all, p.min_size, |_| true);
    let roots: Vec<u32> = (0..g.len() as u32).map(|i| f.find(i)).collect();
    assert_eq!(canonical_ids(&roots).0, untiled.segments);
}

/// Where every piece is one Gaussian (no inner edges), the border pass is the criterion pass
/// itself: a group's summed sizes and `Int` are its component's, so a line of joins is held
/// to its growing size exactly as one pass holds it.
#[test]
fn the_border_pass_over_single_gaussians_is_the_criterion_pass() {
    let mut s = 7u64;
    for round in 0..20 {
        let n = 60;
        let mut edges: Vec<Edge> = (0..240)
            .map(|_| {
                let i = (unit_lcg(&mut s) * n as f32) as u32 % n;
                let j = (i + 1 + (unit_lcg(&mut s) * 4.0) as u32) % n;
                Edge {
                    w: (unit_lcg(&mut s) * 0.6).to_bits(),
                    i: i.min(j),
                    j: i.max(j),
                }
            })
            .filter(|e| e.i != e.j)
            .collect();
        edges.sort_unstable();
        edges.dedup();
        let tau = 0.2 + 0.1 * (round % 5) as f32;
        let single = Forest::singletons(1).component_of(0);
        let met = vec![[single; 2]; edges.len()];
        let mut by_border = Forest::singletons(n as usize);
        by_border.border_pass_in(&edges, &met, tau, None);
        let mut by_criterion = Forest::singletons(n as usize);
        by_criterion.criterion_pass(&edges, tau);
        let ids = |f: &mut Forest| {
            let roots: Vec<u32> = (0..n).map(|i| f.find(i)).collect();
            canonical_ids(&roots).0
        };
        assert_eq!(ids(&mut by_border), ids(&mut by_criterion), "round {round}");
    }
}

#[test]
fn clean_planes_do_not_depend_on_tiles() {
    let (g, _) = planes();
    let a = segment(&g, &params(), "x", None).unwrap().0;
    let b = segment(
        &g,
        &SegmentParams {
            tile_gaussians: 300,
            ..params()
        },
        "x",
        None,
    )
    .unwrap()
    .0;
    // The same segments (the recorded parameters differ: the tile count).
    assert_eq!(a.segments, b.segments);
    assert_eq!(a.segment_count, 3);
}

#[test]
fn a_stop_gives_no_result_and_pools_do_not_change_it() {
    let (g, _) = planes();
    let p = params_in_tiles(500);
    let stopped = SegmentControl::default();
    stopped.stop();
    assert!(
        segment_with(&g, &p, "x", &stopped, || None)
            .unwrap()
            .is_none()
    );
    let pool = |n| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build()
            .unwrap()
    };
    let ctl = SegmentControl::new(Some(pool(1)));
    let narrow = segment_with(&g, &p, "x", &ctl, || None).unwrap().unwrap().0;
    ctl.set_pool(pool(3));
    let wide = segment_with(&g, &p, "x", &ctl, || None).unwrap().unwrap().0;
    let plain = segment(&g, &p, "x", None).unwrap().0;
    assert_eq!(narrow, plain);
    assert_eq!(wide, plain);
}

/// Pools and in-flight budgets that change while the tiles' passes run (as the encode widens
/// the segmentation's pool and lets its tiles hold more once it ends) lose no tile and change
/// no id: each stage runs on the pool of its moment, and each wave of tiles takes its size from
/// that pool and budget (one tile at a time under a budget of one byte).
#[test]
fn pools_changing_under_the_tiles_change_no_id() {
    use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
    let (g, _) = planes();
    let p = params_in_tiles(100);
    let plain = segment(&g, &p, "x", None).unwrap().0;
    let pool = |n| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build()
            .unwrap()
    };
    for pause_us in [50, 200, 800] {
        let ctl = SegmentControl::new(Some(pool(1)));
        let done = AtomicBool::new(false);
        let (got, switches) = std::thread::scope(|s| {
            let switcher = s.spawn(|| {
                let mut switches = 0;
                while !done.load(Relaxed) {
                    ctl.set_pool(pool(switches % 3 + 1));
                    ctl.set_in_flight_bytes([1, 1 << 20, usize::MAX][(switches / 2) % 3]);
                    switches += 1;
                    std::thread::sleep(std::time::Duration::from_micros(pause_us));
                }
                switches
            });
            let got = segment_with(&g, &p, "x", &ctl, || None).unwrap().unwrap().0;
            done.store(true, Relaxed);
            (got, switcher.join().unwrap())
        });
        assert!(switches > 1, "the pool changed {switches} times");
        assert_eq!(got, plain, "{pause_us} µs between pools");
    }
}

/// A shared scene is let go of before the masks' record is waited for (the passes after it need
/// only the count), and the ids are those of a borrowed scene.
#[test]
fn a_shared_scene_is_let_go_before_the_record() {
    let (g, _) = planes();
    let p = params_in_tiles(500);
    let shared = Arc::new(g);
    let kept = Arc::clone(&shared);
    let ctl = SegmentControl::default();
    let mut holders = None;
    let (got, _) = segment_with(shared, &p, "x", &ctl, || {
        holders = Some(Arc::strong_count(&kept));
        None
    })
    .unwrap()
    .unwrap();
    assert_eq!(holders, Some(1));
    assert_eq!(got, segment(&kept, &p, "x", None).unwrap().0);
}

/// What the stages after the geometry read: a borrowed scene lends its own means; a shared one
/// hands over equal means and lets go of the scene (a copy while the encode still holds it).
#[test]
fn a_scene_handle_gives_its_means_and_lets_go() {
    let (g, _) = planes();
    let borrowed = SceneHandle::into_means(&g);
    assert!(
        matches!(borrowed, std::borrow::Cow::Borrowed(m) if std::ptr::eq(m, g.means.as_slice()))
    );
    let shared = Arc::new(g.clone());
    let kept = Arc::clone(&shared);
    let copied = shared.into_means();
    assert_eq!(Arc::strong_count(&kept), 1);
    assert!(matches!(&copied, std::borrow::Cow::Owned(m) if *m == g.means));
    let last = kept.into_means();
    assert!(matches!(&last, std::borrow::Cow::Owned(m) if *m == g.means));
}

#[test]
fn region_profiles_sum_cap_and_disagree() {
    let a = vec![(0u16, 1u16, 2.0f32), (0, 2, 2.0), (3, 1, 1.0)];
    let b = vec![(0u16, 1u16, 1.0f32), (1, 5, 4.0)];
    let m = merge_profiles(&a, &b);
    assert_eq!(m, vec![(0, 1, 3.0), (0, 2, 2.0), (1, 5, 4.0), (3, 1, 1.0)]);
    // Same distribution in the one shared view: no disagreement; disjoint masks: 1.
    assert_eq!(region_disagreement(&a, &a), Some(0.0));
    let other = vec![(0u16, 7u16, 5.0f32)];
    assert_eq!(region_disagreement(&a, &other), Some(1.0));
    // View 0: a is half mask 1, b all mask 1: overlap 0.5 (view 3 and 1 not shared).
    assert_eq!(region_disagreement(&a, &b), Some(0.5));
    assert_eq!(region_disagreement(&a, &[(9, 0, 1.0)]), None);
    assert_eq!(region_disagreement(&a, &[]), None);
    // The cap keeps the heaviest entries, in (view, mask) order.
    let many: Vec<(u16, u16, f32)> = (0..100u16).map(|k| (k, 0, f32::from(k))).collect();
    let capped = merge_profiles(&many, &[]);
    assert_eq!(capped.len(), PROFILE_CAP);
    assert_eq!(capped[0].0 as usize, 100 - PROFILE_CAP);
    assert!(capped.windows(2).all(|w| w[0].0 < w[1].0));
}

#[test]
fn bad_settings_are_refused() {
    let (g, _) = planes();
    for p in [
        SegmentParams {
            neighbours: 0,
            ..params()
        },
        SegmentParams {
            threshold: f32::NAN,
            ..params()
        },
        SegmentParams {
            max_edge: Some(-1.0),
            ..params()
        },
        SegmentParams {
            region_veto: 1.5,
            ..params()
        },
    ] {
        assert!(matches!(
            segment(&g, &p, "x", None),
            Err(Error::Param { .. })
        ));
    }
}

/// A scene that tries the search's corners: a lattice (many exactly tied distances, ties by
/// id), duplicated means, a crowded clump (finer cells), isolated Gaussians beyond
/// `max_edge`, and varied sizes and normals.
fn corners() -> Gaussians {
    let mut g = Gaussians::default();
    let mut s = 11u64;
    let mut rnd = move || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (s >> 40) as f32 / (1u64 << 24) as f32
    };
    let push = |m: [f32; 3], r: f32, q: [f32; 4], g: &mut Gaussians| {
        g.means.push(m);
        g.scales.push([0.05 * r, 0.04 * r, 0.01 * r]);
        g.rotations.push(q);
        g.opacities.push(0.9);
    };
    for a in 0..30 {
        for b in 0..30 {
            let q = [1.0, 0.1 * (a % 3) as f32, 0.0, 0.1 * (b % 4) as f32];
            push([a as f32 * 0.1, b as f32 * 0.1, 0.0], 1.0, q, &mut g);
        }
    }
    for i in 0..200 {
        let m = g.means[i * 3];
        push(m, 1.5, [1.0, 0.0, 0.3, 0.0], &mut g);
    }
    for _ in 0..1500 {
        let m = [1.0 + 0.02 * rnd(), 1.0 + 0.02 * rnd(), 0.5 + 0.02 * rnd()];
        let q = [rnd(), rnd(), rnd(), rnd()];
        push(m, 0.2 + rnd(), q, &mut g);
    }
    for i in 0..40 {
        let m = [10.0 + i as f32 * 3.0, -5.0, 2.0 * rnd()];
        push(m, 1.0, [1.0, 0.0, 0.0, 0.0], &mut g);
    }
    for _ in 0..2000 {
        let m = [4.0 * rnd(), 4.0 * rnd(), 0.3 * rnd()];
        let q = [rnd(), rnd(), rnd(), rnd()];
        push(m, 0.5 + rnd(), q, &mut g);
    }
    g
}

/// A masks' record of `g` over 6 views with `slots` slots: masks by strips of the plane, each
/// view its own.
fn strips_record(g: &Gaussians, slots: usize) -> slag_common::mask_record::MaskRecord {
    let mut r = slag_common::mask_record::MaskRecord::new(g.len(), slots, 6).unwrap();
    for v in 0..6usize {
        let entries = (0..g.len() as u32)
            .filter(|&i| !(i as usize + v).is_multiple_of(3))
            .map(|i| {
                let m = g.means[i as usize];
                let mask = ((m[0] + 0.3 * v as f32) / 0.7).floor().max(0.0) as u32;
                (i, mask, 0.1 + 0.1 * ((i as usize * 7 + v) % 9) as f32)
            });
        r.add_view(v, entries);
    }
    r
}

#[test]
fn grid_neighbours_equal_the_tree_search() {
    let g = corners();
    for (k, h) in [(10, 0.5f32), (3, 0.05), (24, 2.0)] {
        let p = SegmentParams {
            neighbours: k,
            max_edge: Some(h),
            tile_gaussians: usize::MAX,
            ..params()
        };
        let (ax, one, rects) = plan_tiles(&g.means, usize::MAX);
        let tree = reference::neighbour_graph(&g, &p, h, ax, &one, &rects);
        let grid = graph::neighbour_graph(&g.means, &p, h, &SegmentControl::default())
            .unwrap()
            .in_id_order();
        let mut lonely = 0;
        for i in 0..g.len() {
            let a: Vec<u32> = tree.of(i).collect();
            assert_eq!(
                a,
                grid.of(i).collect::<Vec<u32>>(),
                "Gaussian {i}, k {k}, h {h}"
            );
            lonely += usize::from(a.len() < k);
        }
        assert!(
            lonely > 0 && lonely < g.len(),
            "k {k}, h {h}: {lonely} short lists"
        );
    }
    assert_eq!(NO_NEIGHBOUR, u32::MAX);
}

/// [`corners`] and its [`strips_record`].
fn corners_with_record() -> (
    Gaussians,
    std::sync::Arc<slag_common::mask_record::MaskRecord>,
) {
    let g = corners();
    let record = std::sync::Arc::new(strips_record(&g, 4));
    (g, record)
}

/// The parameters [`corners`] is segmented with, in tiles of `tile_gaussians`.
fn corners_params(tile_gaussians: usize) -> SegmentParams {
    SegmentParams {
        max_edge: Some(0.4),
        threshold: 0.3,
        ..params_in_tiles(tile_gaussians)
    }
}

#[test]
fn ids_equal_the_previous_implementation() {
    let (g, record) = corners_with_record();
    // The default slot count: the tiles read their rows as packed lines.
    let packed = std::sync::Arc::new(strips_record(&g, slag_common::mask_record::DEFAULT_SLOTS));
    let base = corners_params(700);
    for (p, masks) in [
        (base, None),
        (base, Some(&record)),
        (base, Some(&packed)),
        (
            SegmentParams {
                region_veto: 0.6,
                ..base
            },
            Some(&record),
        ),
        (
            SegmentParams {
                tile_gaussians: usize::MAX,
                ..base
            },
            Some(&record),
        ),
        (
            SegmentParams {
                min_size: 1,
                ..base
            },
            None,
        ),
    ] {
        let (s, stats) = segment(&g, &p, "x", masks.cloned()).unwrap();
        let want = reference::segment_ids(&g, &p, masks.map(|r| &**r));
        assert_eq!(s.segments, want, "{p:?}, record: {}", masks.is_some());
        assert!(stats.segments > 3, "{stats:?}");
        if p.tile_gaussians == 700 {
            assert!(stats.tiles > 4 && stats.border_edges > 0, "{stats:?}");
        }
    }
}

/// The minimum-size pass's mask veto, checked on the candidates of that pass only (after the
/// tiles' passes, with the default slot count's packed lines for the weights): the reference's
/// ids at a veto strict enough to change them.
#[test]
fn the_mask_veto_on_the_minimum_size_candidates_equals_the_reference() {
    let (g, _) = corners_with_record();
    let record = std::sync::Arc::new(strips_record(&g, slag_common::mask_record::DEFAULT_SLOTS));
    let ids = |mask_veto: f32| {
        let p = SegmentParams {
            mask_veto,
            min_size: 40,
            ..corners_params(700)
        };
        let (s, stats) = segment(&g, &p, "x", Some(record.clone())).unwrap();
        assert!(stats.tiles > 4, "{stats:?}");
        assert_eq!(
            s.segments,
            reference::segment_ids(&g, &p, Some(&*record)),
            "{p:?}"
        );
        s.segments
    };
    assert_ne!(ids(0.05), ids(1.0), "the veto must refuse some joins here");
}

#[test]
fn ids_do_not_depend_on_threads() {
    let (g, record) = corners_with_record();
    let p = corners_params(500);
    let on = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| segment(&g, &p, "x", Some(record.clone())).unwrap().0)
    };
    let one = on(1);
    assert!(one.segment_count > 3);
    assert_eq!(on(2), one);
    assert_eq!(on(7), one);
}

#[test]
fn root_ids_are_the_canonical_ids() {
    let roots: Vec<u32> = (0..500u32).map(|i| (i * 7919 % 97) * 5 % 500).collect();
    assert_eq!(canonical_root_ids(&roots), canonical_ids(&roots));
    // Several of the parallel numbering's chunks, with segments that span chunks.
    let n = 300_000u64;
    let roots: Vec<u32> = (0..n)
        .map(|i| ((i * 2_654_435_761 % 4_099) * 73 % n) as u32)
        .collect();
    assert_eq!(canonical_root_ids(&roots), canonical_ids(&roots));
}

/// The tile plan split in parallel over contiguous keys equals the one-thread plan over the
/// ids: the same tiles, numbered alike, with the same rectangles, on scenes large enough for
/// the parallel splits, with ties in the coordinates (a coarse grid) and without.
#[test]
fn parallel_tile_plan_equals_the_one_thread_plan() {
    let mut s = 11u64;
    let mut next = || unit_lcg(&mut s);
    let smooth: Vec<[f32; 3]> = (0..150_000)
        .map(|_| [next() * 8.0, next() * 3.0, next() * 0.5])
        .collect();
    let coarse: Vec<[f32; 3]> = smooth
        .iter()
        .map(|m| [(m[0] * 4.0).floor(), (m[1] * 4.0).floor(), m[2]])
        .collect();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(4)
        .build()
        .unwrap();
    for means in [&smooth, &coarse] {
        for cap in [2_000, 40_000, 150_000] {
            let parallel = pool.install(|| plan_tiles(means, cap));
            assert_eq!(parallel, reference::plan_tiles(means, cap), "cap {cap}");
            assert!(
                parallel.2.len() >= means.len() / cap,
                "{} tiles",
                parallel.2.len()
            );
        }
    }
}

/// A xorshift64 generator from `seed` (not 0): the edge tests' random numbers.
fn xorshift(seed: u64) -> impl FnMut() -> u64 {
    let mut state = seed;
    move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    }
}

#[test]
fn the_minimum_size_pass_over_the_first_edge_per_pair_joins_as_over_all() {
    // Random edges between near Gaussians of a line of 3,000, a criterion pass over the
    // lightest third (components of many sizes, many below the minimum), then the minimum-size
    // pass over the rest: over every edge between two components, against over the first edge
    // per pair of them.
    let n = 3_000u32;
    let mut next = xorshift(0x9e37_79b9_7f4a_7c15);
    let mut edges: Vec<Edge> = (0..40_000)
        .map(|_| {
            let a = (next() % n as u64) as u32;
            let b = (a + 1 + (next() % 24) as u32).min(n - 1);
            let w = (next() % 4_000) as f32 / 1_000.0;
            Edge {
                w: w.to_bits(),
                i: a.min(b),
                j: a.max(b),
            }
        })
        .filter(|e| e.i != e.j)
        .collect();
    edges.sort_unstable();
    let (first, rest) = edges.split_at(edges.len() / 3);
    let min_size = 12;
    let criterion = || {
        let mut f = Forest::singletons(n as usize);
        f.criterion_pass(first, 0.3);
        f
    };
    let roots = criterion().roots();
    let between: Vec<Edge> = rest
        .iter()
        .filter(|e| roots[e.i as usize] != roots[e.j as usize])
        .copied()
        .collect();
    let every = (|_: &Edge| true, |_: &Edge| true);
    let firsts = super::passes::first_per_pair(&between, |x| roots[x as usize], every);
    assert!(
        firsts.len() * 2 < between.len(),
        "{} of {}",
        firsts.len(),
        between.len()
    );
    let mut over_all = criterion();
    over_all.min_size_pass(&between, min_size, |_| true);
    let mut over_firsts = criterion();
    over_firsts.min_size_pass(&firsts, min_size, |_| true);
    let ids = |f: &Forest| canonical_ids(&f.roots()).0;
    assert_eq!(ids(&over_firsts), ids(&over_all));
    assert_ne!(
        ids(&over_all),
        ids(&criterion()),
        "the pass joins components"
    );
}

#[test]
fn the_first_edge_per_pair_is_the_first_that_passes_both_tests_across_chunks() {
    // 2.5 chunks of the pick's edges between 4,000 elements in 150 components;
    // a cheap candidate test and a veto. The pick asks the veto less often than there are
    // candidates and keeps what filtering by both tests, then keeping the first per pair, keeps.
    let mut next = xorshift(0x2545_f491_4f6c_dd1d);
    let roots: Vec<u32> = (0..4_000).map(|_| (next() % 150) as u32).collect();
    let edges: Vec<Edge> = (0..(5 * super::passes::PICK_CHUNK / 2) as u32)
        .map(|k| {
            let (a, b) = ((next() % 4_000) as u32, (next() % 4_000) as u32);
            Edge {
                w: k,
                i: a.min(b),
                j: a.max(b),
            }
        })
        .collect();
    let root = |x: u32| roots[x as usize];
    let candidate = |e: &Edge| root(e.i) != root(e.j) && (e.i + e.j) % 3 != 0;
    let vetoed = |e: &Edge| (e.i.wrapping_mul(2_654_435_761) ^ e.j) % 4 == 0;
    let asked = std::sync::atomic::AtomicUsize::new(0);
    let absorbs = |e: &Edge| {
        asked.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        !vetoed(e)
    };
    let got = super::passes::first_per_pair(&edges, root, (candidate, absorbs));
    let mut seen = std::collections::HashSet::new();
    let want: Vec<Edge> = edges
        .iter()
        .filter(|e| candidate(e) && !vetoed(e))
        .filter(|e| seen.insert((root(e.i).min(root(e.j)), root(e.i).max(root(e.j)))))
        .copied()
        .collect();
    assert!(got == want, "{} kept, {} expected", got.len(), want.len());
    let candidates = edges.iter().filter(|e| candidate(e)).count();
    let asked = asked.into_inner();
    assert!(
        asked * 2 < candidates,
        "veto asked {asked} times for {candidates} candidates"
    );
}
