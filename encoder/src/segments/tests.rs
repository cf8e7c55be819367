#![allow(clippy::unwrap_used)]

use std::sync::atomic::AtomicBool;

use rstar::RTree;
use rstar::primitives::GeomWithData;

use super::forest::Forest;
use super::graph::tile_edges;
use super::regions::{PROFILE_CAP, merge_profiles, region_disagreement};
use super::weights::Edge;
use super::*;

/// A scene of flat Gaussians on planes: the floor z = 0 over `[0, 4]²`, a wall x = 0 over
/// `y, z ∈ [0, 2]`, and a box (its top face at z = 1 over `[2.5, 3.5]²`) floating apart,
/// on a grid of spacing 0.1 with a little deterministic jitter. Returns the Gaussians and
/// each one's surface (0 floor, 1 wall, 2 box top).
fn planes() -> (Gaussians, Vec<u8>) {
    let mut g = Gaussians::default();
    let mut label = Vec::new();
    let mut s = 7u64;
    let mut jitter = || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((s >> 40) as f32 / (1u64 << 24) as f32 - 0.5) * 0.01
    };
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
    let p = SegmentParams {
        tile_gaussians: 500,
        ..params()
    };
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let a = one.install(|| segment(&g, &p, "x", None).unwrap().0);
    let b = segment(&g, &p, "x", None).unwrap().0;
    assert_eq!(a, b);
}

/// The tiled result equals the same two passes over the whole graph with the edges in
/// tile-grouped order (every tile's inner edges, then the border edges): the statement of
/// the module doc, and one tile equals the untiled algorithm.
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
    let geo = geometry(&g);
    let h = resolve_max_edge(&p, &geo);
    let (ax1, one, r1) = plan_tiles(&g.means, usize::MAX);
    let go = AtomicBool::new(false);
    let (all, none) = tile_edges(0, &g.means, &one, ax1, r1[0], &geo, &p, h, &go);
    assert!(none.is_empty());
    let (_, tile_of, rects) = plan_tiles(&g.means, p.tile_gaussians);
    let mut order: Vec<Edge> = Vec::new();
    for t in 0..rects.len() as u32 {
        order.extend(
            all.iter()
                .filter(|e| tile_of[e.i as usize] == t && tile_of[e.j as usize] == t),
        );
    }
    order.extend(
        all.iter()
            .filter(|e| tile_of[e.i as usize] != tile_of[e.j as usize]),
    );
    assert_eq!(order.len() as u64, stats.edges);
    let mut f = Forest::singletons(g.len());
    f.criterion_pass(&order, p.threshold);
    f.min_size_pass(&order, p.min_size, |_| true);
    let roots: Vec<u32> = (0..g.len() as u32).map(|i| f.find(i)).collect();
    assert_eq!(canonical_ids(&roots).0, tiled.segments);
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
    let p = SegmentParams {
        tile_gaussians: 500,
        ..params()
    };
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

/// Two boxes of different classes touching each other and standing on the ground: the
/// ground z = 0 over `[0, 4]²`, box A over `[1, 2] × [1, 2]`, height 0.6, box B over
/// `[2, 3] × [1, 2]`, height 0.4 (A's wall x = 2 is B's; their front and back walls are
/// coplanar), shells of discs tilted at random by up to ±30° (a trained 3DGS's normals
/// are rough) at spacing 0.1 on each box's top and four sides. Returns
/// the Gaussians and their instance (0 ground, 1 A, 2 B).
fn touching_boxes() -> (Gaussians, Vec<u32>) {
    let mut g = Gaussians::default();
    let mut inst = Vec::new();
    let z_up = [1.0, 0.0, 0.0, 0.0];
    let h = 0.5f32.sqrt();
    let x_normal = [h, 0.0, h, 0.0];
    let y_normal = [h, h, 0.0, 0.0];
    let mut push = |m: [f32; 3], q: [f32; 4], l: u32| {
        // Tilted by up to ±30° about a varying axis, as a trained 3DGS's splats lie.
        let i = g.means.len() as u64;
        let u = |k: u64| ((i * 2_654_435_761 + k * 40_503) % 1000) as f32 / 1000.0 - 0.5;
        let (t, a) = (u(1) * 1.05, [u(2), u(3), u(4)]);
        let an = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt().max(1e-6);
        let (c, sn) = ((t / 2.0).cos(), (t / 2.0).sin() / an);
        let r = [c, sn * a[0], sn * a[1], sn * a[2]];
        let q = [
            r[0] * q[0] - r[1] * q[1] - r[2] * q[2] - r[3] * q[3],
            r[0] * q[1] + r[1] * q[0] + r[2] * q[3] - r[3] * q[2],
            r[0] * q[2] - r[1] * q[3] + r[2] * q[0] + r[3] * q[1],
            r[0] * q[3] + r[1] * q[2] - r[2] * q[1] + r[3] * q[0],
        ];
        g.means.push(m);
        g.scales.push([0.05, 0.05, 0.01]);
        g.rotations.push(q);
        g.opacities.push(0.9);
        inst.push(l);
    };
    let boxes = [
        ([1.0f32, 1.0], [2.0f32, 2.0], 0.6f32),
        ([2.0, 1.0], [3.0, 2.0], 0.4),
    ];
    for a in 0..40 {
        for b in 0..40 {
            let (x, y) = (a as f32 * 0.1 + 0.05, b as f32 * 0.1 + 0.05);
            if !boxes
                .iter()
                .any(|(lo, hi, _)| x > lo[0] && x < hi[0] && y > lo[1] && y < hi[1])
            {
                push([x, y, 0.0], z_up, 0);
            }
        }
    }
    for (k, (lo, hi, top)) in boxes.iter().enumerate() {
        let l = k as u32 + 1;
        let steps = |a: f32, b: f32| {
            let n = ((b - a) / 0.1).round() as usize;
            (0..n).map(move |i| a + 0.05 + i as f32 * 0.1)
        };
        for x in steps(lo[0], hi[0]) {
            for y in steps(lo[1], hi[1]) {
                push([x, y, *top], z_up, l);
            }
            for z in steps(0.0, *top) {
                push([x, lo[1], z], y_normal, l);
                push([x, hi[1], z], y_normal, l);
            }
        }
        for y in steps(lo[1], hi[1]) {
            for z in steps(0.0, *top) {
                // The shared wall belongs to the taller box A only.
                if k == 0 || (lo[0] - 2.0).abs() > 1e-6 {
                    push([lo[0], y, z], x_normal, l);
                }
                push([hi[0], y, z], x_normal, l);
            }
        }
    }
    (g, inst)
}

/// A masks' record as SAM-like masks would give it: 6 views; in each, every Gaussian's
/// dominant mask is its instance, except that the ground is cut into two masks along a line
/// that moves from view to view (SAM's over-segmentation of a large surface), and that a
/// Gaussian within 0.1 of another instance takes that instance's mask in one view of three
/// (masks bleeding over a border).
fn record_of(g: &Gaussians, inst: &[u32]) -> MaskRecord {
    record_bleeding(g, inst, 3, 0.011)
}

/// [`record_of`] with the bleeding as a parameter: a Gaussian within `sqrt(r2)` of another
/// instance takes its mask in one view of `every`.
fn record_bleeding(g: &Gaussians, inst: &[u32], every: usize, r2: f32) -> MaskRecord {
    let n = g.len();
    let mut r = MaskRecord::new(n, 4, 6).unwrap();
    let tree: RTree<GeomWithData<[f32; 3], u32>> = RTree::bulk_load(
        (0..n as u32)
            .map(|i| GeomWithData::new(g.means[i as usize], i))
            .collect(),
    );
    for v in 0..6usize {
        let cut = 0.7 + 0.45 * v as f32;
        let entries = (0..n as u32).map(|i| {
            let m = g.means[i as usize];
            let mut l = inst[i as usize];
            if v % every == (i as usize) % every {
                let near = tree
                    .locate_within_distance(m, r2)
                    .find(|o| inst[o.data as usize] != l);
                if let Some(o) = near {
                    l = inst[o.data as usize];
                }
            }
            let mask = if l == 0 {
                u32::from(m[0] > cut) + 10
            } else {
                l
            };
            (i, mask, 1.0 + (i as usize * 7 + v) as f32 % 5.0)
        });
        r.add_view(v, entries);
    }
    r
}

#[test]
fn touching_objects_of_different_classes_come_apart_with_masks() {
    use crate::eval::segment_quality::{boundary_recall, purity};
    let (g, inst) = touching_boxes();
    let labels: Vec<Option<u32>> = inst.iter().map(|&l| Some(l)).collect();
    let p = params();
    let measure = |s: &Segments| {
        let pu = purity(&labels, &s.segments).unwrap().purity;
        let br = boundary_recall(&g.means, &labels, &s.segments, 8, 0.2).unwrap();
        (pu, br.recall)
    };
    let (geometric, _) = segment(&g, &p, "boxes", None).unwrap();
    let (geo_purity, geo_recall) = measure(&geometric);
    let record = Arc::new(record_of(&g, &inst));
    let (masked, stats) = segment(&g, &p, "boxes", Some(Arc::clone(&record))).unwrap();
    let (purity, recall) = measure(&masked);
    assert_eq!(stats.mask_record, Some(4));
    // Geometry alone joins the coplanar front and back walls of the two boxes (B's walls
    // end in A's segment); the masks keep them apart.
    assert!(
        geo_purity < 0.97,
        "geometry alone: purity {geo_purity}, boundary recall {geo_recall}"
    );
    assert!(
        purity >= 0.99 && recall >= 0.95 && purity > geo_purity,
        "with masks: purity {purity}, boundary recall {recall} ({} segments; geometry \
         alone {geo_purity}, {geo_recall})",
        masked.segment_count
    );
    // The ground is not shredded by its two moving masks, nor a box by the bleeding.
    assert!(
        masked.segment_count <= 16,
        "{} segments",
        masked.segment_count
    );
    // Tiles and thread counts do not change the result.
    let tiled = SegmentParams {
        tile_gaussians: 500,
        ..p
    };
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let a = one.install(|| {
        segment(&g, &tiled, "x", Some(Arc::clone(&record)))
            .unwrap()
            .0
    });
    let b = segment(&g, &tiled, "x", Some(Arc::clone(&record)))
        .unwrap()
        .0;
    assert_eq!(a, b);
    // A record of another scene is refused.
    let other = Arc::new(MaskRecord::new(3, 4, 6).unwrap());
    assert!(matches!(
        segment(&g, &p, "x", Some(other)),
        Err(Error::Mismatch { .. })
    ));
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

/// The region veto on its own: with the edges weighed by geometry alone (mask weight 0,
/// no pairwise veto), the coplanar walls of the two touching boxes join; with the region
/// veto, segments whose Gaussians' recorded masks disagree stay apart. Off (1), it changes
/// nothing.
#[test]
fn the_region_veto_keeps_regions_of_different_masks_apart() {
    use crate::eval::segment_quality::purity;
    let (g, inst) = touching_boxes();
    let labels: Vec<Option<u32>> = inst.iter().map(|&l| Some(l)).collect();
    let record = Arc::new(record_bleeding(&g, &inst, 3, 0.0));
    let run = |region_veto: f32, tiles: usize| {
        let p = SegmentParams {
            region_veto,
            mask_weight: 0.0,
            mask_veto: 1.0,
            tile_gaussians: tiles,
            ..params()
        };
        let (s, _) = segment(&g, &p, "boxes", Some(Arc::clone(&record))).unwrap();
        (purity(&labels, &s.segments).unwrap().purity, s)
    };
    let (off, o) = run(1.0, usize::MAX);
    let (geometric, _) = segment(&g, &params(), "boxes", None).unwrap();
    assert_eq!(
        o.segments, geometric.segments,
        "region veto 1 is geometry alone here"
    );
    let (on, r) = run(0.5, usize::MAX);
    assert!(off < 0.97, "geometry alone: purity {off}");
    assert!(
        on >= 0.99 && r.segment_count <= 40,
        "region veto: purity {on} ({} segments); off {off} ({})",
        r.segment_count,
        o.segment_count
    );
    // Deterministic over thread counts with tiles.
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let a = one.install(|| run(0.5, 500).1);
    assert_eq!(a, run(0.5, 500).1);
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
