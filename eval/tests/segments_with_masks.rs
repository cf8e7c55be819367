//! Geometric segments with the masks' record against known instances: two touching boxes of
//! different classes on the ground, whose coplanar walls geometry alone joins and the recorded
//! masks keep apart, scored by segment purity and boundary recall ([`slag_eval::segment_quality`]).
#![allow(clippy::unwrap_used)]

use std::sync::Arc;

use rstar::RTree;
use rstar::primitives::GeomWithData;
use slag_common::Error;
use slag_common::mask_record::MaskRecord;
use slag_common::scene::Gaussians;
use slag_common::segments::Segments;
use slag_encoder::segments::{SegmentParams, segment};
use slag_eval::segment_quality::{boundary_recall, purity};

/// The segmenter's defaults with edges capped at 0.5 scene units.
fn params() -> SegmentParams {
    SegmentParams {
        max_edge: Some(0.5),
        ..SegmentParams::default()
    }
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

/// The region veto on its own: with the edges weighed by geometry alone (mask weight 0,
/// no pairwise veto), the coplanar walls of the two touching boxes join; with the region
/// veto, segments whose Gaussians' recorded masks disagree stay apart. Off (1), it changes
/// nothing.
#[test]
fn the_region_veto_keeps_regions_of_different_masks_apart() {
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
