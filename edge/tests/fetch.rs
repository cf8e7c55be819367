//! `slag-edge fetch` against an in-process shard server: radius selection, incremental and
//! resumable downloads, verification, generation switches and pruning.
#![allow(clippy::unwrap_used)]

mod support;

use std::sync::atomic::Ordering;

use slag_common::Error;
use slag_common::shards::Dtype;
use slag_edge::fetch::{Center, FetchParams, fetch};
use support::{grid_fetch_params, grid_scene, partial_files, shard_server, stored_ids, temp_store};

fn params(url: &str, center: [f64; 2], radius: f64) -> FetchParams {
    let center = Center::Ground(center);
    FetchParams {
        center,
        jobs: 3,
        ..grid_fetch_params(url, radius)
    }
}

/// Tiles whose square [i*10, i*10+9]² is within `r` of `c` (independent of the R-tree).
fn expected_tiles(c: [f64; 2], r: f64, nx: usize, ny: usize) -> Vec<u64> {
    let mut v = Vec::new();
    for i in 0..nx {
        for j in 0..ny {
            let lo = [i as f64 * 10.0, j as f64 * 10.0];
            let hi = [lo[0] + 9.0, lo[1] + 9.0];
            let dx = (lo[0] - c[0]).max(0.0).max(c[0] - hi[0]);
            let dy = (lo[1] - c[1]).max(0.0).max(c[1] - hi[1]);
            if (dx * dx + dy * dy).sqrt() <= r {
                v.push((i * ny + j) as u64);
            }
        }
    }
    v
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fetch_selects_by_radius_is_incremental_and_prunes_only_when_asked() {
    let scene = grid_scene("grid", 5, 5, 40, 8, Dtype::F16, 1);
    let server = shard_server(scene, None).await;
    let (_dir, store) = temp_store();

    let s1 = fetch(&store, &params(&server.url, [4.0, 4.0], 8.0))
        .await
        .unwrap();
    let want1 = expected_tiles([4.0, 4.0], 8.0, 5, 5);
    assert_eq!(stored_ids(&store), want1);
    assert_eq!(s1.selected, want1.len());
    assert_eq!(s1.downloaded, want1.len());
    assert_eq!(s1.skipped, 0);
    assert_eq!(s1.gaussians, 40 * want1.len() as u64);
    assert_eq!(s1.bytes_received, s1.shard_bytes);
    assert!(store.manifest("grid").unwrap().is_some());
    let rec = store.fetch_record("grid").unwrap().unwrap();
    assert_eq!((rec.center, rec.radius), ([4.0, 4.0], 8.0));

    // Same request again: nothing downloaded.
    let before = server.state.requests.load(Ordering::SeqCst);
    let s2 = fetch(&store, &params(&server.url, [4.0, 4.0], 8.0))
        .await
        .unwrap();
    assert_eq!((s2.downloaded, s2.skipped), (0, want1.len()));
    assert_eq!(server.state.requests.load(Ordering::SeqCst), before);

    // Larger radius: only the new tiles are downloaded.
    let want2 = expected_tiles([4.0, 4.0], 25.0, 5, 5);
    let s3 = fetch(&store, &params(&server.url, [4.0, 4.0], 25.0))
        .await
        .unwrap();
    assert_eq!(s3.downloaded, want2.len() - want1.len());
    assert_eq!(stored_ids(&store), want2);

    // Move away without --prune: old tiles stay; with --prune they go.
    let far = [45.0, 45.0];
    let want3 = expected_tiles(far, 6.0, 5, 5);
    let s4 = fetch(&store, &params(&server.url, far, 6.0)).await.unwrap();
    assert_eq!(s4.evicted, 0);
    let mut union: Vec<u64> = want2.iter().chain(&want3).copied().collect();
    union.sort_unstable();
    union.dedup();
    assert_eq!(stored_ids(&store), union);
    assert_eq!(s4.kept_outside, union.len() - want3.len());
    let mut p = params(&server.url, far, 6.0);
    p.prune = true;
    let s5 = fetch(&store, &p).await.unwrap();
    assert_eq!(stored_ids(&store), want3);
    assert_eq!(s5.evicted, union.len() - want3.len());

    // A world-frame centre (x, y, z) selects like the ground point (x, y) for a z-up scene.
    let mut p = params(&server.url, [0.0, 0.0], 6.0);
    p.center = Center::World([45.0, 45.0, 123.0]);
    p.prune = true;
    fetch(&store, &p).await.unwrap();
    assert_eq!(stored_ids(&store), want3);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn interrupted_download_resumes_with_a_range_request_and_is_never_visible_half_done() {
    let scene = grid_scene("grid", 2, 2, 300, 16, Dtype::F32, 1);
    let tile0_len = scene.shards[&0].len();
    let server = shard_server(scene, None).await;
    server
        .state
        .cut_next
        .lock()
        .unwrap()
        .insert(0, tile0_len / 3);
    let (dir, store) = temp_store();
    let p = params(&server.url, [4.0, 4.0], 1.0); // tile 0 only

    let err = fetch(&store, &p).await.unwrap_err();
    assert!(matches!(err, Error::Network { .. }), "{err}");
    // Not visible: no shard, no manifest; the prefix waits in partial/.
    assert!(stored_ids(&store).is_empty());
    assert!(store.manifest("grid").unwrap().is_none());
    let partial: Vec<_> = std::fs::read_dir(dir.path().join("partial"))
        .unwrap()
        .flatten()
        .collect();
    assert_eq!(partial.len(), 1);
    let have = partial[0].metadata().unwrap().len() as usize;
    assert!(have > 0 && have < tile0_len, "{have} of {tile0_len}");

    let s = fetch(&store, &p).await.unwrap();
    assert_eq!((s.downloaded, s.resumed), (1, 1));
    assert_eq!(s.bytes_received as usize, tile0_len - have);
    assert_eq!(server.state.range_requests.load(Ordering::SeqCst), 1);
    assert_eq!(stored_ids(&store), vec![0]);
    assert_eq!(partial_files(dir.path()), 0);
    let (_, shards, load) = store.load_scene("grid").unwrap();
    assert_eq!(shards.len(), 1);
    assert!(load.rejected.is_empty());

    // With retries, a drop mid-way is retried within the same run.
    server
        .state
        .cut_next
        .lock()
        .unwrap()
        .insert(2, tile0_len / 2);
    let mut p2 = params(&server.url, [14.0, 4.0], 1.0); // tile (1, 0) = id 2
    p2.retries = 2;
    let s = fetch(&store, &p2).await.unwrap();
    assert_eq!((s.downloaded, s.resumed), (1, 1));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_corrupt_server_copy_is_rejected_and_never_stored() {
    let scene = grid_scene("grid", 2, 1, 50, 8, Dtype::I8, 1);
    let server = shard_server(scene, None).await;
    server.state.corrupt.lock().unwrap().insert(1);
    let (_dir, store) = temp_store();
    let err = fetch(&store, &params(&server.url, [0.0, 0.0], 100.0))
        .await
        .unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, Error::Format { .. }), "{msg}");
    assert!(msg.contains("checksum") && msg.contains("twice"), "{msg}");
    // Tile 0 was fine and is kept for the next run; tile 1 is absent; no manifest switch.
    assert_eq!(stored_ids(&store), vec![0]);
    assert!(store.manifest("grid").unwrap().is_none());
    server.state.corrupt.lock().unwrap().clear();
    let s = fetch(&store, &params(&server.url, [0.0, 0.0], 100.0))
        .await
        .unwrap();
    assert_eq!((s.downloaded, s.skipped), (1, 1));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_new_generation_switches_atomically_and_drops_the_old_one() {
    let g1 = grid_scene("grid", 2, 2, 30, 8, Dtype::F16, 1);
    let server = shard_server(g1, None).await;
    let (_dir, store) = temp_store();
    fetch(&store, &params(&server.url, [0.0, 0.0], 100.0))
        .await
        .unwrap();
    let m1 = store.manifest("grid").unwrap().unwrap();

    // The server re-partitions (new content, same tile ids); the download of tile 2 breaks.
    let g2 = grid_scene("grid", 2, 2, 31, 8, Dtype::F16, 2);
    let len2 = g2.shards[&2].len();
    *server.state.scene.write().unwrap() = g2;
    server.state.cut_next.lock().unwrap().insert(2, len2 / 2);
    assert!(
        fetch(&store, &params(&server.url, [0.0, 0.0], 100.0))
            .await
            .is_err()
    );
    // Generation 1 is still what a reader sees, complete.
    let (m, shards, load) = store.load_scene("grid").unwrap();
    assert_eq!(m, m1);
    assert_eq!(shards.len(), 4);
    assert_eq!(load.absent_tiles, 0);

    let s = fetch(&store, &params(&server.url, [0.0, 0.0], 100.0))
        .await
        .unwrap();
    assert_eq!(s.generation, 2);
    assert_eq!(s.evicted, 4, "the four generation-1 shards are dropped");
    let (m, shards, _) = store.load_scene("grid").unwrap();
    assert_eq!(m.generation, 2);
    assert!(shards.iter().all(|s| s.ids.len() == 31));
    assert_eq!(store.stored_shards("grid").unwrap().len(), 4);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_requests_fail_with_messages_that_say_what_to_do() {
    let server = shard_server(
        grid_scene("grid", 1, 1, 5, 8, Dtype::F32, 1),
        Some("s3cret".into()),
    )
    .await;
    let (_dir, store) = temp_store();

    let e = fetch(&store, &params(&server.url, [0.0, 0.0], 5.0))
        .await
        .unwrap_err();
    // Typed: the status a front end acts on (`slag-edge` adds `--shard-token-file` as its hint, a unit test
    // of the binary); the library's message says what it means.
    assert!(
        matches!(
            e,
            Error::Network {
                status: Some(401),
                ..
            }
        ),
        "{e}"
    );
    let e = e.to_string();
    assert!(e.contains("401") && e.contains("token"), "{e}");
    let mut p = params(&server.url, [0.0, 0.0], 5.0);
    p.token = Some("s3cret".into());
    assert_eq!(fetch(&store, &p).await.unwrap().downloaded, 1);

    let mut p = params(&server.url, [0.0, 0.0], 5.0);
    p.scene = "../etc".into();
    assert!(matches!(
        fetch(&store, &p).await,
        Err(Error::Param {
            name: "scene_id",
            ..
        })
    ));
    p.scene = "other".into();
    p.token = Some("s3cret".into());
    let e = fetch(&store, &p).await.unwrap_err().to_string();
    assert!(e.contains("404"), "{e}");
    for r in [f64::NAN, -1.0, f64::INFINITY] {
        let p = params(&server.url, [0.0, 0.0], r);
        assert!(matches!(
            fetch(&store, &p).await,
            Err(Error::Param { name: "radius", .. })
        ));
    }
    // Nothing listens on port 9 of 127.0.0.1: a typed network error naming the URL.
    let e = fetch(&store, &params("http://127.0.0.1:9", [0.0, 0.0], 5.0))
        .await
        .unwrap_err();
    assert!(
        matches!(&e, Error::Network { url, .. } if url.contains("127.0.0.1:9")),
        "{e}"
    );
}

/// A raw HTTP server on loopback: answers `GET …/manifest` with `manifest` at once, and every
/// other request (the signature) with a 200 whose declared 300-byte body comes one byte every
/// 200 ms (never idle long enough for an idle timeout). Returns its URL.
async fn dripping_server(manifest: Vec<u8>) -> String {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    tokio::spawn(async move {
        loop {
            let Ok((mut conn, _)) = listener.accept().await else {
                return;
            };
            let manifest = manifest.clone();
            tokio::spawn(async move {
                let mut head = vec![0u8; 4096];
                let n = conn.read(&mut head).await.unwrap_or(0);
                let line = String::from_utf8_lossy(&head[..n])
                    .lines()
                    .next()
                    .unwrap_or("")
                    .to_string();
                if line.contains("/manifest ") {
                    let h = format!(
                        "HTTP/1.1 200 OK\r\ncontent-length: {}\r\n\r\n",
                        manifest.len()
                    );
                    let _ = conn.write_all(h.as_bytes()).await;
                    let _ = conn.write_all(&manifest).await;
                    return;
                }
                let _ = conn
                    .write_all(b"HTTP/1.1 200 OK\r\ncontent-length: 300\r\n\r\n")
                    .await;
                for _ in 0..300 {
                    tokio::time::sleep(std::time::Duration::from_millis(200)).await;
                    if conn.write_all(b"{").await.is_err() {
                        return;
                    }
                }
            });
        }
    });
    url
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_signature_dripped_a_byte_at_a_time_is_cut_off_at_the_least_rate() {
    let scene = grid_scene("grid", 2, 2, 10, 8, Dtype::F16, 1);
    let url = dripping_server(scene.manifest.to_json()).await;
    let key = slag_common::shards::signature::SigningKey::generate().public();
    let (_dir, store) = temp_store();
    let p = FetchParams {
        timeout: std::time::Duration::from_secs(1),
        min_rate: 1000,
        trusted_keys: Some(key.into()),
        ..grid_fetch_params(&url, 100.0)
    };
    let t = std::time::Instant::now();
    let e = fetch(&store, &p).await.unwrap_err();
    let took = t.elapsed();
    // 1 s of grace, then 1000 bytes/s: cut at about 1 s, where 300 bytes would take 60 s.
    assert!(took < std::time::Duration::from_secs(10), "{took:?}: {e}");
    match &e {
        Error::Network { url, message, .. } => {
            assert!(url.ends_with("manifest.sig"), "{e}");
            assert!(message.contains("least rate of 1000 bytes/s"), "{e}");
        }
        other => panic!("expected a network error, got {other}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_tile_sent_slower_than_the_least_rate_is_cut_off_and_keeps_what_arrived() {
    let server = shard_server(grid_scene("grid", 2, 2, 10, 8, Dtype::F16, 1), None).await;
    *server.state.slow.lock().unwrap() = Some((1, std::time::Duration::from_millis(100)));
    let (dir, store) = temp_store();
    let p = FetchParams {
        timeout: std::time::Duration::from_secs(1),
        min_rate: 1000,
        ..grid_fetch_params(&server.url, 100.0)
    };
    let t = std::time::Instant::now();
    let e = fetch(&store, &p).await.unwrap_err();
    assert!(t.elapsed() < std::time::Duration::from_secs(10), "{e}");
    assert!(e.to_string().contains("least rate"), "{e}");
    // A network failure: what arrived is kept for the next run to resume.
    assert!(partial_files(dir.path()) > 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_error_after_a_redirect_names_the_url_that_answered() {
    let target = shard_server(grid_scene("grid", 2, 2, 10, 8, Dtype::F16, 1), None).await;
    let to = target.url.clone();
    let redirect = axum::Router::new().fallback(move |uri: axum::http::Uri| {
        let to = to.clone();
        async move { axum::response::Redirect::temporary(&format!("{to}{uri}")) }
    });
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let first = format!("http://{}", listener.local_addr().unwrap());
    tokio::spawn(async move { axum::serve(listener, redirect).await.unwrap() });
    let (_dir, store) = temp_store();
    let p = FetchParams {
        scene: "nowhere".into(),
        ..grid_fetch_params(&first, 100.0)
    };
    let e = fetch(&store, &p).await.unwrap_err();
    let m = e.to_string();
    assert!(m.contains(&target.url) && !m.contains(&first), "{m}");
    assert!(m.contains("404"), "{m}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn post_fetch_past_the_request_timeout_answers_408_speaking_of_the_fetch() {
    let server = shard_server(grid_scene("grid", 2, 2, 10, 8, Dtype::F16, 1), None).await;
    let (_dir, store) = support::fetch_grid(&server.url, 100.0).await;
    let url = support::serve_store(
        store,
        std::sync::Arc::new(support::BasisEmbedder::new(8)),
        slag_edge::serve::ServeOptions {
            request_timeout: std::time::Duration::from_secs(1),
            ..support::grid_serve_options(None, false)
        },
    )
    .await;
    // Generation 2, whose tiles never finish arriving.
    *server.state.scene.write().unwrap() = grid_scene("grid", 2, 2, 10, 8, Dtype::F16, 2);
    server
        .state
        .stall
        .lock()
        .unwrap()
        .extend((0..4).map(|t| (t, 10)));
    let body = serde_json::json!({"center": [0.0, 0.0], "radius": 100.0, "server": server.url});
    let (status, answer) = support::send_json(
        reqwest::Client::new()
            .post(format!("{url}/fetch"))
            .json(&body),
    )
    .await;
    assert_eq!(status, 408, "{answer}");
    let m = support::error_message(&answer);
    assert!(m.contains("fetch") && !m.contains("top_k"), "{m}");
    // Queries keep their own 408 advice.
    let (status, _) =
        support::send_json(reqwest::Client::new().get(format!("{url}/query?text=t1"))).await;
    assert_eq!(status, 200);
}
