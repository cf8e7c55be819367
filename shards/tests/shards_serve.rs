//! HTTP serving on loopback (127.0.0.1:0) and atomic export.

mod support;

use slag_common::shards::synthetic::SyntheticScene;
use slag_common::shards::{Dtype, Manifest, decode_shard, shard_checksum};
use slag_shards::store::{ShardStore, partition_into_store};
use std::io::{Read, Write};

struct Resp {
    status: u16,
    headers: Vec<(String, String)>,
    body: Vec<u8>,
}

impl Resp {
    fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(k, _)| k.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.as_str())
    }
}

/// Minimal HTTP/1.1 client (one request per connection, `Connection: close`).
fn get(addr: std::net::SocketAddr, path: &str, extra: &[(&str, &str)]) -> Resp {
    let mut s = std::net::TcpStream::connect(addr).expect("connect");
    let mut req = format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n");
    for (k, v) in extra {
        req.push_str(&format!("{k}: {v}\r\n"));
    }
    req.push_str("\r\n");
    s.write_all(req.as_bytes()).expect("send");
    let mut raw = Vec::new();
    s.read_to_end(&mut raw).expect("read");
    let split = raw
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .expect("header end");
    let head = String::from_utf8_lossy(&raw[..split]).into_owned();
    let mut lines = head.split("\r\n");
    let status = lines
        .next()
        .and_then(|l| l.split(' ').nth(1))
        .and_then(|c| c.parse().ok())
        .expect("status");
    let headers: Vec<(String, String)> = lines
        .filter_map(|l| l.split_once(':'))
        .map(|(k, v)| (k.trim().to_string(), v.trim().to_string()))
        .collect();
    let body = raw[split + 4..].to_vec();
    let r = Resp {
        status,
        headers,
        body,
    };
    if let Some(len) = r.header("content-length") {
        assert_eq!(len.parse::<usize>().expect("len"), r.body.len());
    }
    r
}

fn filled_store(dir: &std::path::Path) -> (ShardStore, Manifest) {
    let store = ShardStore::open(dir).expect("open");
    let scene = SyntheticScene::new(1200, 8, 3, 40.0, 4);
    let p = support::z_up_params("lab.v1", 200, Dtype::I8);
    let m = partition_into_store(&store, &scene, &p).expect("partition");
    (store, m)
}

#[test]
fn manifest_and_shards_over_loopback() {
    let dir = tempfile::tempdir().expect("tmp");
    let (store, m) = filled_store(dir.path());
    let addr = serve_signed(store, None);

    // Manifest.
    let r = get(addr, "/v1/scenes/lab.v1/manifest", &[]);
    assert_eq!(r.status, 200);
    assert_eq!(r.header("content-type"), Some("application/json"));
    let got: Manifest = Manifest::from_json(&r.body, "http").expect("manifest json");
    assert_eq!(got, m);
    let metag = r.header("etag").expect("etag").to_string();
    assert_eq!(
        get(
            addr,
            "/v1/scenes/lab.v1/manifest",
            &[("If-None-Match", &metag)]
        )
        .status,
        304
    );

    // Every shard: bytes, strong ETag = checksum, decodes.
    for t in &m.tiles {
        let r = get(addr, &format!("/v1/scenes/lab.v1/shards/{}", t.id), &[]);
        assert_eq!(r.status, 200);
        assert_eq!(
            r.header("etag"),
            Some(format!("\"{}\"", t.checksum).as_str())
        );
        assert_eq!(r.header("accept-ranges"), Some("bytes"));
        assert_eq!(format!("{:08x}", shard_checksum(&r.body)), t.checksum);
        assert_eq!(decode_shard(&r.body).expect("decode").header.tile_id, t.id);
    }
    let t = &m.tiles[1];
    let path = format!("/v1/scenes/lab.v1/shards/{}", t.id);
    let full = get(addr, &path, &[]).body;
    let etag = format!("\"{}\"", t.checksum);
    let r = get(addr, &path, &[("If-None-Match", &etag)]);
    assert_eq!((r.status, r.body.len()), (304, 0));
    assert_eq!(
        get(addr, &path, &[("If-None-Match", "\"00000000\"")]).status,
        200
    );

    // Ranges.
    let r = get(addr, &path, &[("Range", "bytes=8-15")]);
    assert_eq!(r.status, 206);
    assert_eq!(r.body, full[8..16]);
    assert_eq!(
        r.header("content-range"),
        Some(format!("bytes 8-15/{}", full.len()).as_str())
    );
    let r = get(addr, &path, &[("Range", "bytes=-10")]);
    assert_eq!(
        (r.status, r.body.as_slice()),
        (206, &full[full.len() - 10..])
    );
    let r = get(addr, &path, &[("Range", "bytes=100-")]);
    assert_eq!((r.status, r.body.as_slice()), (206, &full[100..]));
    let r = get(addr, &path, &[("Range", &format!("bytes={}-", full.len()))]);
    assert_eq!(r.status, 416);
    assert_eq!(
        r.header("content-range"),
        Some(format!("bytes */{}", full.len()).as_str())
    );
    let r = get(
        addr,
        &path,
        &[("Range", "bytes=0-3"), ("If-Range", "\"deadbeef\"")],
    );
    assert_eq!((r.status, r.body.len()), (200, full.len()));

    // Errors: JSON 404 / 400, no traversal.
    for (p, code) in [
        ("/v1/scenes/nope/manifest", 404),
        ("/v1/scenes/lab.v1/shards/999999", 404),
        ("/v1/scenes/lab.v1/shards/abc", 400),
        ("/v1/scenes/lab.v1/shards/-1", 400),
        ("/v1/scenes/..%2F..%2Fetc/manifest", 400),
        ("/v1/scenes/.hidden/manifest", 400),
        ("/v1/scenes/lab.v1/shards/..%2F0", 400),
        ("/v1/scenes/lab.v1/../../etc/passwd", 404),
    ] {
        let r = get(addr, p, &[]);
        assert_eq!(r.status, code, "{p}");
        let v: serde_json::Value = serde_json::from_slice(&r.body).expect("json error body");
        assert_eq!(v["status"], code, "{p}");
        assert!(v["error"].as_str().is_some_and(|s| !s.is_empty()));
    }
}

#[test]
fn export_is_complete_and_atomic() {
    let dir = tempfile::tempdir().expect("tmp");
    let (store, m) = filled_store(&dir.path().join("store"));
    let out = dir.path().join("out").join("lab");
    let got = slag_shards::export::export(&store, "lab.v1", &out, false).expect("export");
    assert_eq!(got, m);
    let back = Manifest::from_json(
        &std::fs::read(out.join("manifest.json")).expect("manifest"),
        "export",
    )
    .expect("json");
    assert_eq!(back, m);
    for t in &m.tiles {
        let b = std::fs::read(out.join("shards").join(t.id.to_string())).expect("shard file");
        assert_eq!(format!("{:08x}", shard_checksum(&b)), t.checksum);
    }
    let n_files = std::fs::read_dir(out.join("shards")).expect("dir").count();
    assert_eq!(n_files, m.tiles.len());
    // Refuses to overwrite without force; leaves no temporary folder behind.
    assert!(matches!(
        slag_shards::export::export(&store, "lab.v1", &out, false),
        Err(slag_common::Error::Io { source, .. })
            if source.kind() == std::io::ErrorKind::AlreadyExists
    ));
    // The command line adds the flag.
    let e = slag_shards::export::export(&store, "lab.v1", &out, false).expect_err("exists");
    assert!(!e.to_string().contains("--force"), "{e}");
    assert_eq!(
        slag_shards::cli::hint_for(&e).as_deref(),
        Some("pass --force to replace it")
    );
    assert!(slag_shards::export::export(&store, "nope", &dir.path().join("x"), false).is_err());
    assert!(!dir.path().join("x").exists());
    std::fs::write(out.join("shards").join("stale"), b"old").expect("write");
    slag_shards::export::export(&store, "lab.v1", &out, true).expect("force");
    assert!(!out.join("shards").join("stale").exists());
    let leftovers: Vec<_> = std::fs::read_dir(dir.path().join("out"))
        .expect("dir")
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(leftovers, vec!["lab".to_string()]);
}

/// Serves `store` with `key` on loopback in a thread of its own; returns the address.
fn serve_signed(
    store: ShardStore,
    key: Option<slag_common::shards::signature::SigningKey>,
) -> std::net::SocketAddr {
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let rt = tokio::runtime::Runtime::new().expect("runtime");
        rt.block_on(async move {
            let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
                .await
                .expect("bind");
            tx.send(listener.local_addr().expect("addr"))
                .expect("send addr");
            axum::serve(listener, slag_shards::serve::router_signed(store, key)).await
        })
    });
    rx.recv().expect("server address")
}

#[test]
fn a_signed_partition_serves_and_exports_a_signature_of_the_exact_manifest_bytes() {
    use slag_common::shards::signature::{SigningKey, sha256_hex};
    let dir = tempfile::tempdir().expect("tmp");
    let store = ShardStore::open(&dir.path().join("store")).expect("open");
    let key = SigningKey::read_pem(
        &slag_common::shards::signature::keygen(&dir.path().join("keys"))
            .expect("keygen")
            .private,
    )
    .expect("key");
    let scene = SyntheticScene::new(1200, 8, 3, 40.0, 4);
    let p = support::z_up_params("lab.v1", 200, Dtype::I8);
    slag_shards::store::partition_into_store_signed(&store, &scene, &p, Some(&key))
        .expect("partition");
    let stored = store
        .stored_manifest("lab.v1")
        .expect("read")
        .expect("scene");
    assert!(stored.signature.is_some());
    let unsigned = ShardStore::open(&dir.path().join("unsigned")).expect("open");
    partition_into_store(&unsigned, &scene, &p).expect("partition");

    let addr = serve_signed(store.clone(), None);
    let manifest = get(addr, "/v1/scenes/lab.v1/manifest", &[]);
    let sig = get(addr, "/v1/scenes/lab.v1/manifest.sig", &[]);
    assert_eq!((manifest.status, sig.status), (200, 200));
    assert_eq!(manifest.body, stored.bytes.to_vec());
    key.public()
        .verify(&manifest.body, &sig.body, "http")
        .expect("the stored signature covers the served bytes");
    // Every tile names the SHA-256 of the shard served for it.
    let m = Manifest::from_json(&manifest.body, "http").expect("manifest");
    for t in &m.tiles {
        let shard = get(addr, &format!("/v1/scenes/lab.v1/shards/{}", t.id), &[]);
        assert_eq!(t.sha256.as_deref(), Some(sha256_hex(&shard.body).as_str()));
    }

    // An unsigned store: no signature, unless the server signs with its own key.
    let addr = serve_signed(unsigned.clone(), None);
    assert_eq!(get(addr, "/v1/scenes/lab.v1/manifest.sig", &[]).status, 404);
    let server_key = SigningKey::read_pem(
        &slag_common::shards::signature::keygen(&dir.path().join("server-keys"))
            .expect("keygen")
            .private,
    )
    .expect("key");
    let server_public = server_key.public();
    let addr = serve_signed(unsigned.clone(), Some(server_key));
    let manifest = get(addr, "/v1/scenes/lab.v1/manifest", &[]);
    let sig = get(addr, "/v1/scenes/lab.v1/manifest.sig", &[]);
    assert_eq!(sig.status, 200);
    server_public
        .verify(&manifest.body, &sig.body, "http")
        .expect("signed by the server's key");
    assert!(
        key.public()
            .verify(&manifest.body, &sig.body, "http")
            .is_err()
    );

    // Export: manifest.sig beside manifest.json, over its exact bytes.
    let out = dir.path().join("export");
    slag_shards::export::export(&store, "lab.v1", &out, false).expect("export");
    let json = std::fs::read(out.join("manifest.json")).expect("manifest.json");
    let sig = std::fs::read(out.join("manifest.sig")).expect("manifest.sig");
    key.public()
        .verify(&json, &sig, "export")
        .expect("export signature");
    let out = dir.path().join("export-unsigned");
    slag_shards::export::export(&unsigned, "lab.v1", &out, false).expect("export");
    assert!(!out.join("manifest.sig").exists());
}
