//! `slag-encoder encode` SIGKILLed after it started writing (the dense accumulators spilled to
//! `OUT/.dense-accumulators.partial`) leaves no output that looks complete: no `report.json`, no
//! `embeddings.safetensors` (the embeddings are written to `.partial`, synced and renamed).
#![allow(clippy::unwrap_used)]

use std::process::Stdio;
use std::time::{Duration, Instant};

mod support;

#[test]
fn encode_killed_mid_run_leaves_nothing_that_looks_complete() {
    let root = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    let scene = root.join("data/snowmiku-mini");
    let fixtures = slag_common::paths::source_tree_shared_dir().join("fixtures");
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let mut cmd = support::slag_encoder();
    // A zero accumulator budget spills the dense accumulators to disk from the first view on,
    // so the run writes into OUT early and keeps writing until the end.
    let mut child = cmd
        .args(["encode", "--scene-dir"])
        .arg(&scene)
        .arg("--out")
        .arg(&out)
        .args(["--quiet", "--masks", "graph", "--clip-visual"])
        .arg(fixtures.join("clip/color-clip-visual.onnx"))
        .args([
            "--raster-scale",
            "0.25",
            "--rasterizer",
            "cpu",
            "--accumulator-memory-mb",
            "0",
            "--dense",
            // Every view: a run long enough to be killed mid-way.
            "--views",
            "all",
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let spill = out.join(".dense-accumulators.partial");
    let t0 = Instant::now();
    loop {
        let started = std::fs::read_dir(&spill).is_ok_and(|mut rd| rd.next().is_some());
        if started {
            break;
        }
        if let Some(status) = child.try_wait().unwrap() {
            let mut err = String::new();
            use std::io::Read;
            child
                .stderr
                .take()
                .unwrap()
                .read_to_string(&mut err)
                .unwrap();
            panic!("encode ended ({status}) before writing anything: {err}");
        }
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "encode wrote nothing in 60 s"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    assert!(!out.join("report.json").exists());
    assert!(!out.join("embeddings.safetensors").exists());
    // What is there is visibly unfinished (hidden .partial names).
    for e in std::fs::read_dir(&out).unwrap() {
        let name = e.unwrap().file_name().to_string_lossy().into_owned();
        assert!(name.ends_with(".partial"), "{name}");
    }
}
