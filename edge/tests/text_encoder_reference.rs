//! The edge's text path (CLIP BPE tokenizer through `tokenizers`/onig, CLIP text tower through the
//! dynamically loaded ONNX Runtime) reproduces open_clip's token ids and embeddings
//! (`shared/fixtures/clip/reference.json`, tiny-clip textual tower). Natively this checks the
//! x86_64 build; `scripts/cross-aarch64.sh` runs the same test under qemu-aarch64 with the arm64
//! ONNX Runtime library, which proves the Jetson binary's C/C++ parts and ORT load and compute
//! correctly on aarch64.
//!
//! Needs ONNX Runtime: `. scripts/setup.sh` exports `ORT_DYLIB_PATH`; without it the test fails
//! (SLAG_SKIP_ORT set skips it, for quick local runs).

#![allow(clippy::unwrap_used)]

mod support;

use std::path::PathBuf;

use serde::Deserialize;
use serde_json::Value;
use slag_common::onnx::ExecutionProvider;
use slag_common::text::TextEncoder;

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
    if support::skip_without_ort() {
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
    let texts = Vec::<&str>::deserialize(&reference["texts"]).unwrap();
    assert!(!texts.is_empty());
    let ids = text.tokenize(&texts).unwrap();
    for (i, row) in ids.iter().enumerate() {
        let want = Vec::<i64>::deserialize(&reference["input_ids"][i]).unwrap();
        assert_eq!(row, &want, "token ids of {:?}", texts[i]);
    }
    let embs = text.encode(&texts).unwrap();
    assert_eq!(embs.len(), texts.len());
    for (i, e) in embs.iter().enumerate() {
        let want = Vec::<f64>::deserialize(&reference["text_embeds"][i]).unwrap();
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
