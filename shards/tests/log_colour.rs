//! The log lines of `slag-shards` (and of `slag-encoder`, `slag-edge` and `slag-bench`, which
//! share `slag_common::cli::process::init_logging`) carry no ANSI colour codes when stderr is not
//! a terminal.
#![allow(clippy::unwrap_used)]

use std::process::Command;

#[test]
fn partition_logs_without_colour_codes_into_a_pipe() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let out = Command::new(env!("CARGO_BIN_EXE_slag-shards"))
        .args([
            "partition",
            "--synthetic",
            "2000:16",
            "--scene",
            "syn",
            "--shard-store",
        ])
        .arg(&store)
        .env("RUST_LOG", "debug")
        .env_remove("NO_COLOR")
        .output()
        .unwrap();
    let log = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{log}");
    assert!(log.contains("DEBUG"), "no log line to check: {log}");
    assert!(
        !log.contains('\u{1b}'),
        "escape codes in a piped log: {log:?}"
    );
}
