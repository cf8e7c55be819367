//! The edge's text path (CLIP BPE tokenizer through `tokenizers`/onig, CLIP text tower through the
//! dynamically loaded ONNX Runtime) reproduces open_clip's token ids and embeddings
//! (`shared/fixtures/clip/reference.json`, tiny-clip textual tower). Natively this checks the
//! x86_64 build; `scripts/cross-aarch64.sh` runs the same test under qemu-aarch64 with the arm64
//! ONNX Runtime library, which proves the Jetson binary's C/C++ parts and ORT load and compute
//! correctly on aarch64.
//!
//! Needs ONNX Runtime: `. scripts/setup.sh` exports `ORT_DYLIB_PATH`; without it the test fails
//! (SLAG_SKIP_ORT=1 skips it, for quick local runs).

#![allow(clippy::unwrap_used)]

use std::path::PathBuf;

use serde_json::Value;
use slag_common::onnx::ExecutionProvider;
use slag_common::text::TextEncoder;

fn ort_available() -> bool {
    if std::env::var_os("ORT_DYLIB_PATH").is_some() {
        return true;
    }
    if std::env::var("SLAG_SKIP_ORT").as_deref() == Ok("1") {
        eprintln!("SKIPPED (SLAG_SKIP_ORT=1): ORT_DYLIB_PATH is not set");
        return false;
    }
    panic!("ORT_DYLIB_PATH is not set: run `. scripts/setup.sh` (or set SLAG_SKIP_ORT=1 to skip)");
}

fn clip_dir() -> PathBuf {
    slag_common::paths::source_tree_shared_dir().join("fixtures/clip")
}

fn cosine(a: &[f32], b: &[f64]) -> f64 {
    let dot: f64 = a.iter().zip(b).map(|(&x, &y)| f64::from(x) * y).sum();
    let na: f64 = a.iter().map(|&x| f64::from(x).powi(2)).sum::<f64>().sqrt();
    let nb: f64 = b.iter().map(|y| y * y).sum::<f64>().sqrt();
    dot / (na * nb)
}

#[test]
fn text_encoder_reproduces_open_clip() {
    if !ort_available() {
        return;
    }
    let reference: Value =
        serde_json::from_slice(&std::fs::read(clip_dir().join("reference.json")).unwrap()).unwrap();
    let mut text = TextEncoder::new(
        &clip_dir().join("tiny-clip-textual.onnx"),
        &clip_dir().join("clip-tokenizer.json"),
        ExecutionProvider::Cpu,
    )
    .unwrap();
    let texts: Vec<&str> = reference["texts"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t.as_str().unwrap())
        .collect();
    assert!(!texts.is_empty());
    let ids = text.tokenize(&texts).unwrap();
    for (i, row) in ids.iter().enumerate() {
        let want: Vec<i64> = reference["input_ids"][i]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_i64().unwrap())
            .collect();
        assert_eq!(row, &want, "token ids of {:?}", texts[i]);
    }
    let embs = text.encode(&texts).unwrap();
    assert_eq!(embs.len(), texts.len());
    for (i, e) in embs.iter().enumerate() {
        let want: Vec<f64> = reference["text_embeds"][i]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        assert_eq!(e.len(), want.len(), "embedding width of {:?}", texts[i]);
        let cos = cosine(e, &want);
        assert!(cos >= 0.999, "text {:?}: cosine {cos}", texts[i]);
        let norm: f32 = e.iter().map(|x| x * x).sum::<f32>().sqrt();
        assert!(
            (norm - 1.0).abs() < 1e-4,
            "embeddings are L2-normalised, got {norm}"
        );
    }
}
