//! Faults on the robot side: `slag-edge fetch` killed by SIGKILL mid-download, stalled downloads
//! with a timeout, shards with a future format version, shards corrupted in the store, hostile
//! ids and checksums. A fetch stopped at every durability boundary in turn is
//! `crash_points.rs`.
//! Under qemu (cross build) the binary is started through `$SLAG_TEST_RUNNER`.
#![allow(clippy::unwrap_used)]

mod support;

use std::process::{Command, Stdio};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use slag_common::Error;
use slag_common::shards::{Dtype, TileInfo, shard_checksum};
use slag_edge::fetch::{FetchParams, fetch};
use slag_edge::store::EdgeStore;
use support::{
    BasisEmbedder, fetch_grid, grid_fetch_params, grid_scene, send_json, serve_on_loopback,
    shard_server, slag_edge_with_log, temp_store,
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
            sha256: None,
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
