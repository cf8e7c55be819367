//! Tests of the generator's parts against segment_anything's definitions: the prompt grid, box
//! NMS order, decoder batch sizes, parameter checks, and the block-decided upsampling against
//! the full one, bit for bit.

#![allow(clippy::unwrap_used)]

use super::*;

#[test]
fn point_grid_matches_segment_anything() {
    let g = build_point_grid(16);
    assert_eq!(g.len(), 256);
    assert_eq!(g[0], [1.0 / 32.0, 1.0 / 32.0]);
    assert_eq!(g[1][1], 1.0 / 32.0);
    assert!((g[1][0] - 3.0 / 32.0).abs() < 1e-15);
    assert_eq!(g[255], [31.0 / 32.0, 31.0 / 32.0]);
    // The reference's first mask came from grid point (31/32 * 990, ...).
    assert_eq!(g[15][0] * 990.0, 959.0625);
}

fn cand(bbox: [u32; 4], iou: f32) -> Candidate {
    Candidate {
        bits: vec![],
        bbox,
        area: 1,
        iou,
        stability: 1.0,
        point: [0.0; 2],
        channel: 1,
    }
}

#[test]
fn nms_suppresses_overlaps_above_threshold_in_score_order() {
    let c = vec![
        cand([0, 0, 10, 10], 0.8),
        cand([0, 0, 10, 11], 0.9), // IoU 100/110 with the first: suppresses it
        cand([20, 20, 30, 30], 0.85),
        cand([0, 0, 10, 15], 0.95), // IoU with #1 = 110/150 = 0.733 > 0.7
    ];
    // #0 overlaps #3 at 100/150 = 0.667: kept at 0.7.
    assert_eq!(nms(&c, 0.7), vec![3, 2, 0]);
    // At 0.75 the 0.733 overlap survives, then #0 is suppressed by #1 (0.909).
    assert_eq!(nms(&c, 0.75), vec![3, 1, 2]);
}

#[test]
fn decoder_batches_shrink_to_their_memory_budget() {
    let p = SamParams::default();
    assert_eq!(
        p.batch_for(742, 990, false),
        CPU_POINTS_PER_BATCH,
        "CPU: 64 by default"
    );
    assert_eq!(p.batch_for(742, 990, true), GPU_POINTS_PER_BATCH);
    let small = SamParams {
        points_per_side: 8,
        ..SamParams::default()
    };
    assert_eq!(
        small.batch_for(742, 990, true),
        64,
        "never more than the grid"
    );
    let asked = SamParams {
        points_per_batch: Some(100),
        ..SamParams::default()
    };
    assert_eq!(
        asked.batch_for(742, 990, true),
        100,
        "asked for: on any provider"
    );
    assert_eq!(asked.batch_for(742, 990, false), 100);
    let per = decoder_bytes_per_prompt(742, 990);
    assert_eq!(per, 32 * (742 * 990 + 1024 * 1024));
    let capped = |bytes| {
        SamParams {
            decoder_batch_bytes: Some(bytes),
            ..SamParams::default()
        }
        .batch_for(742, 990, false)
    };
    assert_eq!(capped(10 * per + 1), 10);
    assert_eq!(capped(0), 1, "at least one prompt");
    assert_eq!(capped(1000 * per), 64, "never above the batch asked for");
}

#[test]
fn params_are_validated() {
    assert!(SamParams::default().validate().is_ok());
    let bad = SamParams {
        points_per_batch: Some(0),
        ..SamParams::default()
    };
    assert!(matches!(
        bad.validate(),
        Err(Error::Param {
            name: "points_per_batch",
            ..
        })
    ));
    let bad = SamParams {
        pred_iou_thresh: f32::NAN,
        ..SamParams::default()
    };
    assert!(matches!(
        bad.validate(),
        Err(Error::Param {
            name: "pred_iou_thresh",
            ..
        })
    ));
}

/// Deterministic uniform floats in [0, 1) (splitmix64).
fn uniform(seed: u64) -> impl FnMut() -> f32 {
    let mut state = seed;
    move || {
        state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// A 256 × 256 logit map: blobs (smooth, SAM-like, ±20) or a sharp-edged step map with
/// plateaus (color-sam-like), from `seed`.
fn logit_map(seed: u64, sharp: bool) -> Vec<f32> {
    let mut u = uniform(seed);
    let blobs: Vec<[f32; 4]> = (0..6)
        .map(|_| [u() * 256.0, u() * 256.0, 8.0 + u() * 60.0, u() * 2.0 - 0.7])
        .collect();
    (0..256 * 256)
        .map(|k| {
            let (x, y) = ((k % 256) as f32, (k / 256) as f32);
            let v: f32 = blobs
                .iter()
                .map(|b| b[3] * (-((x - b[0]).powi(2) + (y - b[1]).powi(2)) / (b[2] * b[2])).exp())
                .sum();
            if sharp {
                if v > 0.1 { 12.0 } else { -12.0 }
            } else {
                40.0 * v - 1.0
            }
        })
        .collect()
}

fn assert_same(a: Option<Candidate>, b: Option<Candidate>, what: &str) {
    match (a, b) {
        (None, None) => {}
        (Some(a), Some(b)) => {
            assert_eq!(a.bbox, b.bbox, "{what}: box");
            assert_eq!(a.area, b.area, "{what}: area");
            assert_eq!(
                a.stability.to_bits(),
                b.stability.to_bits(),
                "{what}: stability"
            );
            assert!(a.bits == b.bits, "{what}: pixels");
            assert_eq!(
                (a.iou, a.channel, a.point),
                (b.iou, b.channel, b.point),
                "{what}"
            );
        }
        (a, b) => panic!("{what}: kept {} vs {}", a.is_some(), b.is_some()),
    }
}

#[test]
fn block_decided_candidates_equal_the_full_upsampling() {
    let params = |thr: f32, off: f32, stab: f32| SamParams {
        mask_threshold: thr,
        stability_score_offset: off,
        stability_score_thresh: stab,
        ..SamParams::default()
    };
    let mut maps: Vec<(String, Vec<f32>)> = (0..6)
        .map(|s| (format!("map {s}"), logit_map(s, s % 3 == 2)))
        .collect();
    for v in [0.0f32, 1.0, -1.0, 1e-6, 1.0 - 1e-6, 5.0] {
        maps.push((format!("constant {v}"), vec![v; 256 * 256]));
    }
    let mut ramp = logit_map(9, false);
    ramp[1234] = f32::NAN;
    maps.push(("NaN logit".into(), ramp));
    let mut inf = logit_map(10, true);
    inf[40_000] = f32::INFINITY;
    maps.push(("infinite logit".into(), inf));
    let sizes = [
        (742u32, 990u32),
        (990, 742),
        (1024, 1024),
        (17, 31),
        (1500, 2000),
        (1, 1),
    ];
    for (h, w) in sizes {
        let up = LowResUpsampler::new((h, w), sam_preprocess_shape(h, w, SAM_IMAGE_SIZE));
        let (mut rows, mut full) = (vec![0f32; 256 * w as usize], vec![0f32; (h * w) as usize]);
        let mut scratch = up.scratch();
        for p in [
            params(0.0, 1.0, 0.0),
            params(0.0, 1.0, 0.9),
            params(0.3, 0.0, 0.5),
            params(-2.0, 4.0, 0.0),
        ] {
            for (name, low) in &maps {
                up.upsample(low, &mut rows, &mut full);
                let want = candidate(&full, w as usize, &p, 0.9, [1.5, 2.5], 2);
                let got = up.candidate(low, &mut scratch, &p, 0.9, [1.5, 2.5], 2);
                let what = format!(
                    "{name}, {w}x{h}, threshold {} offset {}",
                    p.mask_threshold, p.stability_score_offset
                );
                assert_same(got, want, &what);
            }
        }
    }
}
