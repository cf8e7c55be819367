//! `slag-edge`'s log lines carry no ANSI colour codes when stderr is not a terminal (a log file,
//! journald, CI): `slag-edge serve 2> log` stays plain text.
#![allow(clippy::unwrap_used)]

mod support;

use std::io::{BufRead, BufReader};
use std::process::Stdio;

use slag_common::shards::Dtype;
use support::{
    assert_success, color_clip_text_model, fetch_args, grid_scene, output_blocking, shard_server,
    text_model_args,
};

/// Runs `serve` with stderr piped until it logs that it listens, then stops it: the log line is
/// there and holds no escape sequence.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn serve_logs_without_colour_codes_into_a_pipe() {
    if support::skip_without_ort() {
        return;
    }
    // Under qemu (cross build) the binary is started through `$SLAG_TEST_RUNNER`.
    let command = |args: &[&str]| {
        let mut c = support::slag_edge_command();
        c.args(args).env("RUST_LOG", "info").env_remove("NO_COLOR");
        c
    };

    let server = shard_server(grid_scene("grid", 2, 2, 10, 512, Dtype::F16, 1), None).await;
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store").display().to_string();
    let fetch = command(&fetch_args(&server.url, &store, "100"));
    assert_success(&output_blocking(fetch).await, "fetch");

    let [tm, tok] = color_clip_text_model();
    let serve = text_model_args("serve", &store, "grid", [&tm, &tok]);
    let mut child = command(&[&serve[..], &["--listen", "127.0.0.1:0"]].concat())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = child.stderr.take().unwrap();
    let log = tokio::task::spawn_blocking(move || {
        let mut log = String::new();
        for line in BufReader::new(stderr).lines() {
            let line = line.unwrap();
            log.push_str(&line);
            log.push('\n');
            if line.contains("listening on http://") {
                break;
            }
        }
        log
    })
    .await
    .unwrap();
    let _ = child.kill();
    let _ = child.wait();
    assert!(log.contains("listening on http://"), "{log}");
    assert!(log.contains("INFO"), "{log}");
    assert!(
        !log.contains('\u{1b}'),
        "escape codes in a piped log: {log:?}"
    );
}
