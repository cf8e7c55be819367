//! `slag-encoder encode` computes the geometric segments beside the encode (on a pool of its
//! own) and writes `segments.safetensors` only after the encode succeeded: the file is
//! byte-identical to `slag-encoder segment`'s on the same scene, and a failed encode leaves none.
#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};
use std::process::Output;

mod support;
use support::{assert_success, slag_encoder};

/// `data/snowmiku-mini` (60k Gaussians, 13 views).
fn scene() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../data/snowmiku-mini")
}

/// `slag-encoder encode` of `scene` into `out` with the default segments (on): graph masks,
/// color-clip, the CPU rasterizer at raster scale 0.25.
fn encode(scene: &Path, out: &Path) -> Output {
    let clip =
        slag_common::paths::source_tree_shared_dir().join("fixtures/clip/color-clip-visual.onnx");
    slag_encoder()
        .args([
            "encode",
            "--quiet",
            "--dense",
            "--masks",
            "graph",
            "--rasterizer",
            "cpu",
        ])
        .args(["--raster-scale", "0.25", "--scene-dir"])
        .arg(scene)
        .arg("--clip-visual")
        .arg(clip)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap()
}

#[test]
fn encode_writes_the_segments_of_slag_encoder_segment() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let run = encode(&scene(), &out);
    assert_success(&run);
    let alone = dir.path().join("alone.safetensors");
    // The segmentation alone, from the masks' record the encode kept, gives the same file.
    let seg = slag_encoder()
        .args(["segment", "--scene-dir"])
        .arg(scene())
        .arg("--mask-record")
        .arg(out.join(slag_common::mask_record::FILE_NAME))
        .arg("--out")
        .arg(&alone)
        .output()
        .unwrap();
    assert_success(&seg);
    let with_encode = std::fs::read(out.join("segments.safetensors")).unwrap();
    let segmented =
        slag_common::segments::Segments::read(&out.join("segments.safetensors")).unwrap();
    assert_eq!(segmented.segments.len(), 60_000);
    assert!(segmented.segment_count > 1);
    assert!(with_encode == std::fs::read(&alone).unwrap());
    assert!(out.join("embeddings.safetensors").exists() && out.join("report.json").exists());
}

#[test]
fn failed_encode_writes_no_segments() {
    let dir = tempfile::tempdir().unwrap();
    // A copy of the scene whose last image has the wrong size: the encode fails at its last
    // view, usually after the segmentation beside it is done (a failure at the first view, with
    // the segmentation stopped, is tests/tests/encode_bad_input.rs's).
    let copy = dir.path().join("scene");
    for sub in ["images", "sparse/0"] {
        std::fs::create_dir_all(copy.join(sub)).unwrap();
        for e in std::fs::read_dir(scene().join(sub)).unwrap() {
            let e = e.unwrap();
            std::fs::copy(e.path(), copy.join(sub).join(e.file_name())).unwrap();
        }
    }
    std::fs::copy(
        scene().join("point_cloud.ply"),
        copy.join("point_cloud.ply"),
    )
    .unwrap();
    let images = std::fs::read_dir(copy.join("images")).unwrap();
    let last = images.map(|e| e.unwrap().path()).max().unwrap();
    image::RgbImage::new(100, 80).save(&last).unwrap();
    let out = dir.path().join("out");
    let run = encode(&copy, &out);
    let err = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success(), "{err}");
    assert!(err.contains("100x80"), "{err}");
    for name in [
        "segments.safetensors",
        "embeddings.safetensors",
        "report.json",
    ] {
        assert!(!out.join(name).exists(), "{name}");
    }
}
