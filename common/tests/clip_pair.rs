//! CLIP model pairing through real ONNX files: the `slag.clip_pair_id` metadata is preferred over
//! the file name, and a text tower of another model is refused with [`Error::ModelMismatch`].
//!
//! The metadata is added here without Python: an ONNX file is a `ModelProto` protobuf, and
//! appending field 14 (`metadata_props`, a repeated `StringStringEntryProto {key = 1, value = 2}`)
//! to its bytes adds one entry.
#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};

use slag_common::Error;
use slag_common::onnx::{self, CLIP_PAIR_ID_KEY, ExecutionProvider};
use slag_common::text::TextEncoder;

fn clip_dir() -> PathBuf {
    slag_common::paths::source_tree_shared_dir().join("fixtures/clip")
}

/// Whether ONNX Runtime is set up; without it the test may only skip when `SLAG_SKIP_ORT` is set.
fn ort_ready() -> bool {
    let ready = std::env::var_os("ORT_DYLIB_PATH").is_some();
    let remedy = "ORT_DYLIB_PATH is not set: run `. scripts/setup.sh` (or set SLAG_SKIP_ORT=1)";
    assert!(
        ready || std::env::var_os("SLAG_SKIP_ORT").is_some(),
        "{remedy}"
    );
    ready
}

fn varint(mut v: usize, out: &mut Vec<u8>) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

fn field(tag: u8, bytes: &[u8], out: &mut Vec<u8>) {
    out.push(tag);
    varint(bytes.len(), out);
    out.extend_from_slice(bytes);
}

/// Copies the ONNX model `src` to `dst` with one more `metadata_props` entry `key = value`.
fn with_metadata(src: &Path, dst: &Path, key: &str, value: &str) {
    let mut bytes = std::fs::read(src).unwrap();
    let mut entry = Vec::new();
    field(0x0a, key.as_bytes(), &mut entry);
    field(0x12, value.as_bytes(), &mut entry);
    field((14 << 3) | 2, &entry, &mut bytes);
    std::fs::write(dst, bytes).unwrap();
}

/// A copy of the tiny-clip text tower at `dst` whose metadata gives the CLIP pair id `id`.
fn tiny_textual_with_pair_id(dst: &Path, id: &str) {
    with_metadata(
        &clip_dir().join("tiny-clip-textual.onnx"),
        dst,
        CLIP_PAIR_ID_KEY,
        id,
    );
}

fn text_encoder(model: &Path) -> TextEncoder {
    TextEncoder::new(
        model,
        &clip_dir().join("clip-tokenizer.json"),
        ExecutionProvider::Cpu,
    )
    .unwrap()
}

#[test]
fn fixtures_without_metadata_pair_by_file_name() {
    if !ort_ready() {
        return;
    }
    let color = text_encoder(&clip_dir().join("color-clip-textual.onnx"));
    assert_eq!(color.pair_id(), "color-clip");
    // New stores record the pair id, old ones the visual file stem: both accepted.
    color.check_pair("color-clip").unwrap();
    color.check_pair("color-clip-visual").unwrap();
    let tiny = text_encoder(&clip_dir().join("tiny-clip-textual.onnx"));
    assert_eq!(tiny.pair_id(), "tiny-clip");
    tiny.check_pair("tiny-clip-visual").unwrap();
    let e = tiny.check_pair("color-clip-visual").unwrap_err();
    assert!(
        matches!(&e, Error::ModelMismatch { text_model, embeddings_model, .. }
            if text_model == "tiny-clip" && embeddings_model == "color-clip"),
        "{e}"
    );
}

#[test]
fn metadata_id_is_preferred_over_the_file_name() {
    if !ort_ready() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    // Named like the color-clip text tower, but its metadata says it belongs to another model.
    let renamed = dir.path().join("color-clip-textual.onnx");
    tiny_textual_with_pair_id(&renamed, "ViT-B-16/openai/0123abcd");
    let t = text_encoder(&renamed);
    assert_eq!(t.pair_id(), "ViT-B-16/openai/0123abcd");
    t.check_pair("ViT-B-16/openai/0123abcd").unwrap();
    let e = t.check_pair("color-clip").unwrap_err();
    let msg = e.to_string();
    assert!(
        matches!(e, Error::ModelMismatch { .. })
            && msg.contains("ViT-B-16/openai/0123abcd")
            && msg.contains("`color-clip`"),
        "{msg}"
    );
    // The same id read directly from a session (the encoder's image-tower path).
    let s = onnx::load_session(&renamed, ExecutionProvider::Cpu, 1).unwrap();
    assert_eq!(onnx::clip_pair_id(&s, &renamed), "ViT-B-16/openai/0123abcd");
    // An empty metadata value falls back to the file name.
    let empty = dir.path().join("mine_textual.onnx");
    tiny_textual_with_pair_id(&empty, " ");
    assert_eq!(text_encoder(&empty).pair_id(), "mine");
}
