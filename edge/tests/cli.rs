//! The `slag-edge` binary as a user runs it: `fetch` (summary, exit codes, messages), `check` and
//! `query` with the color-clip text tower. Under qemu (cross build) the binary is started through
//! `$SLAG_TEST_RUNNER`.
#![allow(clippy::unwrap_used)]

mod support;

use std::process::{Command, Output};

use slag_common::shards::Dtype;
use support::{
    Grid, assert_success, color_clip_text_model, fetch_args, fixture, grid_scene,
    grid_scene_segmented, output_blocking, shard_server, slag_edge_command, slag_edge_with_log,
    success_json, text_model_args,
};

fn slag_edge(args: &[&str]) -> Output {
    slag_edge_with_log(args, "warn").output().unwrap()
}

/// `slag-edge ARGS` run to completion off the test's runtime (which serves the shards).
async fn slag_edge_async(args: &[&str]) -> Output {
    output_blocking(slag_edge_with_log(args, "warn")).await
}

/// `stderr` is two lines: `error: …` naming `error`, then `hint: …` holding each of `hint`.
fn assert_error_then_hint(stderr: &str, error: &str, hint: &[&str]) {
    let lines: Vec<&str> = stderr.trim().lines().collect();
    assert_eq!(lines.len(), 2, "{stderr}");
    let error_line = lines[0].starts_with("error: ") && lines[0].contains(error);
    assert!(error_line, "{stderr}");
    let hint_line = lines[1].starts_with("hint: ") && hint.iter().all(|h| lines[1].contains(h));
    assert!(hint_line, "{stderr}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fetch_check_and_query_from_the_command_line() {
    // 512-d so that color-clip's text tower fits the stored embeddings.
    let server = shard_server(grid_scene("grid", 3, 3, 20, 512, Dtype::F16, 1), None).await;
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store").display().to_string();
    let url = server.url.clone();

    let fetch = [fetch_args(&url, &store, "5"), vec!["--json"]].concat();
    let summary = success_json(&slag_edge_async(&fetch).await);
    assert_eq!(summary["selected"], 1);
    assert_eq!(summary["gaussians"], 20);

    // Bad input: non-zero exit and a message naming the flag.
    let bad = [
        "fetch", "--from", &url, "--scene", "grid", "--center", "0,zero", "--store", &store,
    ];
    let out = slag_edge_async(&bad).await;
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--center"));

    let [tm, tok] = color_clip_text_model();
    if support::skip_without_ort() {
        return;
    }
    let report = success_json(
        &slag_edge_async(&text_model_args("check", &store, "grid", [&tm, &tok])).await,
    );
    assert_eq!(report["gaussians"], 20);
    assert_eq!(report["text_dim"], 512);

    let query = text_model_args("query", &store, "grid", [&tm, &tok]);
    let ranked = ["--text", "red", "--top-k", "5", "--threshold", "none"];
    let a = success_json(&slag_edge_async(&[&query[..], &ranked].concat()).await);
    assert_eq!(a["matches"].as_array().unwrap().len(), 5);
    assert_eq!(a["searched"], 20);

    // A text tower of another CLIP model (tiny-clip) than the stored one (color-clip): refused.
    let tiny = fixture("clip/tiny-clip-textual.onnx");
    let query = text_model_args("query", &store, "grid", [&tiny, &tok]);
    let out = slag_edge_async(&[&query[..], &["--text", "red"]].concat()).await;
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("`tiny-clip`") && err.contains("`color-clip`"),
        "{err}"
    );

    // A scene that was never fetched: non-zero exit, the message says to run fetch.
    let check = text_model_args("check", &store, "nope", ["x", "y"]);
    assert!(!slag_edge_async(&check).await.status.success());
}

/// Failed queries: no store folder is created, each refusal gives the CLI's own hint, and an error
/// is one line without a backtrace unless --verbose is given (even with RUST_BACKTRACE=1).
#[test]
fn failed_queries_create_nothing_give_cli_hints_and_no_backtrace() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("no-store");
    let s = store.display().to_string();
    let run = |text: &str, extra: &[&str], backtrace: bool| {
        let mut cmd = slag_edge_command();
        cmd.args(text_model_args("query", &s, "grid", ["m.onnx", "t.json"]))
            .args(["--text", text])
            .args(extra)
            .env("RUST_LOG", "warn");
        if backtrace {
            cmd.env("RUST_BACKTRACE", "1");
        } else {
            cmd.env_remove("RUST_BACKTRACE")
                .env_remove("RUST_LIB_BACKTRACE");
        }
        let out = cmd.output().unwrap();
        assert!(!out.status.success());
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    // Missing store: a typed error saying to fetch first; the folder is not created.
    let e = run("chair", &[], true);
    assert!(
        e.contains("slag-edge fetch") && e.contains("no-store"),
        "{e}"
    );
    assert!(!e.to_lowercase().contains("backtrace"), "{e}");
    // One line for the error (the library's words: the store parameter), one for the CLI's hint
    // (the fetch command to run).
    assert_error_then_hint(&e, "no-store", &["slag-edge fetch"]);
    assert!(
        !store.exists(),
        "slag-edge query created {}",
        store.display()
    );
    // --verbose shows the debug form (with the backtrace anyhow captured).
    let e = run("chair", &["--verbose"], true);
    assert!(
        e.contains("Stack backtrace") || e.contains("stack backtrace"),
        "{e}"
    );
    // Blank and too-long prompts: refused before the store is touched, with the CLI hint.
    for text in ["", "   "] {
        let e = run(text, &[], false);
        assert!(
            e.contains("missing query text") && e.contains("--text"),
            "{e}"
        );
        assert!(
            !e.contains("/query?text"),
            "the CLI gave the HTTP hint: {e}"
        );
    }
    let long = "a".repeat(slag_common::prompt::MAX_PROMPT_BYTES + 1);
    let e = run(&long, &[], false);
    assert!(e.contains("at most 1000") && e.contains("--text"), "{e}");
    assert!(!store.exists());
    // check and serve do not create it either.
    for sub in ["check", "serve"] {
        let bin = env!("CARGO_BIN_EXE_slag-edge");
        if std::env::var("SLAG_TEST_RUNNER").is_ok_and(|r| !r.trim().is_empty()) {
            break;
        }
        let out = Command::new(bin)
            .args(text_model_args(sub, &s, "grid", ["m.onnx", "t.json"]))
            .args(["--listen", "127.0.0.1:0"])
            .env("RUST_LOG", "warn")
            .output()
            .unwrap();
        assert!(!out.status.success());
        assert!(
            !store.exists(),
            "slag-edge {sub} created {}",
            store.display()
        );
    }
}

/// `serve --hnsw-backend`: an unknown name, a backend without `--hnsw`, and (in a binary built
/// without the cargo feature) `qdrant-edge` are refused at start-up, before the store or the text
/// model is opened, with the error and the CLI's hint.
#[test]
fn serve_refuses_an_unusable_hnsw_backend_at_start_up() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("no-store");
    let s = store.display().to_string();
    let serve = |extra: &[&str]| {
        let mut args = text_model_args("serve", &s, "grid", ["m.onnx", "t.json"]);
        args.extend_from_slice(&["--listen", "127.0.0.1:0"]);
        args.extend_from_slice(extra);
        let out = slag_edge(&args);
        assert!(!out.status.success());
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    let e = serve(&["--hnsw", "--hnsw-backend", "faiss"]);
    assert!(
        e.contains("hnsw_backend") && e.contains("instant-distance or qdrant-edge"),
        "{e}"
    );
    assert!(e.contains("hint: pass --hnsw-backend"), "{e}");
    let e = serve(&["--hnsw-backend", "instant-distance"]);
    assert!(e.contains("without --hnsw"), "{e}");
    if !cfg!(feature = "qdrant-edge") {
        let e = serve(&["--hnsw", "--hnsw-backend", "qdrant-edge"]);
        let hint = ["--hnsw-backend instant-distance", "--features qdrant-edge"];
        assert_error_then_hint(&e, "cargo feature `qdrant-edge`", &hint);
    }
    assert!(!store.exists());
}

/// `slag-edge query --smooth segment`: each score is the mean of its segment's scores (checked
/// against the unsmoothed scores of the same store); a store without segments is refused with
/// a hint.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn query_smooth_segment_from_the_command_line() {
    if support::skip_without_ort() {
        return;
    }
    let [tm, tok] = color_clip_text_model();
    // Tile 0 only (20 Gaussians, ids 0..20), four segments of five (id % 4).
    let segmented = grid_scene_segmented(Grid("grid", 3, 3, 20, 512, Dtype::F16, 1), &|id| id % 4);
    let dir = tempfile::tempdir().unwrap();
    let mut stores = Vec::new();
    for (name, scene) in [
        ("segmented", segmented),
        ("plain", grid_scene("grid", 3, 3, 20, 512, Dtype::F16, 1)),
    ] {
        let server = shard_server(scene, None).await;
        let store = dir.path().join(name).display().to_string();
        let out = slag_edge_async(&fetch_args(&server.url, &store, "5")).await;
        assert_success(&out, name);
        stores.push(store);
    }
    let query = |store: &str, extra: &[&str]| {
        let query = text_model_args("query", store, "grid", [&tm, &tok]);
        let ranked = ["--text", "red", "--top-k", "20", "--threshold", "none"];
        slag_edge(&[&query[..], &ranked, extra].concat())
    };
    let scores = |out: &Output| -> Vec<(u64, f64)> {
        let a = success_json(out);
        let mut v: Vec<(u64, f64)> = a["matches"]
            .as_array()
            .unwrap()
            .iter()
            .map(|m| (m["id"].as_u64().unwrap(), m["score"].as_f64().unwrap()))
            .collect();
        v.sort_by_key(|x| x.0);
        v
    };
    let plain = scores(&query(&stores[0], &[]));
    let smooth_out = query(&stores[0], &["--smooth", "segment"]);
    let a: serde_json::Value = serde_json::from_slice(&smooth_out.stdout).unwrap_or_default();
    assert_eq!(
        a["smooth"],
        "segment",
        "{}",
        String::from_utf8_lossy(&smooth_out.stderr)
    );
    let smoothed = scores(&smooth_out);
    assert_eq!(plain.len(), 20);
    assert_eq!(
        smoothed.iter().map(|s| s.0).collect::<Vec<_>>(),
        plain.iter().map(|s| s.0).collect::<Vec<_>>()
    );
    for seg in 0..4u64 {
        let own: Vec<f64> = plain
            .iter()
            .filter(|p| p.0 % 4 == seg)
            .map(|p| p.1)
            .collect();
        let mean = own.iter().sum::<f64>() / own.len() as f64;
        // The fixture's scores differ within a segment, so an unsmoothed answer cannot pass.
        assert!(own.iter().any(|s| (s - mean).abs() > 1e-4), "{own:?}");
        for s in smoothed.iter().filter(|s| s.0 % 4 == seg) {
            assert!((s.1 - mean).abs() < 1e-5, "id {}: {} vs {mean}", s.0, s.1);
        }
    }
    // No segments in the store: refused, with what to do.
    let out = query(&stores[1], &["--smooth", "segment"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("no geometric segments") && err.contains("hint: leave out --smooth"),
        "{err}"
    );
    let out = query(&stores[1], &["--smooth", "mean"]);
    assert!(String::from_utf8_lossy(&out.stderr).contains("pass --smooth none|segment"));
}
