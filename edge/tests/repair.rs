//! The store repairs itself: every kind of damage to stored shards (flipped bytes, truncated,
//! appended to, two files swapped, another scene's shard, a folder in a shard's place, a stale
//! partial download) is set aside and repaired by one fetch, after which the answers equal those
//! of the undamaged store; manifests that declare impossible sizes or are too large, a disk too
//! small, a disk that fills up mid-download and a damaged database; `POST /fetch` with the
//! configured shard token; `slag-edge check` naming missing, corrupt and zero shards. Under qemu
//! (cross build) the binary is started through `$SLAG_TEST_RUNNER`.
#![allow(clippy::unwrap_used)]

mod support;

use std::path::Path;
use std::process::Command;
use std::sync::atomic::Ordering;

use slag_common::shards::{Dtype, MAX_MANIFEST_BYTES, ShardLayout, TileInfo};
use slag_common::{Error, Resource};
use slag_edge::fetch::{FetchParams, FetchSummary, fetch};
use slag_edge::query::RawQuery;
use slag_edge::store::EdgeStore;
use support::{
    BasisEmbedder, exact_answer, grid_fetch_params, grid_scene, open_after_drop, output_blocking,
    partial_files, serve_on_loopback, shard_path, shard_server, slag_edge_with_log, success_json,
    temp_store, text_model_args,
};

fn params(url: &str) -> FetchParams {
    grid_fetch_params(url, 100.0)
}

/// The answers to one prompt per tile direction (every match, no threshold) from what the store
/// serves, plus what loading rejected.
fn answers(store: &EdgeStore) -> (Vec<serde_json::Value>, Vec<String>) {
    let engine = slag_edge::engine::Engine::load(store, "grid", false).unwrap();
    let out = (0..4)
        .map(|t| {
            let q = RawQuery {
                text: Some(format!("t{t}")),
                top_k: Some("1000".into()),
                threshold: Some("none".into()),
                mode: None,
                bbox: None,
                index: None,
                frame: None,
                ..Default::default()
            };
            let a = exact_answer(&engine, 8, q, false);
            serde_json::to_value(&a.matches).unwrap()
        })
        .collect();
    (out, engine.load.rejected)
}

fn quarantined(dir: &Path) -> Vec<String> {
    std::fs::read_dir(dir.join("quarantine"))
        .map(|rd| {
            rd.flatten()
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default()
}

/// `err` is the typed refusal of a `resource` limit.
fn assert_limit(err: &Error, resource: Resource) {
    assert!(
        matches!(err, Error::Limit { resource: r, .. } if *r == resource),
        "{err}"
    );
}

/// A damage done to a complete store of the 2 × 2 grid, and what the repairing fetch must
/// report: (tiles set aside, tiles downloaded).
type Damage = fn(&EdgeStore) -> (usize, usize);

fn flip(store: &EdgeStore) -> (usize, usize) {
    let p = shard_path(store, 0);
    let mut v = std::fs::read(&p).unwrap();
    let mid = v.len() / 2;
    v[mid] ^= 0x10;
    std::fs::write(&p, v).unwrap();
    (1, 1)
}

fn truncate(store: &EdgeStore) -> (usize, usize) {
    let p = shard_path(store, 1);
    let v = std::fs::read(&p).unwrap();
    std::fs::write(&p, &v[..v.len() - 100]).unwrap();
    (1, 1)
}

fn append(store: &EdgeStore) -> (usize, usize) {
    use std::io::Write;
    let p = shard_path(store, 2);
    let mut f = std::fs::OpenOptions::new().append(true).open(&p).unwrap();
    f.write_all(b"appended").unwrap();
    (1, 1)
}

fn swap(store: &EdgeStore) -> (usize, usize) {
    // Tiles 1 and 3 carry no display sections: the same length, only their content differs.
    let (a, b) = (shard_path(store, 1), shard_path(store, 3));
    let (va, vb) = (std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
    assert_eq!(va.len(), vb.len());
    std::fs::write(&a, vb).unwrap();
    std::fs::write(&b, va).unwrap();
    (2, 2)
}

fn foreign(store: &EdgeStore) -> (usize, usize) {
    // The same tile of another scene of the same size and shape: only the header's scene id
    // (and so the checksum) tells it apart.
    let other = grid_scene("gri2", 2, 2, 25, 8, Dtype::F16, 1);
    std::fs::write(shard_path(store, 3), &other.shards[&3]).unwrap();
    (1, 1)
}

fn directory(store: &EdgeStore) -> (usize, usize) {
    let p = shard_path(store, 0);
    std::fs::remove_file(&p).unwrap();
    std::fs::create_dir_all(p.join("inside")).unwrap();
    std::fs::write(p.join("inside").join("f"), b"x").unwrap();
    // Loading does not fail on it: the folder is reported like a corrupted shard.
    let (_, rejected) = answers(store);
    assert_eq!(rejected.len(), 1, "{rejected:?}");
    (1, 1)
}

fn stale_partial(store: &EdgeStore) -> (usize, usize) {
    // Tile 2's file is gone and a partial download of it of full length holds garbage: it is
    // verified, discarded and downloaded again.
    let m = store.manifest("grid").unwrap().unwrap();
    let t = m.tiles.iter().find(|t| t.id == 2).unwrap();
    std::fs::remove_file(store.shard_path("grid", t).unwrap()).unwrap();
    std::fs::write(store.partial_path("grid", t), vec![0xab; t.bytes as usize]).unwrap();
    // Tile 1's partial path is a folder: set aside.
    let t1 = m.tiles.iter().find(|t| t.id == 1).unwrap();
    std::fs::remove_file(store.shard_path("grid", t1).unwrap()).unwrap();
    std::fs::create_dir_all(store.partial_path("grid", t1)).unwrap();
    (0, 2)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_damage_is_repaired_by_one_fetch_and_the_answers_equal_the_reference() {
    let server = shard_server(grid_scene("grid", 2, 2, 25, 8, Dtype::F16, 1), None).await;
    let cases: [(&str, Damage); 7] = [
        ("flip", flip),
        ("truncate", truncate),
        ("append", append),
        ("swap", swap),
        ("foreign", foreign),
        ("directory", directory),
        ("stale partial", stale_partial),
    ];
    let mut reference = None;
    for (prune, (name, damage)) in [false, true]
        .into_iter()
        .flat_map(|p| cases.map(|c| (p, c)))
    {
        let (dir, store) = temp_store();
        let first = fetch(&store, &params(&server.url)).await.unwrap();
        assert_eq!(first.downloaded, 4);
        let (want, rejected) = answers(&store);
        assert!(rejected.is_empty());
        let reference = reference.get_or_insert(want.clone());
        assert_eq!(&want, reference);
        assert!(want.iter().all(|a| a.as_array().unwrap().len() == 100));

        let (set_aside, downloaded) = damage(&store);
        let mut p = params(&server.url);
        p.prune = prune;
        let s: FetchSummary = fetch(&store, &p).await.unwrap();
        assert_eq!(
            (s.set_aside, s.downloaded, s.skipped),
            (set_aside, downloaded, 4 - downloaded),
            "{name} (prune {prune}): {s}"
        );
        let (got, rejected) = answers(&store);
        assert!(rejected.is_empty(), "{name}: {rejected:?}");
        assert_eq!(&got, reference, "{name} (prune {prune})");
        // What was set aside is kept, not deleted; the partial folder is empty.
        let q = quarantined(dir.path());
        let expect_q = set_aside + usize::from(name == "stale partial");
        assert_eq!(q.len(), expect_q, "{name}: {q:?}");
        assert_eq!(partial_files(dir.path()), 0);
        // A second fetch finds everything verified.
        let again = fetch(&store, &p).await.unwrap();
        assert_eq!(
            (again.set_aside, again.downloaded, again.skipped),
            (0, 0, 4),
            "{name}"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_manifest_declaring_sizes_the_format_does_not_allow_is_refused_before_any_write() {
    let mut scene = grid_scene("grid", 2, 1, 10, 8, Dtype::F16, 1);
    scene.manifest.tiles[1].bytes = 1_000_000_000_000;
    let server = shard_server(scene, None).await;
    let (dir, store) = temp_store();
    let err = fetch(&store, &params(&server.url)).await.unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, Error::Format { .. }), "{msg}");
    assert!(
        msg.contains("tile 1") && msg.contains("1000000000000 bytes"),
        "{msg}"
    );
    assert_eq!(server.state.requests.load(Ordering::SeqCst), 0);
    assert_eq!(partial_files(dir.path()), 0);
    assert!(store.manifest("grid").unwrap().is_none());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_download_larger_than_the_free_disk_space_is_refused_naming_the_folder() {
    // Sizes the format allows, but 2^32 - 1 rows of 65536 f32 (a petabyte): no disk holds it.
    let mut scene = grid_scene("grid", 1, 1, 10, 8, Dtype::F16, 1);
    let layout = ShardLayout {
        dtype: Dtype::F32,
        dim: 65536,
        scales: false,
        opacities: false,
        rotations: false,
        sh_dc: false,
        segments: false,
        scene_id_len: 4,
        model_len: "color-clip".len(),
    };
    scene.manifest.dim = 65536;
    scene.manifest.dtype = Dtype::F32;
    let t: &mut TileInfo = &mut scene.manifest.tiles[0];
    t.count = u32::MAX as u64;
    t.bytes = layout.shard_len(t.count);
    scene.manifest.total_gaussians = u32::MAX as u64;
    let server = shard_server(scene, None).await;
    let (dir, store) = temp_store();
    let err = fetch(&store, &params(&server.url)).await.unwrap_err();
    let msg = err.to_string();
    assert_limit(&err, Resource::DiskSpace);
    assert!(
        msg.contains(&dir.path().join("partial").display().to_string()),
        "{msg}"
    );
    assert_eq!(server.state.requests.load(Ordering::SeqCst), 0);
    assert_eq!(partial_files(dir.path()), 0);
}

/// Serves `GET /v1/scenes/grid/manifest` as 200 MB of JSON whitespace, with or without a
/// `Content-Length`; returns the base URL and a count of the bytes the server handed over.
async fn huge_manifest_server(
    content_length: bool,
) -> (String, std::sync::Arc<std::sync::atomic::AtomicU64>) {
    use axum::body::{Body, Bytes};
    let sent = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
    let counter = sent.clone();
    let app = axum::Router::new().route(
        "/v1/scenes/grid/manifest",
        axum::routing::get(move || {
            let counter = counter.clone();
            async move {
                let chunk = Bytes::from(vec![b' '; 1 << 20]);
                let stream = futures_util::stream::iter((0..200).map(move |_| {
                    counter.fetch_add(chunk.len() as u64, Ordering::SeqCst);
                    Ok::<_, std::io::Error>(chunk.clone())
                }));
                let mut r = axum::response::Response::builder();
                if content_length {
                    r = r.header("content-length", 200u64 << 20);
                }
                r.body(Body::from_stream(stream)).unwrap()
            }
        }),
    );
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    tokio::spawn(async move { axum::serve(listener, app).await.unwrap() });
    (url, sent)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_200_mb_manifest_is_refused_without_reading_it_whole() {
    for content_length in [true, false] {
        let (url, sent) = huge_manifest_server(content_length).await;
        let (_dir, store) = temp_store();
        let err = fetch(&store, &params(&url)).await.unwrap_err();
        let msg = err.to_string();
        assert_limit(&err, Resource::ManifestBytes);
        assert!(msg.contains(&MAX_MANIFEST_BYTES.to_string()), "{msg}");
        // The reader stopped at the cap (the server may have queued a few more chunks).
        if !content_length {
            assert!(
                sent.load(Ordering::SeqCst) < 100 << 20,
                "{} bytes sent",
                sent.load(Ordering::SeqCst)
            );
        }
    }
}

/// `slag-edge` (through `$SLAG_TEST_RUNNER` when set), not yet started.
fn slag_edge(args: &[&str]) -> Command {
    slag_edge_with_log(args, "warn")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_mid_download_removes_the_partial_files_and_a_rerun_completes() {
    let server = shard_server(grid_scene("grid", 2, 2, 200, 16, Dtype::F32, 1), None).await;
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let s = store.display().to_string();
    let fetch = support::fetch_args(&server.url, &s, "100");
    let args = [&fetch[..], &["--jobs", "2", "--retries", "0", "--json"]].concat();
    let mut cmd = slag_edge(&args);
    cmd.env("SLAG_FAULT_ENOSPC_AT", "3");
    let out = output_blocking(cmd).await;
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(err.contains("No space left on device"), "{err}");
    assert_eq!(partial_files(&store), 0, "{err}");
    {
        let edge = EdgeStore::open(&store).unwrap();
        assert!(edge.manifest("grid").unwrap().is_none());
    }
    let summary = success_json(&output_blocking(slag_edge(&args)).await);
    assert_eq!(summary["selected"], 4);
    assert_eq!(
        summary["downloaded"].as_u64().unwrap() + summary["skipped"].as_u64().unwrap(),
        4
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_damaged_database_is_rebuilt_from_the_manifest_copies() {
    let server = shard_server(grid_scene("grid", 2, 2, 25, 8, Dtype::F16, 1), None).await;
    // Garbage over every database file, or over its data file only (a bad flash block).
    for only_data in [false, true] {
        let dir = tempfile::tempdir().unwrap();
        let (want, manifest) = {
            let store = EdgeStore::open(dir.path()).unwrap();
            fetch(&store, &params(&server.url)).await.unwrap();
            (answers(&store).0, store.manifest("grid").unwrap().unwrap())
        };
        support::damage_db(dir.path(), only_data);
        let store = open_after_drop(dir.path());
        assert_eq!(store.manifest("grid").unwrap().as_ref(), Some(&manifest));
        assert!(store.fetch_record("grid").unwrap().is_some());
        let (got, rejected) = answers(&store);
        assert!(rejected.is_empty());
        assert_eq!(got, want);
        // sled refuses garbage in its config file (set aside) but drops a garbage data file
        // and opens empty (refilled in place).
        assert_eq!(
            quarantined(dir.path()).iter().any(|n| n.ends_with("-db")),
            !only_data,
            "{:?}",
            quarantined(dir.path())
        );
        // And a fetch finds every shard verified.
        let s = fetch(&store, &params(&server.url)).await.unwrap();
        assert_eq!((s.skipped, s.downloaded), (4, 0));
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn post_fetch_sends_the_configured_shard_token() {
    let server = shard_server(
        grid_scene("grid", 2, 2, 25, 8, Dtype::F16, 1),
        Some("s3cret".into()),
    )
    .await;
    for configured in [Some("s3cret"), None] {
        let (_dir, store) = temp_store();
        let mut p = params(&server.url);
        p.token = Some("s3cret".into());
        p.radius = 5.0;
        fetch(&store, &p).await.unwrap();
        let state = slag_edge::serve::AppState::new(
            store,
            std::sync::Arc::new(BasisEmbedder::new(8)),
            slag_edge::serve::ServeOptions {
                shard_token: configured.map(str::to_string),
                ..slag_edge::serve::ServeOptions::new("grid")
            },
        )
        .unwrap();
        let url = serve_on_loopback(state).await;
        let r = reqwest::Client::new()
            .post(format!("{url}/fetch"))
            .json(&serde_json::json!({"center": [0.0, 0.0], "radius": 100.0}))
            .send()
            .await
            .unwrap();
        let status = r.status().as_u16();
        let body: serde_json::Value = r.json().await.unwrap();
        match configured {
            Some(_) => {
                assert_eq!(status, 200, "{body}");
                assert_eq!(body["selected"], 4, "{body}");
            }
            None => {
                assert_eq!(status, 502, "{body}");
                let e = body["error"].as_str().unwrap();
                assert!(e.contains("401") && e.contains("SLAG_SHARD_TOKEN"), "{e}");
            }
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn check_fails_naming_missing_corrupt_and_zero_shards() {
    let Some((server, [tm, tok])) = support::clip_grid_server().await else {
        return;
    };
    let check = |store: &Path| {
        let s = store.display().to_string();
        slag_edge(&text_model_args("check", &s, "grid", [&tm, &tok]))
    };
    /// (name, damage, what the problems must name; none: ok).
    type Case = (&'static str, fn(&EdgeStore), &'static [&'static str]);
    let damages: [Case; 4] = [
        ("none", |_| {}, &[]),
        (
            "all deleted",
            |s| {
                for t in 0..4 {
                    std::fs::remove_file(shard_path(s, t)).unwrap();
                }
            },
            &["shard 0 ", "shard 3 ", "no Gaussians"],
        ),
        (
            "one missing",
            |s| std::fs::remove_file(shard_path(s, 2)).unwrap(),
            &["shard 2 of the fetched disc is missing"],
        ),
        (
            "one corrupt",
            |s| {
                let p = shard_path(s, 1);
                let mut v = std::fs::read(&p).unwrap();
                let n = v.len();
                v[n - 10] ^= 1;
                std::fs::write(&p, v).unwrap();
            },
            &["corrupt shard", "shard 1 of scene grid"],
        ),
    ];
    for (name, damage, expect) in damages {
        let dir = tempfile::tempdir().unwrap();
        {
            let store = EdgeStore::open(dir.path()).unwrap();
            fetch(&store, &params(&server.url)).await.unwrap();
            damage(&store);
        }
        let out = output_blocking(check(dir.path())).await;
        let report: serde_json::Value = serde_json::from_slice(&out.stdout)
            .unwrap_or_else(|e| panic!("{name}: {e}: {}", String::from_utf8_lossy(&out.stderr)));
        let problems: Vec<String> = serde_json::from_value(report["problems"].clone()).unwrap();
        assert_eq!(report["ok"], expect.is_empty(), "{name}: {report}");
        assert_eq!(out.status.success(), expect.is_empty(), "{name}: {report}");
        for e in expect {
            assert!(
                problems.iter().any(|p| p.contains(e)),
                "{name}: {e:?} in {problems:?}"
            );
        }
        if name == "all deleted" {
            assert_eq!(report["gaussians"], 0);
            assert_eq!(problems.len(), 5, "{problems:?}");
        }
    }
}
