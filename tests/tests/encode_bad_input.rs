//! Bad input to `encode` gets a typed error naming the file and what to do, never a panic and
//! never an output that looks complete.

#![allow(clippy::unwrap_used)]

use slag_encoder::config::RasterBackend;
use slag_tests::{default_scene, encode, fixture, graph_config};

/// A copy of the embedded default scene that a test may damage.
fn scene_copy(dir: &std::path::Path) -> std::path::PathBuf {
    let src = default_scene();
    let dst = dir.join("scene");
    for sub in ["images", "sparse/0"] {
        std::fs::create_dir_all(dst.join(sub)).unwrap();
        for e in std::fs::read_dir(src.join(sub)).unwrap() {
            let e = e.unwrap();
            std::fs::copy(e.path(), dst.join(sub).join(e.file_name())).unwrap();
        }
    }
    std::fs::copy(src.join("point_cloud.ply"), dst.join("point_cloud.ply")).unwrap();
    dst
}

/// The first image (by name) of a scene folder.
fn first_image(scene: &std::path::Path) -> std::path::PathBuf {
    let images = std::fs::read_dir(scene.join("images")).unwrap();
    images.map(|e| e.unwrap().path()).min().unwrap()
}

fn encode_graph(scene: &std::path::Path, out: &std::path::Path) -> anyhow::Result<()> {
    let mut config = graph_config(scene, out);
    config.raster.scale = 0.25;
    config.raster.backend = RasterBackend::Cpu;
    encode(config).map(|_| ())
}

#[test]
fn image_of_the_wrong_size_is_a_clear_error_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let scene = scene_copy(dir.path());
    let first = first_image(&scene);
    image::RgbImage::new(100, 80).save(&first).unwrap();
    let out = dir.path().join("out");
    let err = format!("{:#}", encode_graph(&scene, &out).unwrap_err());
    assert!(err.contains("100x80") && err.contains("camera"), "{err}");
    // The segments, computed beside the encode (stopped here), are not written either.
    for name in [
        "embeddings.safetensors",
        "report.json",
        "segments.safetensors",
    ] {
        assert!(!out.join(name).exists(), "{name}");
    }
}

#[test]
fn missing_image_names_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let scene = scene_copy(dir.path());
    let first = first_image(&scene);
    std::fs::remove_file(&first).unwrap();
    let err = format!(
        "{:#}",
        encode_graph(&scene, &dir.path().join("out")).unwrap_err()
    );
    assert!(
        err.contains(first.file_name().unwrap().to_str().unwrap()),
        "{err}"
    );
}

#[test]
fn nan_in_the_ply_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let scene = scene_copy(dir.path());
    let ply = scene.join("point_cloud.ply");
    let mut bytes = std::fs::read(&ply).unwrap();
    let body = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .unwrap()
        + 11;
    // Vertex 0, property 0 (x) := NaN.
    bytes[body..body + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    std::fs::write(&ply, bytes).unwrap();
    let err = format!(
        "{:#}",
        encode_graph(&scene, &dir.path().join("out")).unwrap_err()
    );
    assert!(
        err.contains("point_cloud.ply") && err.to_lowercase().contains("vertex 0"),
        "{err}"
    );
}

#[test]
fn wrong_model_for_the_role_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = graph_config(&default_scene(), &dir.path().join("out"));
    config.clip.visual = fixture("clip/color-clip-textual.onnx");
    let err = encode(config).unwrap_err();
    let err = format!("{err:#}");
    assert!(
        err.contains("color-clip-textual.onnx") && err.contains("pixel_values"),
        "{err}"
    );
}

#[test]
fn raster_scale_out_of_range_is_a_clear_error_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    for scale in [0.0, -1.0, 5.0, f64::NAN] {
        let mut config = graph_config(&default_scene(), &out);
        config.raster.scale = scale;
        let e = encode(config).unwrap_err();
        // The library names the parameter (slag-encoder's hint adds the flag, tested in
        // cli/src/hints.rs).
        let err = format!("{e:#}");
        assert!(err.contains("raster_scale"), "{scale}: {err}");
        let param = e
            .chain()
            .find_map(|c| match c.downcast_ref::<slag_common::Error>() {
                Some(slag_common::Error::Param { name, .. }) => Some(name.to_string()),
                _ => None,
            });
        assert_eq!(param.as_deref(), Some("raster_scale"), "{scale}: {err}");
    }
    assert!(!out.exists());
}
