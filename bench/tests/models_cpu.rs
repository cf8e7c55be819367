//! `slag-bench models` on the CPU with the small real-architecture fixtures (tiny CLIP, tiny SAM)
//! on the embedded scene: every row is measured, a model compared with itself agrees exactly,
//! and a different model does not.

#![allow(clippy::unwrap_used)]

use std::path::PathBuf;

use slag_bench::models::{ModelsArgs, run};
use slag_common::cli::EpArg;

fn fixtures() -> Option<PathBuf> {
    let shared = std::env::var_os("SLAG_SHARED")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared"));
    let f = shared.join("fixtures");
    f.join("clip/tiny-clip-visual.onnx").exists().then_some(f)
}

/// The cells of the markdown table row whose first cell contains `needle`.
fn row<'a>(table: &'a str, needle: &str, nth: usize) -> Vec<&'a str> {
    table
        .lines()
        .filter(|l| l.starts_with("| ") && l.contains(needle))
        .nth(nth)
        .unwrap_or_else(|| panic!("no row {nth} with {needle} in\n{table}"))
        .split('|')
        .map(str::trim)
        .filter(|c| !c.is_empty())
        .collect()
}

#[test]
fn models_times_each_model_and_compares_variants_with_the_first() {
    if std::env::var_os("ORT_DYLIB_PATH").is_none() {
        eprintln!("skipped: ORT_DYLIB_PATH unset (. scripts/setup.sh)");
        return;
    }
    let Some(f) = fixtures() else {
        panic!("shared/fixtures not found: set SLAG_SHARED");
    };
    let tiny = f.join("clip/tiny-clip-visual.onnx");
    let color = f.join("clip/color-clip-visual.onnx");
    // color-clip given byte input by scripts/clip-u8-pixels.py.
    let color_u8 = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../encoder/tests/fixtures/color-clip-visual-u8.onnx");
    let args = ModelsArgs {
        scene: PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../data/snowmiku-mini"),
        images: 1,
        clip_visual: vec![tiny.clone(), tiny.clone(), color, color_u8],
        batch: 16,
        sam_encoder: vec![f.join("sam-amg/sam-tiny-random-encoder.onnx"); 2],
        sam_decoder: vec![f.join("sam-amg/sam-tiny-random-decoder.onnx"); 2],
        points_per_side: 3,
        prompt_batch: 4,
        repeats: 1,
        ep: EpArg::Cpu,
    };
    let out = run(&args).unwrap();
    let first = row(&out, "tiny-clip-visual", 0);
    assert_eq!(first[1], "f32, normalised on the host");
    assert_eq!(first[4], "reference");
    assert_eq!(first[5], "reference");
    let ms: f64 = first[2].parse().unwrap();
    assert!(ms > 0.0, "ms per crop {ms}");
    let same = row(&out, "tiny-clip-visual", 1);
    let (min, med) = same[4].split_once(" / ").unwrap();
    assert!(min.parse::<f64>().unwrap() > 0.99999, "{same:?}");
    assert!(med.parse::<f64>().unwrap() > 0.99999, "{same:?}");
    // color-clip answers colours, not tiny-clip's random features: far from cosine 1.
    let other = row(&out, "color-clip-visual", 0);
    let (min, _) = other[5].split_once(" / ").unwrap();
    assert!(min.parse::<f64>().unwrap() < 0.9, "{other:?}");
    let (min, _) = same[5].split_once(" / ").unwrap();
    assert!(min.parse::<f64>().unwrap() > 0.99999, "{same:?}");
    // The byte tower is timed with its own input and gives color-clip's embeddings.
    let bytes = row(&out, "color-clip-visual-u8", 0);
    assert_eq!(bytes[1], "u8 pixels");
    assert_eq!(bytes[4], other[4], "{bytes:?} against {other:?}");
    // SAM: the same decoder twice agrees exactly (IoU difference 0, mask IoU 1).
    let sam = row(&out, "sam-tiny-random-decoder", 1);
    assert!(sam[1].parse::<f64>().unwrap() > 0.0 && sam[2].parse::<f64>().unwrap() > 0.0);
    assert_eq!(sam[3].parse::<f64>().unwrap(), 0.0, "{sam:?}");
    assert_eq!(sam[4], "1.0000 / 1.0000", "{sam:?}");
}
