//! The default outputs are enough for partition, serve and query: `slag-encoder encode` with no
//! output flag writes the mixture, the segments and the report (no dense file), and `partition`
//! (given the dense path the encode did not write, or the mixture), `serve` and `query` work
//! from them as the binary runs them; a command that needs the dense file says which flag makes
//! it. A tiny synthetic scene on the CPU.

#![allow(clippy::unwrap_used)]

mod support;

use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Output, Stdio};

use slag_common::testing::served_address;
use support::{assert_success, slag_encoder};

fn fixtures() -> PathBuf {
    slag_common::paths::source_tree_shared_dir().join("fixtures")
}

fn ok(o: Output) -> String {
    assert_success(&o);
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// `GET path` on `addr` over plain HTTP/1.1: the status code and the body.
fn get(addr: &str, path: &str) -> (u16, Vec<u8>) {
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    write!(
        s,
        "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut raw = Vec::new();
    s.read_to_end(&mut raw).unwrap();
    let split = raw.windows(4).position(|w| w == b"\r\n\r\n").unwrap();
    let head = String::from_utf8_lossy(&raw[..split]).into_owned();
    let status = head.split_whitespace().nth(1).unwrap().parse().unwrap();
    (status, raw[split + 4..].to_vec())
}

/// `slag-encoder query` of `text` against `embeddings`: the printed JSON.
fn query(embeddings: &Path, text: &str) -> serde_json::Value {
    let clip = fixtures().join("clip");
    let o = slag_encoder()
        .arg("query")
        .arg("--embeddings")
        .arg(embeddings)
        .arg("--clip-textual")
        .arg(clip.join("color-clip-textual.onnx"))
        .arg("--tokenizer")
        .arg(clip.join("clip-tokenizer.json"))
        .args(["--text", text, "--threshold", "0", "--top-k", "5"])
        .output()
        .unwrap();
    serde_json::from_str(&ok(o)).unwrap()
}

#[test]
fn the_default_outputs_are_enough_for_partition_serve_and_query() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    let out = dir.path().join("out");
    ok(slag_encoder()
        .args(["synth-scene", "--gaussians", "3000", "--view-count", "4"])
        .args(["--width", "96", "--height", "72", "--extent", "20", "--out"])
        .arg(&scene)
        .output()
        .unwrap());
    let encoded = slag_encoder()
        .args([
            "encode",
            "--quiet",
            "--masks",
            "graph",
            "--rasterizer",
            "cpu",
            "--scene-dir",
        ])
        .arg(&scene)
        .arg("--clip-visual")
        .arg(fixtures().join("clip/color-clip-visual.onnx"))
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    let closing = String::from_utf8_lossy(&encoded.stderr).into_owned();
    ok(encoded);
    let mut names: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| !n.starts_with('.'))
        .collect();
    names.sort();
    // The masks' record is the segmentation's mask term, kept for `slag-encoder segment`.
    assert_eq!(
        names,
        [
            "mask-record.safetensors",
            "mixture.safetensors",
            "report.json",
            "segments.safetensors"
        ],
        "the default outputs"
    );
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    assert!(
        report["outputs"]["embeddings"].is_null(),
        "{}",
        report["outputs"]
    );
    // The report, written again after the segments, says where the tail's time went.
    let segments = &report["segments"];
    assert_eq!(
        segments["path"].as_str().map(PathBuf::from),
        Some(out.join("segments.safetensors")),
        "{segments}"
    );
    assert_eq!(
        segments["mask_record"].as_str().map(PathBuf::from),
        Some(out.join("mask-record.safetensors")),
        "{segments}"
    );
    let stored = slag_common::segments::Segments::read(&out.join("segments.safetensors")).unwrap();
    assert_eq!(
        segments["stats"]["segments"].as_u64(),
        Some(u64::from(stored.segment_count)),
        "{segments}"
    );
    assert!(segments["waited_s"].as_f64().unwrap() >= 0.0, "{segments}");
    assert!(
        segments["stats"]["stages"]["neighbours"].is_number(),
        "{segments}"
    );
    assert!(
        report["timings"]["reduce"].as_f64().unwrap() > 0.0,
        "{}",
        report["timings"]
    );
    assert!(
        closing.contains("on the CPU, write") && closing.contains("segments waited"),
        "{closing}"
    );
    let mix =
        slag_common::mixture::MixtureEmbeddings::read(&out.join("mixture.safetensors")).unwrap();
    assert_eq!(mix.keep.min(4), mix.keep, "at most the default 4 slots");
    assert!(mix.len() > 100, "{} observed", mix.len());

    // partition, given the dense path the encode did not write: the mixture beside it.
    let store = dir.path().join("store");
    let dense_path = out.join("embeddings.safetensors");
    let o = slag_encoder()
        .arg("partition")
        .arg("--embeddings")
        .arg(&dense_path)
        .arg("--shard-store")
        .arg(&store)
        .args(["--scene", "tiny"])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr).into_owned();
    let stdout = ok(o);
    assert!(stderr.contains("mixture.safetensors"), "{stderr}");
    assert!(stdout.contains("as mixtures of"), "{stdout}");

    // serve: the manifest (a mixture scene, every observed Gaussian) and the codebook.
    let mut server = slag_encoder()
        .arg("serve")
        .arg("--shard-store")
        .arg(&store)
        .args(["--listen", "127.0.0.1:0"])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let addr = served_address(&mut server);
    let (status, body) = get(&addr, "/v1/scenes/tiny/manifest");
    let (codebook_status, codebook) = get(&addr, "/v1/scenes/tiny/codebook");
    server.kill().unwrap();
    server.wait().unwrap();
    assert_eq!(status, 200);
    let manifest: serde_json::Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(manifest["total_gaussians"].as_u64(), Some(mix.len() as u64));
    assert!(manifest["mixture"].is_object(), "{manifest}");
    assert_eq!((codebook_status, codebook.is_empty()), (200, false));

    // query: the mixture, and the dense path the encode did not write, give the same answer.
    let a = query(&out.join("mixture.safetensors"), "red");
    let b = query(&dense_path, "red");
    assert_eq!(a["matches"].as_array().unwrap().len(), 5, "{a}");
    assert_eq!(a["matches"], b["matches"]);

    // A command that needs the dense rows names the flag that writes them.
    let o = slag_encoder()
        .arg("eval-colors")
        .arg("--scene-dir")
        .arg(&scene)
        .arg("--embeddings")
        .arg(&dense_path)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(
        err.contains("--dense") && !err.contains("panicked"),
        "{err}"
    );
}
