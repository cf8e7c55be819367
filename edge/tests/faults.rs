//! Faults on the robot side: `slag-edge fetch` killed at every durability boundary
//! (`SLAG_FAULT_EXIT_AT`) and by SIGKILL mid-download, stalled downloads with a timeout, shards
//! with a future format version, shards corrupted in the store, hostile ids and checksums.
//! Under qemu (cross build) the binary is started through `$SLAG_TEST_RUNNER`.
#![allow(clippy::unwrap_used)]

mod support;

use std::path::Path;
use std::process::{Command, Stdio};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use slag_common::Error;
use slag_common::shards::{Dtype, Manifest, TileInfo, shard_checksum};
use slag_edge::fetch::{FAULT_EXIT_STATUS, FetchParams, fetch};
use slag_edge::store::{EdgeStore, verify_shard};
use support::{
    BasisEmbedder, assert_success, fetch_grid, grid_fetch_params, grid_scene, output_blocking,
    partial_files, send_json, serve_on_loopback, shard_server, slag_edge_with_log, temp_store,
};

fn params(url: &str, radius: f64) -> FetchParams {
    FetchParams {
        jobs: 1,
        ..grid_fetch_params(url, radius)
    }
}

/// `slag-edge` (through `$SLAG_TEST_RUNNER` when set), not yet started.
fn slag_edge(args: &[&str]) -> Command {
    slag_edge_with_log(args, "error")
}

/// The whole grid, one job, no retries, the summary as JSON.
fn fetch_args<'a>(url: &'a str, store: &'a str) -> Vec<&'a str> {
    let one_try = ["--jobs", "1", "--retries", "0", "--json"];
    [support::fetch_args(url, store, "100"), one_try.to_vec()].concat()
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &to.join(e.file_name()));
        } else {
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
}

/// The store after a kill: it opens; what a reader sees is one complete verified generation (or
/// nothing); every stored shard of a known manifest verifies.
fn assert_consistent(dir: &Path, manifests: &[&Manifest], n: u64) {
    let store = EdgeStore::open(dir).unwrap();
    match store.load_scene("grid") {
        Err(e @ Error::Param { name: "scene", .. }) => {
            assert!(e.to_string().contains("no completed fetch"), "n={n}: {e}")
        }
        Err(e) => panic!("n={n}: {e}"),
        Ok((m, shards, load)) => {
            assert!(manifests.contains(&&m), "n={n}: unknown manifest");
            assert!(load.rejected.is_empty(), "n={n}: {:?}", load.rejected);
            assert_eq!(
                load.absent_tiles, 0,
                "n={n}: a generation is visible half done"
            );
            assert_eq!(shards.len(), m.tiles.len(), "n={n}");
        }
    }
    for (tile, checksum, _) in store.stored_shards("grid").unwrap() {
        let (m, t) = manifests
            .iter()
            .find_map(|m| {
                m.tiles
                    .iter()
                    .find(|t| t.id == tile && t.checksum == format!("{checksum:08x}"))
                    .map(|t| (*m, t))
            })
            .unwrap_or_else(|| panic!("n={n}: stored shard {tile} {checksum:08x} is unknown"));
        let bytes = store.shard_bytes("grid", t).unwrap().unwrap();
        verify_shard(m, t, &bytes).unwrap_or_else(|e| panic!("n={n}: {e}"));
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fetch_killed_at_every_durability_boundary_leaves_a_consistent_store_and_reruns() {
    // Generation 1 fully stored; the server moves to generation 2 and the fetch of it is killed
    // at boundary n = 1, 2, … until a run completes without reaching n.
    let g1 = grid_scene("grid", 2, 2, 30, 8, Dtype::F16, 1);
    let g2 = grid_scene("grid", 2, 2, 31, 8, Dtype::F16, 2);
    let (m1, m2) = (g1.manifest.clone(), g2.manifest.clone());
    let s1 = shard_server(g1, None).await;
    let s2 = shard_server(g2, None).await;
    let tmp = tempfile::tempdir().unwrap();
    let template = tmp.path().join("template");
    {
        let store = EdgeStore::open(&template).unwrap();
        fetch(&store, &params(&s1.url, 100.0)).await.unwrap();
    }
    let mut n = 0u64;
    loop {
        n += 1;
        assert!(n < 200, "the fetch never completed");
        let dir = tmp.path().join(format!("run{n}"));
        copy_dir(&template, &dir);
        let store_s = dir.display().to_string();
        let url = s2.url.clone();
        let mut killed_at_n = slag_edge(&fetch_args(&url, &store_s));
        killed_at_n.env("SLAG_FAULT_EXIT_AT", n.to_string());
        let out = output_blocking(killed_at_n).await;
        if out.status.success() {
            break;
        }
        assert_eq!(
            out.status.code(),
            Some(FAULT_EXIT_STATUS),
            "n={n}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let d = dir.clone();
        let (a, b) = (m1.clone(), m2.clone());
        tokio::task::spawn_blocking(move || assert_consistent(&d, &[&a, &b], n))
            .await
            .unwrap();
        // A plain rerun completes with every tile of generation 2.
        let url = s2.url.clone();
        let out = output_blocking(slag_edge(&fetch_args(&url, &store_s))).await;
        assert_success(&out, &format!("n={n}"));
        let store = EdgeStore::open(&dir).unwrap();
        let (m, shards, load) = store.load_scene("grid").unwrap();
        assert_eq!(m, m2, "n={n}");
        assert_eq!((shards.len(), load.rejected.len()), (4, 0), "n={n}");
        assert_eq!(store.stored_shards("grid").unwrap().len(), 4, "n={n}");
        assert_eq!(partial_files(&dir), 0);
    }
    // Four tiles: at least one write, one sync and one commit each, plus the two manifest
    // boundaries, were each hit by a kill.
    assert!(n > 4 * 3 + 2, "only {} boundaries", n - 1);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigkill_mid_download_then_a_rerun_resumes_with_a_range_request() {
    let scene = grid_scene("grid", 1, 1, 400, 16, Dtype::F32, 1);
    let len = scene.shards[&0].len();
    let server = shard_server(scene, None).await;
    *server.state.slow.lock().unwrap() = Some((len / 40, Duration::from_millis(40)));
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("store");
    let store_s = dir.display().to_string();
    let mut child = slag_edge(&fetch_args(&server.url, &store_s))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let part = dir.join("partial");
    let t0 = Instant::now();
    let have = loop {
        let n = std::fs::read_dir(&part)
            .map(|rd| {
                rd.flatten()
                    .filter_map(|e| e.metadata().ok())
                    .map(|m| m.len())
                    .sum()
            })
            .unwrap_or(0u64);
        if n > 0 {
            break n;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(8),
            "no partial file appeared"
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    };
    child.kill().unwrap();
    child.wait().unwrap();
    assert!((have as usize) < len, "{have} of {len}");
    *server.state.slow.lock().unwrap() = None;

    let store = EdgeStore::open(&dir).unwrap();
    assert!(store.manifest("grid").unwrap().is_none());
    assert!(store.stored_shards("grid").unwrap().is_empty());
    let s = fetch(&store, &params(&server.url, 100.0)).await.unwrap();
    assert_eq!((s.downloaded, s.resumed), (1, 1));
    assert!(
        s.bytes_received < len as u64,
        "{} of {len}",
        s.bytes_received
    );
    assert_eq!(server.state.range_requests.load(Ordering::SeqCst), 1);
    let (_, shards, load) = store.load_scene("grid").unwrap();
    assert_eq!((shards.len(), load.rejected.len()), (1, 0));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stalled_download_times_out_with_the_url_and_resumes() {
    let scene = grid_scene("grid", 1, 1, 300, 16, Dtype::F32, 1);
    let len = scene.shards[&0].len();
    let server = shard_server(scene, None).await;
    server.state.stall.lock().unwrap().insert(0, len / 2);
    let (_dir, store) = temp_store();
    let mut p = params(&server.url, 100.0);
    p.timeout = Duration::from_secs(1);
    let err = fetch(&store, &p).await.unwrap_err();
    match &err {
        Error::Network { url, message, .. } => {
            assert!(url.ends_with("/v1/scenes/grid/shards/0"), "{url}");
            assert!(
                message.contains("timed out") && message.contains("timeout"),
                "{message}"
            );
        }
        e => panic!("expected a network error, got {e}"),
    }
    assert!(store.manifest("grid").unwrap().is_none());
    server.state.stall.lock().unwrap().clear();
    let s = fetch(&store, &p).await.unwrap();
    assert_eq!((s.downloaded, s.resumed), (1, 1));
    assert_eq!(s.bytes_received as usize, len - len / 2);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_shard_of_a_future_format_version_is_refused_naming_the_version() {
    let mut scene = grid_scene("grid", 2, 1, 20, 8, Dtype::F16, 1);
    // Format version is the u16 at byte 8 (little-endian); the manifest matches the new bytes,
    // so only the version can be wrong.
    let b = scene.shards.get_mut(&1).unwrap();
    let v = u16::from_le_bytes([b[8], b[9]]) + 1;
    b[8..10].copy_from_slice(&v.to_le_bytes());
    let sum = format!("{:08x}", shard_checksum(b));
    scene
        .manifest
        .tiles
        .iter_mut()
        .find(|t| t.id == 1)
        .unwrap()
        .checksum = sum;
    let server = shard_server(scene, None).await;
    let (_dir, store) = temp_store();
    let err = fetch(&store, &params(&server.url, 100.0))
        .await
        .unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, Error::Unsupported { .. }), "{msg}");
    assert!(
        msg.contains(&format!("version {v}")) && msg.contains("upgrade"),
        "{msg}"
    );
    assert!(store.manifest("grid").unwrap().is_none());
    // Refused once: a version mismatch is not corruption, so it is not downloaded twice.
    assert_eq!(server.state.requests.load(Ordering::SeqCst), 2);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_shard_corrupted_in_the_store_is_not_served_and_is_reported() {
    let scene = grid_scene("grid", 2, 2, 25, 8, Dtype::F32, 1);
    let server = shard_server(scene, None).await;
    let (_dir, store) = fetch_grid(&server.url, 100.0).await;
    // Flip one byte of one stored shard behind the store's back (bit rot, a bad flash block).
    {
        let m = store.manifest("grid").unwrap().unwrap();
        let path = store.shard_path("grid", &m.tiles[0]).unwrap();
        let mut v = std::fs::read(&path).unwrap();
        let mid = v.len() / 2;
        v[mid] ^= 0x40;
        std::fs::write(&path, v).unwrap();
    }
    let state = slag_edge::serve::AppState::new(
        store,
        std::sync::Arc::new(BasisEmbedder::new(8)),
        slag_edge::serve::ServeOptions {
            request_timeout: Duration::from_secs(10),
            ..slag_edge::serve::ServeOptions::new("grid")
        },
    )
    .unwrap();
    let url = serve_on_loopback(state).await;
    let (_, stats) = send_json(reqwest::Client::new().get(format!("{url}/stats"))).await;
    let rejected = stats["shards_rejected"].as_array().unwrap();
    assert_eq!(rejected.len(), 1, "{stats}");
    let msg = rejected[0].as_str().unwrap();
    assert!(msg.contains("checksum") && msg.contains("shard"), "{msg}");
    assert_eq!(stats["shards_loaded"], 3);
    assert_eq!(
        stats["gaussians"], 75,
        "the corrupted tile's 25 Gaussians are not served"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hostile_ids_and_checksums_never_leave_the_partial_folder() {
    let (dir, store) = temp_store();
    let partial = dir.path().join("partial");
    for (scene, checksum) in [
        ("../../etc", "0000abcd"),
        ("grid", "../../../../tmp/x"),
        ("a/b\0c", "/abs/path"),
        ("..", ".."),
        ("grid", "0000ABCD"),
    ] {
        let t = TileInfo {
            id: 3,
            footprint: TileInfo::rect_ring([0.0, 0.0], [1.0, 1.0]),
            aabb: slag_common::shards::Aabb::of_points([[0.0f32; 3]]).unwrap(),
            count: 1,
            bytes: 1,
            checksum: checksum.into(),
        };
        let p = store.partial_path(scene, &t);
        assert_eq!(p.parent(), Some(partial.as_path()), "{p:?}");
        let name = p.file_name().unwrap().to_str().unwrap();
        assert!(
            name.ends_with(".part")
                && !name.contains('/')
                && !name.contains("..")
                && !name.contains('\0'),
            "{name}"
        );
    }
    // A manifest whose checksum is a path is refused before anything is written.
    let mut scene = grid_scene("grid", 1, 1, 5, 8, Dtype::F32, 1);
    scene.manifest.tiles[0].checksum = "../../../../tmp/slag-escape".into();
    let server = shard_server(scene, None).await;
    let err = fetch(&store, &params(&server.url, 100.0))
        .await
        .unwrap_err();
    assert!(
        matches!(err, Error::Format { .. }) && err.to_string().contains("checksum"),
        "{err}"
    );
    assert_eq!(server.state.requests.load(Ordering::SeqCst), 0);
    assert_eq!(std::fs::read_dir(&partial).unwrap().count(), 0);
}

#[test]
fn a_store_of_an_older_slag_edge_is_refused_with_a_typed_error_saying_to_fetch_again() {
    // Older slag-edge kept shard bytes in the sled tree `shards` (key scene \0 tile checksum).
    let dir = tempfile::tempdir().unwrap();
    {
        let db = sled::open(dir.path().join("db")).unwrap();
        let shards = db.open_tree("shards").unwrap();
        let scene = grid_scene("grid", 1, 1, 5, 8, Dtype::F32, 1);
        let mut key = b"grid\0".to_vec();
        key.extend_from_slice(&0u64.to_be_bytes());
        key.extend_from_slice(&shard_checksum(&scene.shards[&0]).to_be_bytes());
        shards.insert(key, scene.shards[&0].as_slice()).unwrap();
        db.flush().unwrap();
    }
    // sled's flusher thread of the dropped database can hold the file lock a moment longer on a
    // loaded machine (the lock error is right for a store in use): wait for it to let go.
    let t0 = std::time::Instant::now();
    let err = loop {
        match EdgeStore::open(dir.path()) {
            Err(e)
                if e.to_string().contains("could not acquire lock")
                    && t0.elapsed() < std::time::Duration::from_secs(20) =>
            {
                std::thread::sleep(std::time::Duration::from_millis(50));
            }
            other => break other.unwrap_err(),
        }
    };
    let msg = err.to_string();
    assert!(matches!(err, Error::Unsupported { .. }), "{msg}");
    assert!(
        msg.contains("older slag-edge") && msg.contains("slag-edge fetch"),
        "{msg}"
    );
    // An empty tree of that name (nothing to lose) is dropped and the store opens.
    {
        let db = sled::open(dir.path().join("db")).unwrap();
        db.open_tree("shards").unwrap().clear().unwrap();
        db.flush().unwrap();
    }
    let store = EdgeStore::open(dir.path()).unwrap();
    assert!(store.manifest("grid").unwrap().is_none());
}
