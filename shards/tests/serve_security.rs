//! `slag-encoder serve` under hostile or unauthorised requests: bearer token (401 JSON without
//! it), path-traversal scene and shard ids (400, never a file path), token file parsing.
#![allow(clippy::unwrap_used)]

mod support;

use std::io::{Read, Write};

/// One `GET` over a fresh connection: (status, headers text, body).
fn get(addr: std::net::SocketAddr, path: &str, auth: Option<&str>) -> (u16, String, Vec<u8>) {
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    let mut req = format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n");
    if let Some(a) = auth {
        req.push_str(&format!("Authorization: {a}\r\n"));
    }
    req.push_str("\r\n");
    s.write_all(req.as_bytes()).unwrap();
    let mut raw = Vec::new();
    s.read_to_end(&mut raw).unwrap();
    let split = raw.windows(4).position(|w| w == b"\r\n\r\n").unwrap();
    let head = String::from_utf8_lossy(&raw[..split]).into_owned();
    let status = head.split(' ').nth(1).unwrap().parse().unwrap();
    (status, head, raw[split + 4..].to_vec())
}

fn start(token: Option<&str>) -> (std::net::SocketAddr, tempfile::TempDir) {
    let (dir, store) = support::lab_store();
    let token = token.map(str::to_string);
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let rt = tokio::runtime::Runtime::new().unwrap();
        rt.block_on(async move {
            let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
            tx.send(listener.local_addr().unwrap()).unwrap();
            axum::serve(
                listener,
                slag_shards::serve::router_with_token(store, token),
            )
            .await
        })
    });
    (rx.recv().unwrap(), dir)
}

#[test]
fn a_token_guards_every_route_with_a_401_json_answer() {
    let (addr, _dir) = start(Some("s3cret"));
    for path in [
        "/v1/scenes",
        "/v1/scenes/lab/manifest",
        "/v1/scenes/lab/shards/0",
    ] {
        for auth in [
            None,
            Some("Bearer wrong"),
            Some("Bearer s3cre"),
            Some("Basic s3cret"),
        ] {
            let (status, head, body) = get(addr, path, auth);
            assert_eq!(status, 401, "{path} {auth:?}");
            assert!(
                head.to_ascii_lowercase()
                    .contains("www-authenticate: bearer"),
                "{head}"
            );
            let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
            assert_eq!(v["status"], 401);
            assert!(v["error"].as_str().unwrap().contains("--token"), "{v}");
        }
    }
    let (status, _, body) = get(addr, "/v1/scenes/lab/manifest", Some("Bearer s3cret"));
    assert_eq!(status, 200);
    let m = slag_common::shards::Manifest::from_json(&body, "http").unwrap();
    let id = m.tiles[0].id;
    let (status, _, body) = get(
        addr,
        &format!("/v1/scenes/lab/shards/{id}"),
        Some("Bearer s3cret"),
    );
    assert_eq!(status, 200);
    assert_eq!(body.len() as u64, m.tiles[0].bytes);
    // Without a token the same store is open.
    let (open, _dir2) = start(None);
    assert_eq!(get(open, "/v1/scenes/lab/manifest", None).0, 200);
}

#[test]
fn path_traversal_ids_are_rejected_as_bad_requests() {
    let (addr, _dir) = start(None);
    for path in [
        "/v1/scenes/..%2F..%2Fetc%2Fpasswd/manifest",
        "/v1/scenes/.hidden/manifest",
        "/v1/scenes/..%5Cwin/manifest",
        "/v1/scenes/lab%00x/manifest",
        "/v1/scenes/..%2Flab/shards/0",
        "/v1/scenes/lab/shards/..%2F..%2F0",
        "/v1/scenes/lab/shards/-1",
        "/v1/scenes/lab/shards/99999999999999999999999",
    ] {
        let (status, _, body) = get(addr, path, None);
        assert_eq!(status, 400, "{path}: {}", String::from_utf8_lossy(&body));
        let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
        assert!(v["error"].as_str().unwrap().contains("invalid"), "{v}");
    }
    // Raw `..` segments are normalised away by nobody: they simply match no route.
    assert_eq!(get(addr, "/v1/scenes/../../etc/passwd", None).0, 404);
}

#[test]
fn the_token_file_is_read_and_an_empty_one_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let f = dir.path().join("token");
    std::fs::write(&f, "  abc123 \nignored\n").unwrap();
    let t = slag_shards::cli::serve_token(Some(&f)).unwrap();
    assert_eq!(t.as_deref(), Some("abc123"));
    std::fs::write(&f, "\n").unwrap();
    let e = slag_shards::cli::serve_token(Some(&f)).unwrap_err();
    assert!(e.to_string().contains("empty"), "{e}");
    let e = slag_shards::cli::serve_token(Some(&dir.path().join("absent"))).unwrap_err();
    assert!(matches!(e, slag_common::Error::Io { .. }), "{e}");
}
