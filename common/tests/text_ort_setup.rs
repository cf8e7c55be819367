//! ONNX Runtime discovery errors, seen through [`TextEncoder::new`]: `ORT_DYLIB_PATH` unset or
//! pointing to a missing file must give a typed error that says how to install the runtime.
//!
//! The runtime is loaded once per process, so each case runs in a child process (this test binary
//! re-run with `SLAG_ORT_CASE` set and a modified environment).

#![allow(clippy::unwrap_used)]

use std::path::PathBuf;
use std::process::Command;

use slag_common::Error;
use slag_common::onnx::ExecutionProvider;
use slag_common::text::TextEncoder;

fn clip_dir() -> PathBuf {
    slag_common::paths::source_tree_shared_dir().join("fixtures/clip")
}

fn try_load() -> Error {
    TextEncoder::new(
        &clip_dir().join("tiny-clip-textual.onnx"),
        &clip_dir().join("clip-tokenizer.json"),
        ExecutionProvider::Cpu,
    )
    .err()
    .expect("loading must fail without a usable ONNX Runtime")
}

/// Runs `case` in a child process with `ORT_DYLIB_PATH` set to `dylib` (or removed).
fn run_child(case: &str, dylib: Option<&str>) {
    let exe = std::env::current_exe().unwrap();
    let mut cmd = Command::new(exe);
    cmd.args(["--exact", "child_case", "--nocapture"])
        .env("SLAG_ORT_CASE", case);
    match dylib {
        Some(p) => cmd.env("ORT_DYLIB_PATH", p),
        None => cmd.env_remove("ORT_DYLIB_PATH"),
    };
    let out = cmd.output().unwrap();
    let text =
        String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "child case {case} failed:\n{text}");
    assert!(
        text.contains(&format!("case {case} checked")),
        "child case {case} did not run:\n{text}"
    );
}

/// The child side: does nothing unless `SLAG_ORT_CASE` is set.
#[test]
fn child_case() {
    let Ok(case) = std::env::var("SLAG_ORT_CASE") else {
        return;
    };
    let err = try_load();
    match case.as_str() {
        "unset" => {
            let Error::Invalid(msg) = &err else {
                panic!("expected Error::Invalid, got {err}")
            };
            assert!(msg.contains("ORT_DYLIB_PATH is not set"), "{msg}");
            assert!(msg.contains("install-onnxruntime.sh"), "{msg}");
        }
        "missing" => {
            let Error::Model { path, message } = &err else {
                panic!("expected Error::Model, got {err}")
            };
            assert_eq!(path, &PathBuf::from("/nonexistent/libonnxruntime.so"));
            assert!(message.contains("install-onnxruntime.sh"), "{message}");
        }
        other => panic!("unknown case {other}"),
    }
    println!("case {case} checked");
}

#[test]
fn unset_ort_dylib_path_is_a_typed_error() {
    run_child("unset", None);
}

#[test]
fn missing_ort_library_is_a_typed_error() {
    run_child("missing", Some("/nonexistent/libonnxruntime.so"));
}
