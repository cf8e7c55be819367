//! End to end on real input: encode snowmiku (a subset small enough for CI) with color-sam +
//! color-clip and with the graph segmenter, then measure colour mIoU; run the real-architecture
//! SAM/CLIP path. The mIoU floors come from the full runs in docs/results/accuracy.md.

#![allow(clippy::unwrap_used)]

use slag_encoder::config::EncodeConfig;
use slag_eval::colors::EvalColorsConfig;
use slag_tests::{color_sam, encode, fixture, graph_config, random_weights_config, shared};

fn snowmiku() -> std::path::PathBuf {
    shared().join("scenes/snowmiku")
}

fn eval(out: &std::path::Path) -> slag_eval::ColourEval {
    let a = EvalColorsConfig {
        color_clip: Some(shared().join("fixtures/clip")),
        ..EvalColorsConfig::new(snowmiku(), out.join("embeddings.safetensors"))
    };
    slag_eval::colors::run(&a).expect("eval-colors")
}

/// The colour evaluation of the encode in `out` (printed, labelled `masks`) reaches `floor`.
fn assert_miou_floor(out: &std::path::Path, masks: &str, floor: f64) {
    let e = eval(out);
    eprintln!("{masks} subset: {}", serde_json::to_string(&e).unwrap());
    let miou = e.miou.expect("mIoU defined");
    assert!(miou >= floor, "{masks}: mIoU {miou} below floor {floor}");
}

/// The CI subset: every 12th image (9 views), raster scale 0.25.
fn subset(mut c: EncodeConfig) -> EncodeConfig {
    c.scene.every = 12;
    c.raster.scale = 0.25;
    c
}

#[test]
fn color_sam_and_color_clip_reach_the_miou_floor() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let mut config = subset(graph_config(&snowmiku(), &out));
    config.masks = color_sam(16);
    let report = encode(config).expect("encode");
    assert_eq!(report.counts.views_used, 9);
    assert!(report.counts.observed > 0);
    assert!(out.join("report.json").exists());
    assert_miou_floor(&out, "color-sam", MIOU_FLOOR_SAM);
}

#[test]
fn graph_segmenter_and_color_clip_reach_the_miou_floor() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    encode(subset(graph_config(&snowmiku(), &out))).expect("encode");
    assert_miou_floor(&out, "graph", MIOU_FLOOR_GRAPH);
}

#[test]
fn real_architecture_models_run_end_to_end() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let sam = ["encoder", "decoder"].map(|p| fixture(&format!("sam-amg/sam-tiny-random-{p}.onnx")));
    let visual = fixture("clip/tiny-clip-visual.onnx");
    let config = random_weights_config(snowmiku(), visual, sam, 48, &out);
    let report = encode(config).expect("encode");
    assert_eq!(report.counts.views_used, 3);
    assert!(
        report.counts.masks > 0,
        "the random SAM produced no mask at all"
    );
    let emb =
        slag_common::embeddings::Embeddings::read(&out.join("embeddings.safetensors")).unwrap();
    assert_eq!(emb.dim, 512);
    assert_eq!(emb.len(), report.counts.observed);
    assert!(emb.vectors.iter().all(|v| v.is_finite()));
}

/// Floors (docs/results/accuracy.md): this CI subset (9 views, raster scale 0.25) measured mIoU 0.195 with
/// color-sam and 0.165 with the graph segmenter on the 2-core CPU machine, see docs/results/accuracy.md for the full
/// every-2nd-image runs; the floors sit ~25% below the subset values and above the trivial answer
/// (every Gaussian "gray", the majority class: mIoU 52464/108957/5 = 0.096), so a broken stage
/// (wrong mask resampling, wrong pose convention, unnormalised sums) fails, while run-to-run noise
/// cannot (the pipeline is deterministic).
const MIOU_FLOOR_SAM: f64 = 0.15;
const MIOU_FLOOR_GRAPH: f64 = 0.12;
