//! SAM automatic mask generation against segment_anything 1.0's own output
//! (`shared/fixtures/sam-amg/reference.json`, color-sam ONNX models, two snowmiku images), and an
//! end-to-end run of the real SAM architecture (`sam-tiny-random-*`).
//!
//! These tests need ONNX Runtime: `. scripts/setup.sh` exports `ORT_DYLIB_PATH` (the path
//! printed by `shared/tools/install-onnxruntime.sh`); without it they fail (SLAG_SKIP_ORT=1 skips).

#![allow(clippy::unwrap_used)]

use std::path::Path;
use std::time::Instant;

use serde::Deserialize;
use serde_json::Value;
use slag_common::Error;
use slag_common::onnx::ExecutionProvider;
use slag_encoder::masks::sam::{MaskPostprocess, SamAutomaticMaskGenerator, SamParams};
use slag_encoder::masks::{Mask, MaskGenerator};
use slag_encoder::preprocess::sam_pixel_values;

mod support;
use support::{ort_fixtures, rle_to_pixels, shared, test_fixture};

/// The generator of `dir/{model}-encoder.onnx` and `dir/{model}-decoder.onnx` on the CPU.
fn cpu_generator(dir: &Path, model: &str, params: SamParams) -> SamAutomaticMaskGenerator {
    let (encoder, decoder) = (
        format!("{model}-encoder.onnx"),
        format!("{model}-decoder.onnx"),
    );
    let cpu = ExecutionProvider::Cpu;
    SamAutomaticMaskGenerator::new(&dir.join(encoder), &dir.join(decoder), cpu, 0, params).unwrap()
}

fn iou(a: &[u8], b: &[u8]) -> f64 {
    let (mut i, mut u) = (0u64, 0u64);
    for (&x, &y) in a.iter().zip(b) {
        i += u64::from(x & y);
        u += u64::from(x | y);
    }
    i as f64 / u.max(1) as f64
}

fn load_rgb(path: &Path) -> image::RgbImage {
    slag_encoder::preprocess::load_rgb(path).unwrap()
}

/// Pixel-derived consistency of one generated mask.
fn assert_mask_valid(m: &Mask, w: u32, h: u32) {
    assert_eq!((m.width, m.height), (w, h));
    assert_eq!(m.pixels.len(), (w * h) as usize);
    let from = Mask::from_pixels(w, h, m.pixels.clone()).expect("SAM masks are never empty");
    assert_eq!(from.bbox_xywh, m.bbox_xywh, "bbox must match the pixels");
    assert_eq!(from.area, m.area, "area must match the pixels");
    assert!(m.predicted_iou.is_finite() && m.stability_score.is_finite());
}

#[test]
fn sam_amg_reproduces_segment_anything_reference() {
    let Some(dir) = ort_fixtures("sam-amg") else {
        return;
    };
    let reference: Value =
        serde_json::from_slice(&std::fs::read(dir.join("reference.json")).unwrap()).unwrap();
    let p = &reference["params"];
    let params = SamParams::default();
    assert_eq!(
        p["points_per_side"].as_u64(),
        Some(u64::from(params.points_per_side))
    );
    // The reference ran segment_anything's CPU default, slag's default on the CPU.
    assert_eq!(params.points_per_batch, None);
    assert_eq!(
        p["points_per_batch"].as_u64(),
        Some(slag_encoder::masks::sam::CPU_POINTS_PER_BATCH as u64)
    );
    for (key, v) in [
        ("pred_iou_thresh", params.pred_iou_thresh),
        ("stability_score_thresh", params.stability_score_thresh),
        ("stability_score_offset", params.stability_score_offset),
        ("box_nms_thresh", params.box_nms_thresh),
    ] {
        assert!(
            (p[key].as_f64().unwrap() - f64::from(v)).abs() < 1e-6,
            "default {key}"
        );
    }
    let mut sam = cpu_generator(&dir, "color-sam", params);
    assert_eq!(sam.name(), "sam");
    for r in reference["images"].as_array().unwrap() {
        let name = r["image"].as_str().unwrap();
        let img = load_rgb(&shared().join("scenes/snowmiku/images").join(name));
        assert_eq!(img.width() as u64, r["width"].as_u64().unwrap());
        assert_eq!(img.height() as u64, r["height"].as_u64().unwrap());

        // Encoder input (PIL bilinear ResizeLongestSide + normalisation + padding).
        let (pixels, _) = sam_pixel_values(&img).unwrap();
        let sum: f64 = pixels.iter().map(|&v| f64::from(v)).sum();
        let want = r["encoder_input_sum"].as_f64().unwrap();
        eprintln!("{name}: encoder input sum {sum:.4} (reference {want:.4})");
        assert!(
            (sum - want).abs() < 1e-3,
            "{name}: encoder input sum {sum} vs {want}"
        );

        let t = Instant::now();
        let masks = sam.generate(&img).unwrap();
        eprintln!(
            "{name}: {} masks (reference {}), color-sam AMG {:.2} s",
            masks.len(),
            r["masks"].as_array().unwrap().len(),
            t.elapsed().as_secs_f64()
        );
        let refs = r["masks"].as_array().unwrap();
        assert!(
            (masks.len() as i64 - refs.len() as i64).abs() <= 2,
            "{name}: {} masks vs {} in the reference",
            masks.len(),
            refs.len()
        );
        for m in &masks {
            assert_mask_valid(m, img.width(), img.height());
        }
        // Output order: descending predicted IoU (NMS order), as SAM's.
        assert!(
            masks
                .windows(2)
                .all(|w| w[0].predicted_iou >= w[1].predicted_iou)
        );

        for (k, rm) in refs.iter().enumerate() {
            let (_, _, rpx) = rle_to_pixels(&rm["rle"]);
            let rb = Vec::<i64>::deserialize(&rm["bbox_xywh"]).unwrap();
            // Candidates: boxes within 2 px in every coordinate, best IoU among them.
            let best = masks
                .iter()
                .filter(|m| {
                    m.bbox_xywh
                        .iter()
                        .zip(&rb)
                        .all(|(&a, &b)| (i64::from(a) - b).abs() <= 2)
                })
                .map(|m| (iou(&m.pixels, &rpx), m))
                .max_by(|a, b| a.0.total_cmp(&b.0));
            let Some((best_iou, m)) = best else {
                panic!("{name}: reference mask {k} (bbox {rb:?}) has no mask with a similar box");
            };
            assert!(
                best_iou >= 0.98,
                "{name}: reference mask {k}: best IoU {best_iou}"
            );
            for (a, b) in m.bbox_xywh.iter().zip(&rb) {
                assert!(
                    (i64::from(*a) - b).abs() <= 1,
                    "{name} mask {k}: bbox {:?} vs {rb:?}",
                    m.bbox_xywh
                );
            }
            let (pi, ss) = (
                rm["predicted_iou"].as_f64().unwrap(),
                rm["stability_score"].as_f64().unwrap(),
            );
            assert!(
                (f64::from(m.predicted_iou) - pi).abs() <= 1e-3,
                "{name} mask {k}: iou {} vs {pi}",
                m.predicted_iou
            );
            assert!(
                (f64::from(m.stability_score) - ss).abs() <= 1e-3,
                "{name} mask {k}: stability {} vs {ss}",
                m.stability_score
            );
            let rp = &rm["point_coords"][0];
            let point = m.point.unwrap();
            assert!((f64::from(point[0]) - rp[0].as_f64().unwrap()).abs() < 1e-3);
            assert!((f64::from(point[1]) - rp[1].as_f64().unwrap()).abs() < 1e-3);
        }
    }
}

#[test]
fn sam_tiny_random_runs_end_to_end() {
    let Some(dir) = ort_fixtures("sam-amg") else {
        return;
    };
    let img = load_rgb(&shared().join("scenes/snowmiku/images/20240212_003919.jpg"));
    // Thresholds at 0 keep every non-empty candidate, so the real decoder's full output path
    // (all three channels, several batches, NMS) is exercised. A 4x4 grid in batches of 6 (the
    // last one partial) keeps the CPU run short; the full 16x16 timing is in the report.
    let params = SamParams {
        points_per_side: 4,
        points_per_batch: Some(6),
        pred_iou_thresh: 0.0,
        stability_score_thresh: 0.0,
        ..SamParams::default()
    };
    let mut sam = cpu_generator(&dir, "sam-tiny-random", params);
    let t = Instant::now();
    let masks = sam.generate(&img).unwrap();
    eprintln!(
        "sam-tiny-random AMG: {} masks in {:.2} s",
        masks.len(),
        t.elapsed().as_secs_f64()
    );
    for m in &masks {
        assert_mask_valid(m, img.width(), img.height());
    }
}

#[test]
fn sam_rejects_models_of_the_wrong_role() {
    let Some(sam_dir) = ort_fixtures("sam-amg") else {
        return;
    };
    let clip = shared().join("fixtures/clip/tiny-clip-visual.onnx");
    // The error of a generator from (encoder, decoder), which must fail.
    let refused = |encoder: &Path, decoder: &str, why: &str| {
        let decoder = sam_dir.join(decoder);
        let cpu = ExecutionProvider::Cpu;
        let sam = SamAutomaticMaskGenerator::new(encoder, &decoder, cpu, 0, SamParams::default());
        sam.err().unwrap_or_else(|| panic!("{why}"))
    };
    let err = refused(
        &clip,
        "color-sam-decoder.onnx",
        "a CLIP model is not a SAM encoder",
    );
    let Error::Model { path, message } = &err else {
        panic!("expected Error::Model, got {err}")
    };
    assert_eq!(path, &clip);
    assert!(
        message.contains("expected inputs [pixel_values: f32[1,3,1024,1024]]"),
        "{message}"
    );
    assert!(
        message.contains("found inputs [pixel_values: f32[?,3,224,224]]"),
        "{message}"
    );
    // Encoder passed as decoder.
    let encoder = sam_dir.join("color-sam-encoder.onnx");
    let err = refused(
        &encoder,
        "color-sam-encoder.onnx",
        "an encoder is not a decoder",
    );
    assert!(
        matches!(&err, Error::Model { message, .. } if message.contains("SAM mask decoder")),
        "{err}"
    );
    // Missing file.
    let err = refused(
        &sam_dir.join("nope.onnx"),
        "color-sam-decoder.onnx",
        "missing model",
    );
    assert!(matches!(err, Error::Io { .. }), "{err}");
}

/// The default low-resolution path (decoder asked for `iou_predictions` + `low_res_masks`, logits
/// upsampled on the host for the candidates that pass the IoU filter) gives the masks of the
/// graph's own full-resolution `masks` output: same count and order, IoU ≥ 0.99, boxes within
/// 1 px, stability within 1e-3, on color-sam with every filter at 0 (every candidate kept).
#[test]
fn low_res_postprocess_matches_the_graphs_full_resolution_masks() {
    let Some(dir) = ort_fixtures("sam-amg") else {
        return;
    };
    let img = load_rgb(&shared().join("scenes/snowmiku/images/20240212_004040.jpg"));
    let run = |postprocess| {
        let params = SamParams {
            points_per_side: 6,
            points_per_batch: Some(16),
            pred_iou_thresh: 0.0,
            stability_score_thresh: 0.0,
            postprocess,
            ..SamParams::default()
        };
        let mut sam = cpu_generator(&dir, "color-sam", params);
        sam.generate(&img).unwrap(); // warm-up
        let t = Instant::now();
        let m = sam.generate(&img).unwrap();
        (m, t.elapsed().as_secs_f64())
    };
    let (graph, t_graph) = run(MaskPostprocess::Graph);
    let (low, t_low) = run(MaskPostprocess::LowRes);
    eprintln!(
        "color-sam 6x6: graph masks {} in {t_graph:.2} s, low-res path {} in {t_low:.2} s",
        graph.len(),
        low.len()
    );
    assert!(graph.len() > 5, "too few masks to compare: {}", graph.len());
    assert_eq!(graph.len(), low.len());
    for (k, (a, b)) in graph.iter().zip(&low).enumerate() {
        assert_mask_valid(b, img.width(), img.height());
        let iou = iou(&a.pixels, &b.pixels);
        assert!(iou >= 0.99, "mask {k}: IoU {iou}");
        for (x, y) in a.bbox_xywh.iter().zip(&b.bbox_xywh) {
            assert!(
                x.abs_diff(*y) <= 1,
                "mask {k}: {:?} vs {:?}",
                a.bbox_xywh,
                b.bbox_xywh
            );
        }
        assert_eq!(a.predicted_iou, b.predicted_iou, "mask {k}");
        assert!(
            (a.stability_score - b.stability_score).abs() <= 1e-3,
            "mask {k}"
        );
    }
}

/// A decoder cut down to `iou_predictions` and `low_res_masks` by
/// `scripts/sam-decoder-low-res.py` (`tests/fixtures/color-sam-decoder-low-res.onnx`, from
/// shared's color-sam decoder) gives the same masks as the full decoder, bit for bit, and
/// refuses the graph's own post-processing, which reads the output it no longer has.
#[test]
fn low_res_decoder_gives_the_full_decoders_masks() {
    let Some(dir) = ort_fixtures("sam-amg") else {
        return;
    };
    let low_res_decoder = test_fixture("color-sam-decoder-low-res.onnx");
    let img = load_rgb(&shared().join("scenes/snowmiku/images/20240212_003919.jpg"));
    let params = SamParams {
        points_per_side: 8,
        ..SamParams::default()
    };
    let encoder = dir.join("color-sam-encoder.onnx");
    let cpu = ExecutionProvider::Cpu;
    let mut full = cpu_generator(&dir, "color-sam", params.clone());
    let mut low =
        SamAutomaticMaskGenerator::new(&encoder, &low_res_decoder, cpu, 0, params.clone()).unwrap();
    let (a, b) = (full.generate(&img).unwrap(), low.generate(&img).unwrap());
    assert!(a.len() > 5, "too few masks to compare: {}", a.len());
    assert_eq!(a, b);

    let graph = SamParams {
        postprocess: MaskPostprocess::Graph,
        ..params
    };
    let err = SamAutomaticMaskGenerator::new(&encoder, &low_res_decoder, cpu, 0, graph)
        .err()
        .expect("the graph post-processing needs the full decoder");
    assert!(
        matches!(&err, Error::Param { name: "postprocess", expected, .. } if expected.contains("full decoder")),
        "{err}"
    );
}

/// Four generators sharing one generator's sessions ([`SamAutomaticMaskGenerator::share`], as
/// the front workers of a GPU do) on four threads give every image the masks it gets alone: a
/// decoder call's outputs stay intact while other threads run the session.
#[test]
fn shared_sessions_give_every_image_its_own_masks() {
    let Some(dir) = ort_fixtures("sam-amg") else {
        return;
    };
    let names = ["20240212_003919.jpg", "20240212_004040.jpg"];
    let images: Vec<_> = names
        .iter()
        .map(|n| load_rgb(&shared().join("scenes/snowmiku/images").join(n)))
        .collect();
    let params = SamParams {
        points_per_side: 6,
        points_per_batch: Some(9),
        ..SamParams::default()
    };
    let mut one = cpu_generator(&dir, "color-sam", params.clone());
    let expected: Vec<_> = images.iter().map(|i| one.generate(i).unwrap()).collect();
    assert!(
        expected.iter().all(|m| m.len() > 3),
        "too few masks to compare"
    );
    assert_ne!(expected[0], expected[1], "the images must differ");
    let shared_sam = cpu_generator(&dir, "color-sam", params);
    std::thread::scope(|s| {
        let runs: Vec<_> = (0..4)
            .map(|t| {
                let mut sam = shared_sam.share();
                let (images, expected) = (&images, &expected);
                s.spawn(move || {
                    for round in 0..3 {
                        let k = (t + round) % images.len();
                        assert_eq!(sam.generate(&images[k]).unwrap(), expected[k], "image {k}");
                    }
                })
            })
            .collect();
        for r in runs {
            r.join().unwrap();
        }
    });
}
