//! The 2D held-out protocol (`eval-colors --held-out`) end to end on the embedded scene
//! data/snowmiku-mini (13 views, 60,000 Gaussians, 495×371): encode with the graph segmenter and
//! color-clip at `--every 4` (views 0, 4, 8, 12), then score the held-out views 2, 6 and 10 per
//! pixel against the photos' colour classes, with the majority and pixel-lifting-oracle
//! baselines.
//!
//! Needs ONNX Runtime (color-clip): `. scripts/setup.sh`; SLAG_SKIP_ORT=1 skips.

#[path = "../../encoder/tests/support/mod.rs"]
mod support;

use slag_encoder::aggregate::MaskOverlap;
use slag_encoder::config::{EncodeConfig, MasksConfig};
use slag_encoder::pipeline::Encoder;
use slag_eval::colors::{EvalColorsConfig, run_held_out};
use support::{ort_tempdir, shared};

fn mini() -> std::path::PathBuf {
    std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../data/snowmiku-mini")
}

/// An encode of snowmiku-mini at `every` 4 (every such view encoded), raster 0.5, with
/// color-clip and `masks`, the dense embeddings (what `eval-colors` reads) beside the mixture.
fn mini_config(out: &std::path::Path, masks: MasksConfig) -> EncodeConfig {
    let clip = shared().join("fixtures/clip/color-clip-visual.onnx");
    let mut c = EncodeConfig::new(mini(), clip, out);
    c.masks = masks;
    c.scene.every = 4;
    c.scene.views.mode = slag_encoder::views::SelectionMode::All;
    c.raster.scale = 0.5;
    c.output.progress = false;
    c.output.dense = true;
    c
}

/// Runs `config` (an encode of [`mini_config`]); returns the output folder's embeddings path.
fn encode_mini(config: EncodeConfig) -> std::path::PathBuf {
    let out = config.output.dir.clone();
    let report = Encoder::new(config)
        .expect("encode config")
        .run()
        .expect("encode");
    assert_eq!(report.counts.views_used, 4);
    out.join("embeddings.safetensors")
}

fn eval_args(embeddings: std::path::PathBuf, compare: Vec<std::path::PathBuf>) -> EvalColorsConfig {
    EvalColorsConfig {
        color_clip: Some(slag_common::paths::source_tree_shared_dir().join("fixtures/clip")),
        // every and raster_scale: from the report beside the embeddings
        compare,
        ..EvalColorsConfig::new(mini(), embeddings)
    }
}

/// color-sam masks (16×16 grid, pred-IoU 0.8, stability 0.5) with the encoder's default
/// aggregation (`--overlap finest`) against the paper's mean (`--overlap all`) on the same
/// held-out pixels, scored in one pass (`--compare`): the default must reach its floor and beat
/// the mean clearly.
#[test]
fn default_aggregation_beats_the_mean_on_held_out_views() {
    let Some(dir) = ort_tempdir() else {
        return;
    };
    let fixtures = shared().join("fixtures/sam-amg");
    let mut sam = MasksConfig::sam(
        fixtures.join("color-sam-encoder.onnx"),
        fixtures.join("color-sam-decoder.onnx"),
    );
    sam.sam.points_per_side = 16;
    sam.sam.pred_iou_thresh = 0.8;
    sam.sam.stability_score_thresh = 0.5;
    let default = encode_mini(mini_config(&dir.path().join("default"), sam.clone()));
    let mut mean = mini_config(&dir.path().join("mean"), sam);
    mean.aggregate.overlap = MaskOverlap::All;
    let mean = encode_mini(mean);
    let r = run_held_out(&eval_args(default, vec![mean])).expect("eval-colors --held-out");
    let h = &r.held_out;
    let variant = |name: &str| {
        h.variants
            .iter()
            .find(|v| v.name == name)
            .and_then(|v| v.score.miou)
            .unwrap_or_else(|| panic!("variant {name} scored: {:?}", h.variants))
    };
    let (ours, paper, oracle) = (
        h.slag.miou.expect("default mIoU"),
        variant("compare"),
        h.oracle.miou.expect("oracle mIoU"),
    );
    eprintln!("held-out mini, color-sam: default {ours}, paper mean {paper}, oracle {oracle}");
    for v in &h.variants {
        eprintln!("  variant {}: {:?}", v.name, v.score.miou);
    }
    assert!(
        ours >= SAM_DEFAULT_FLOOR,
        "default aggregation held-out mIoU {ours} below {SAM_DEFAULT_FLOOR}"
    );
    assert!(
        ours >= paper + SAM_MARGIN_OVER_MEAN,
        "default aggregation {ours} does not beat the paper's mean {paper} by \
         {SAM_MARGIN_OVER_MEAN}"
    );
    // The default stored form (the mixture over each Gaussian's 4 strongest masks, written
    // beside the dense rows) holds the same floor and margin: measured 0.290 here.
    let stored = variant("mixture-mean-S4");
    assert!(
        stored >= SAM_DEFAULT_FLOOR && stored >= paper + SAM_MARGIN_OVER_MEAN,
        "default mixture form {stored}: floor {SAM_DEFAULT_FLOOR}, mean {paper}"
    );
}

/// Floors from the values measured on this subset (see the constants): slag must beat the
/// majority class clearly, and the oracle, which lifts the photos' own classes with the same
/// blend weights, must reach at least slag.
#[test]
fn held_out_protocol_on_snowmiku_mini() {
    let Some(dir) = ort_tempdir() else {
        return;
    };
    let out = dir.path().join("out");
    encode_mini(mini_config(&out, MasksConfig::graph()));

    let a = eval_args(out.join("embeddings.safetensors"), Vec::new());
    let r = run_held_out(&a).expect("eval-colors --held-out");
    let h = &r.held_out;
    eprintln!(
        "held-out mini: slag {:?}, oracle {:?}, majority {:?} ({}), counted {} of {} pixels; \
         3D {:?}",
        h.slag.miou,
        h.oracle.miou,
        h.majority.miou,
        h.majority_class,
        h.counted_pixels,
        h.pixels,
        r.colour_3d.miou
    );
    eprintln!("{}", serde_json::to_string(&r).expect("json"));

    // The protocol's bookkeeping.
    assert_eq!(h.every, 4);
    assert_eq!(
        h.held_out_views,
        [
            "20240212_003936.jpg",
            "20240212_004014.jpg",
            "20240212_004107.jpg"
        ]
    );
    assert_eq!(h.encoded_views, 4);
    assert_eq!(h.oracle_raster_scale, 0.5);
    assert_eq!(
        h.pixels,
        3 * 495 * 371,
        "held-out views render at full resolution"
    );
    assert!(
        h.counted_pixels * 2 > h.pixels,
        "only {} of {} pixels have alpha ≥ 0.5: the scene is not being rendered",
        h.counted_pixels,
        h.pixels
    );
    assert!(h.miou_classes.len() >= 3, "{:?}", h.miou_classes);
    for s in [&h.slag, &h.oracle, &h.majority] {
        assert_eq!(s.classes.len(), 12);
        let truth: u64 = s.classes.iter().map(|c| c.truth_pixels).sum();
        let pred: u64 = s.classes.iter().map(|c| c.predicted_pixels).sum();
        assert_eq!(truth, h.counted_pixels);
        assert_eq!(pred, h.counted_pixels);
        for c in &s.classes {
            if let Some(iou) = c.iou {
                assert!((0.0..=1.0).contains(&iou), "{}: IoU {iou}", c.name);
            }
            assert!(c.intersection <= c.truth_pixels.min(c.predicted_pixels));
        }
    }
    let (slag, oracle, majority) = (
        h.slag.miou.expect("slag mIoU"),
        h.oracle.miou.expect("oracle mIoU"),
        h.majority.miou.expect("majority mIoU"),
    );
    // Majority: one class's share / number of averaged classes.
    assert!(majority < 0.2, "majority baseline {majority}");
    assert!(
        slag >= majority + MARGIN_OVER_MAJORITY,
        "slag {slag} does not clearly beat the majority class {majority}"
    );
    assert!(
        slag >= SLAG_FLOOR,
        "slag held-out mIoU {slag} below {SLAG_FLOOR}"
    );
    assert!(oracle >= slag, "oracle {oracle} below slag {slag}");
    // The default stored form (mixture, top 4 masks per Gaussian; measured 0.223 here, as the
    // dense rows) holds the same floor.
    let stored = h
        .variants
        .iter()
        .find(|v| v.name == "mixture-mean-S4")
        .and_then(|v| v.score.miou)
        .expect("the default mixture form is written and scored");
    assert!(
        stored >= SLAG_FLOOR && stored >= majority + MARGIN_OVER_MAJORITY,
        "default mixture form {stored}: floor {SLAG_FLOOR}, majority {majority}"
    );
    assert!(
        oracle >= ORACLE_FLOOR,
        "oracle {oracle} below {ORACLE_FLOOR}"
    );
}

/// Measured on this subset (release build, 2-core CPU, lavapipe; docs/results/accuracy.md): slag 0.223,
/// oracle 0.323, majority class (gray) 0.112; the pipeline is deterministic. slag must stay clearly
/// above the majority class (a broken render, pose or argmax falls to it or below).
const MARGIN_OVER_MAJORITY: f64 = 0.05;
/// ~25 % below the measured 0.223.
const SLAG_FLOOR: f64 = 0.17;
/// ~25 % below the measured 0.323.
const ORACLE_FLOOR: f64 = 0.25;
/// color-sam with the default `--overlap finest` measured 0.290 here (release build, 2-core CPU,
/// lavapipe), the paper's mean 0.275, the oracle 0.323 (docs/results/accuracy.md); ~10 % below 0.290.
const SAM_DEFAULT_FLOOR: f64 = 0.26;
/// Half the measured gain of 0.015 over the mean.
const SAM_MARGIN_OVER_MEAN: f64 = 0.007;

/// Coverage selection among the training views of `--hold-out-every 4` (the 10 views other
/// than 2, 6 and 10): the report records the chosen views and the held-out pass reads the step
/// and the encoded views from it; no held-out view is encoded.
#[test]
fn coverage_selection_trains_on_the_held_out_splits_training_views_only() {
    let Some(dir) = ort_tempdir() else {
        return;
    };
    let out = dir.path().join("out");
    let mut c = mini_config(&out, MasksConfig::graph());
    c.scene.every = 1;
    c.scene.hold_out_every = Some(4);
    c.scene.views.mode = slag_encoder::views::SelectionMode::Coverage;
    c.scene.views.count = Some(5);
    // Every view that adds a pair, so that the count binds.
    c.scene.views.coverage.min_gain = 0.0;
    c.segments.enabled = false;
    let report = Encoder::new(c)
        .expect("encode config")
        .run()
        .expect("encode");
    let s = report.view_selection.expect("view_selection in the report");
    assert_eq!(s.candidates, 10);
    assert_eq!(s.chosen.len(), 5);
    assert_eq!(report.counts.views_used, 5);
    assert!(s.coverage.is_some_and(|c| c.order.len() >= 5));

    let r = run_held_out(&eval_args(out.join("embeddings.safetensors"), Vec::new()))
        .expect("eval-colors --held-out");
    let h = &r.held_out;
    assert_eq!(h.every, 4);
    assert_eq!(h.encoded_views, 5, "the oracle lifts the chosen views");
    assert_eq!(
        h.held_out_views,
        [
            "20240212_003936.jpg",
            "20240212_004014.jpg",
            "20240212_004107.jpg"
        ]
    );
    assert!(s.chosen.iter().all(|v| !h.held_out_views.contains(v)));
}
