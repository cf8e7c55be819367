//! The store's integrity rules: a manifest must be a set (no tile listed twice, counts that add
//! up), refused before anything is stored, on fetch and on load (`POST /fetch` of such a
//! manifest, or of one in another format, answers 502); the store reads only regular
//! files: a FIFO, a symbolic link (to `/dev/zero`, dangling, or to a valid shard outside the
//! store) or a longer file in a shard's place is reported at once, never followed or read past
//! the manifest's length, and one fetch replaces it with the real shard; a database folder
//! holding a link or FIFO is set aside and rebuilt; `slag-edge check` names each of them.
#![allow(clippy::unwrap_used)]

mod support;

use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use slag_common::Error;
use slag_common::shards::{Dtype, ShardError};
use slag_edge::engine::Engine;
use slag_edge::fetch::fetch;
use slag_edge::store::{EdgeStore, FetchRecord, Stored};
use support::{
    BasisEmbedder, error_message, grid_fetch_params, grid_scene, grid_serve_options,
    open_after_drop, output_blocking, send_json, serve_store, shard_path, shard_server,
    slag_edge_with_log, temp_store, text_model_args,
};

/// `err` is the refusal of a manifest that is not a set.
fn assert_not_a_set(err: &Error, what: &str) {
    assert!(
        matches!(err, Error::Shard(ShardError::ManifestNotASet(_))),
        "{what}: {err}"
    );
}

/// Loads the scene on a blocking thread, failing (instead of hanging) after 20 s.
async fn load(store: &EdgeStore) -> slag_common::Result<Engine> {
    let store = store.clone();
    let task = tokio::task::spawn_blocking(move || Engine::load(&store, "grid", false));
    tokio::time::timeout(Duration::from_secs(20), task)
        .await
        .expect("loading the store hung")
        .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_manifest_that_is_not_a_set_is_refused_before_anything_is_stored() {
    let server = shard_server(grid_scene("grid", 2, 2, 25, 8, Dtype::F16, 1), None).await;
    let good = server.state.scene.read().unwrap().manifest.clone();
    let mut twice = good.clone();
    twice.tiles.push(good.tiles[0].clone());
    let mut twice_adding_up = twice.clone();
    twice_adding_up.total_gaussians += good.tiles[0].count;
    let mut total = good.clone();
    total.total_gaussians += 1;
    for (name, doctored) in [
        ("a tile twice", &twice),
        ("a tile twice, the total adjusted", &twice_adding_up),
        ("counts that do not add up", &total),
    ] {
        server.state.scene.write().unwrap().manifest = doctored.clone();
        for jobs in [1, 4] {
            let (dir, store) = temp_store();
            let mut p = grid_fetch_params(&server.url, 100.0);
            p.jobs = jobs;
            let err = fetch(&store, &p).await.unwrap_err();
            assert_not_a_set(&err, name);
            assert!(err.to_string().contains("re-partition"), "{err}");
            assert!(store.manifest("grid").unwrap().is_none(), "{name}");
            assert!(store.stored_shards("grid").unwrap().is_empty(), "{name}");
            assert_eq!(support::partial_files(dir.path()), 0, "{name}");
        }
    }
    // A store whose stored manifest lists a tile twice (written by an older slag-edge, or
    // damaged) is refused when loaded, not served double.
    server.state.scene.write().unwrap().manifest = good;
    let (_dir, store) = temp_store();
    fetch(&store, &grid_fetch_params(&server.url, 100.0))
        .await
        .unwrap();
    let record = store.fetch_record("grid").unwrap().unwrap();
    {
        let _g = store.lock_generation();
        store
            .commit_fetch(
                &twice_adding_up,
                &FetchRecord {
                    tiles: None,
                    kept: None,
                    ..record
                },
            )
            .unwrap();
    }
    let err = load(&store).await.err().unwrap();
    assert!(
        matches!(&err, Error::Shard(ShardError::ManifestNotASet(m)) if m.contains("listed twice")),
        "{err}"
    );
}

/// `POST /fetch` from a shard server whose manifest cannot be used (not a set of tiles, or of
/// another format) is the shard server's fault: 502, saying that its manifest is bad; the scene
/// fetched before keeps answering.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn post_fetch_of_a_bad_manifest_is_502_naming_the_shard_servers_manifest() {
    let server = shard_server(grid_scene("grid", 2, 2, 25, 8, Dtype::F16, 1), None).await;
    let (_dir, store) = temp_store();
    fetch(&store, &grid_fetch_params(&server.url, 100.0))
        .await
        .unwrap();
    let url = serve_store(
        store,
        Arc::new(BasisEmbedder::new(8)),
        grid_serve_options(None, false),
    )
    .await;
    let good = server.state.scene.read().unwrap().manifest.clone();
    let mut twice = good.clone();
    twice.tiles.push(good.tiles[0].clone());
    let mut foreign = good.clone();
    foreign.format = "not-a-slag-manifest".into();
    let client = reqwest::Client::new();
    for (name, doctored, cause) in [
        ("a tile twice", twice, "not a set of tiles"),
        ("another format", foreign, "not-a-slag-manifest"),
    ] {
        server.state.scene.write().unwrap().manifest = doctored;
        let (status, v) = send_json(
            client
                .post(format!("{url}/fetch"))
                .json(&serde_json::json!({"center": [0.0, 0.0], "radius": 100.0})),
        )
        .await;
        assert_eq!(
            (status, &v["status"]),
            (502, &serde_json::json!(502)),
            "{name}: {v}"
        );
        let m = error_message(&v);
        assert!(
            m.contains("shard server's manifest is bad") && m.contains(cause),
            "{name}: {m}"
        );
        let (status, v) = send_json(client.get(format!("{url}/query?text=t0"))).await;
        assert_eq!(status, 200, "{name}: {v}");
    }
}

/// A thing put in place of tile 0's shard file: its name, and how it is made at `path`
/// (`outside`: a folder outside the store holding a verified copy of the shard).
type Replacement = (&'static str, fn(&Path, &Path));

fn replacements() -> [Replacement; 5] {
    fn fifo(p: &Path, _: &Path) {
        std::fs::remove_file(p).unwrap();
        let s = std::process::Command::new("mkfifo")
            .arg(p)
            .status()
            .unwrap();
        assert!(s.success());
    }
    fn zero(p: &Path, _: &Path) {
        std::fs::remove_file(p).unwrap();
        std::os::unix::fs::symlink("/dev/zero", p).unwrap();
    }
    fn dangling(p: &Path, outside: &Path) {
        std::fs::remove_file(p).unwrap();
        std::os::unix::fs::symlink(outside.join("gone.shard"), p).unwrap();
    }
    fn link_out(p: &Path, outside: &Path) {
        // A verified copy outside the store: its bytes would pass, but the link is not followed.
        let copy = outside.join("copy.shard");
        std::fs::rename(p, &copy).unwrap();
        std::os::unix::fs::symlink(&copy, p).unwrap();
    }
    fn longer(p: &Path, _: &Path) {
        use std::io::Write;
        let mut f = std::fs::OpenOptions::new().append(true).open(p).unwrap();
        f.write_all(&vec![0u8; 1 << 20]).unwrap();
    }
    [
        ("FIFO", fifo),
        ("symbolic link", zero),
        ("symbolic link", dangling),
        ("symbolic link", link_out),
        ("longer than", longer),
    ]
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn what_is_not_a_regular_shard_file_is_reported_never_followed_and_one_fetch_repairs_it() {
    let server = shard_server(grid_scene("grid", 2, 2, 25, 8, Dtype::F16, 1), None).await;
    let original = server.state.scene.read().unwrap().shards[&0].clone();
    for (i, (kind, replace)) in replacements().into_iter().enumerate() {
        let (dir, store) = temp_store();
        let outside = tempfile::tempdir().unwrap();
        fetch(&store, &grid_fetch_params(&server.url, 100.0))
            .await
            .unwrap();
        let path = shard_path(&store, 0);
        replace(&path, outside.path());
        // Loading answers at once: the other three tiles are served, tile 0 is reported.
        let e = load(&store).await.unwrap();
        assert_eq!(e.store.len(), 75, "case {i} ({kind})");
        assert_eq!(e.load.rejected.len(), 1, "case {i}: {:?}", e.load.rejected);
        let why = &e.load.rejected[0];
        assert!(
            why.contains(kind) && why.contains("shard 0 of scene grid"),
            "case {i}: {why}"
        );
        // A fetch finds it damaged without following it, sets it aside and downloads the shard.
        let m = store.manifest("grid").unwrap().unwrap();
        let stored = store.check_stored(&m, &m.tiles[0]).unwrap();
        assert!(
            matches!(&stored, Stored::Damaged { why, .. } if why.contains(kind)),
            "case {i}: {stored:?}"
        );
        let s = fetch(&store, &grid_fetch_params(&server.url, 100.0))
            .await
            .unwrap();
        assert_eq!((s.set_aside, s.downloaded), (1, 1), "case {i}: {s}");
        let meta = std::fs::symlink_metadata(&path).unwrap();
        assert!(meta.is_file(), "case {i}");
        assert_eq!(std::fs::read(&path).unwrap(), original, "case {i}");
        let e = load(&store).await.unwrap();
        assert_eq!((e.store.len(), e.load.rejected.len()), (100, 0), "case {i}");
        let q = std::fs::read_dir(dir.path().join("quarantine"))
            .unwrap()
            .count();
        assert_eq!(q, 1, "case {i}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_database_folder_holding_a_link_or_a_fifo_is_set_aside_and_rebuilt() {
    let server = shard_server(grid_scene("grid", 2, 2, 25, 8, Dtype::F16, 1), None).await;
    for (i, fifo) in [true, false].into_iter().enumerate() {
        let dir = tempfile::tempdir().unwrap();
        {
            let store = EdgeStore::open(dir.path()).unwrap();
            fetch(&store, &grid_fetch_params(&server.url, 100.0))
                .await
                .unwrap();
        }
        let odd = dir.path().join("db").join("snap.odd");
        if fifo {
            let s = std::process::Command::new("mkfifo")
                .arg(&odd)
                .status()
                .unwrap();
            assert!(s.success());
        } else {
            std::os::unix::fs::symlink("/dev/zero", &odd).unwrap();
        }
        let store = tokio::task::spawn_blocking({
            let root = dir.path().to_path_buf();
            move || open_after_drop(&root)
        });
        let store = tokio::time::timeout(Duration::from_secs(30), store)
            .await
            .expect("opening the store hung")
            .unwrap();
        assert!(store.manifest("grid").unwrap().is_some(), "case {i}");
        let e = load(&store).await.unwrap();
        assert_eq!(e.store.len(), 100, "case {i}");
        let q: Vec<String> = std::fs::read_dir(dir.path().join("quarantine"))
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        assert!(q.len() == 1 && q[0].ends_with("-db"), "case {i}: {q:?}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn check_names_every_entry_that_is_not_a_regular_verified_shard_without_hanging() {
    let Some((server, [tm, tok])) = support::clip_grid_server().await else {
        return;
    };
    for (i, (kind, replace)) in replacements().into_iter().enumerate() {
        let dir = tempfile::tempdir().unwrap();
        let outside = tempfile::tempdir().unwrap();
        {
            let store = EdgeStore::open(dir.path()).unwrap();
            fetch(&store, &grid_fetch_params(&server.url, 100.0))
                .await
                .unwrap();
            replace(&shard_path(&store, 0), outside.path());
        }
        let s = dir.path().display().to_string();
        let mut cmd =
            slag_edge_with_log(&text_model_args("check", &s, "grid", [&tm, &tok]), "warn");
        cmd.stdin(std::process::Stdio::null());
        let out = tokio::time::timeout(Duration::from_secs(60), output_blocking(cmd))
            .await
            .expect("check hung");
        let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        let problems: Vec<String> = serde_json::from_value(report["problems"].clone()).unwrap();
        assert!(!out.status.success(), "case {i}: {report}");
        assert_eq!(report["ok"], false, "case {i}");
        assert!(
            problems
                .iter()
                .any(|p| p.contains(kind) && p.contains("shard 0 of scene grid")),
            "case {i} ({kind}): {problems:?}"
        );
    }
}
