//! `slag-edge serve` refuses what it cannot answer truthfully or must not keep: a shard-server
//! URL with a user name and password (400; the secret is not stored, not shown in `/stats`, not
//! in `fetch.json`), a `text` that is not a JSON string, a query string that is not UTF-8 once
//! percent-decoded, and two `Authorization` headers (401).
#![allow(clippy::unwrap_used)]

mod support;

use std::sync::Arc;

use slag_common::shards::Dtype;
use slag_common::testing::{assert_json_error, exchange, get_request as get};
use slag_edge::fetch::fetch;
use support::{
    BasisEmbedder, error_message, grid_fetch_params, grid_scene, grid_serve_options, send_json,
    serve_store, shard_server, slag_edge_command, temp_store,
};

/// The password of the refused URLs: must appear nowhere.
const SECRET: &str = "pw-5e3c7a";
/// The shard server's bearer token: must appear in no answer and no stored file.
const SHARD_TOKEN: &str = "shard-tok-9f2c41";
/// The edge's own bearer token.
const EDGE_TOKEN: &str = "edge-tok";

struct Edge {
    url: String,
    shards: String,
    dir: tempfile::TempDir,
    client: reqwest::Client,
}

impl Edge {
    /// `POST /fetch` with the JSON `body`: the status and the JSON answer.
    async fn post_fetch(&self, body: serde_json::Value) -> (u16, serde_json::Value) {
        send_json(self.client.post(format!("{}/fetch", self.url)).json(&body)).await
    }

    /// The body of `GET /stats`, as text.
    async fn stats(&self) -> String {
        self.client
            .get(format!("{}/stats", self.url))
            .send()
            .await
            .unwrap()
            .text()
            .await
            .unwrap()
    }
}

/// A shard server that wants [`SHARD_TOKEN`], a store fetched from it, and the edge serving
/// that store with `token`.
async fn start(token: Option<&str>) -> Edge {
    let shards = shard_server(
        grid_scene("grid", 2, 2, 20, 8, Dtype::F32, 1),
        Some(SHARD_TOKEN.into()),
    )
    .await;
    let (dir, store) = temp_store();
    let params = slag_edge::fetch::FetchParams {
        token: Some(SHARD_TOKEN.into()),
        ..grid_fetch_params(&shards.url, 100.0)
    };
    fetch(&store, &params).await.unwrap();
    let url = serve_store(
        store,
        Arc::new(BasisEmbedder::new(8)),
        grid_serve_options(token, false),
    )
    .await;
    Edge {
        url,
        shards: shards.url,
        dir,
        client: reqwest::Client::new(),
    }
}

/// Every file under `dir` (the store: sled database, manifests, `fetch.json`) as bytes.
fn files_under(dir: &std::path::Path) -> Vec<(std::path::PathBuf, Vec<u8>)> {
    let mut out = Vec::new();
    let mut todo = vec![dir.to_path_buf()];
    while let Some(d) = todo.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                todo.push(p);
            } else {
                out.push((p.clone(), std::fs::read(&p).unwrap()));
            }
        }
    }
    out
}

fn contains(hay: &[u8], needle: &str) -> bool {
    hay.windows(needle.len()).any(|w| w == needle.as_bytes())
}

/// No stored file holds [`SECRET`] or [`SHARD_TOKEN`]; at least one `fetch.json` exists.
fn assert_no_secret_stored(dir: &std::path::Path) {
    let files = files_under(dir);
    assert!(files.iter().any(|(p, _)| p.ends_with("fetch.json")));
    for (p, bytes) in &files {
        for s in [SECRET, SHARD_TOKEN] {
            assert!(!contains(bytes, s), "{s} stored in {}", p.display());
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fetch_url_with_credentials_is_refused_and_no_secret_is_shown_or_stored() {
    let e = start(None).await;
    let host = e.shards.trim_start_matches("http://");
    let with_credentials = format!("http://robot:{SECRET}@{host}");
    let (status, v) = e
        .post_fetch(
            serde_json::json!({"center": [0.0, 0.0], "radius": 100.0, "server": with_credentials}),
        )
        .await;
    assert_eq!(status, 400, "{v}");
    let m = error_message(&v);
    assert!(m.contains("server") && m.contains("token"), "{m}");
    assert!(!m.contains(SECRET), "{m}");
    // Nothing saved: the last fetch is still the one without credentials.
    let stats = e.stats().await;
    assert!(
        !stats.contains(SECRET) && !stats.contains(SHARD_TOKEN),
        "{stats}"
    );
    let stats: serde_json::Value = serde_json::from_str(&stats).unwrap();
    assert_eq!(stats["last_fetch"]["server"], e.shards.as_str(), "{stats}");
    assert_no_secret_stored(e.dir.path());

    // A fetch with the token in the body: it works, and the token is neither shown nor stored.
    let (status, v) = e
        .post_fetch(
            serde_json::json!({"center": [0.0, 0.0], "radius": 100.0, "token": SHARD_TOKEN}),
        )
        .await;
    assert_eq!(status, 200, "{v}");
    assert!(!v.to_string().contains(SHARD_TOKEN), "{v}");
    let stats = e.stats().await;
    assert!(!stats.contains(SHARD_TOKEN), "{stats}");
    assert_no_secret_stored(e.dir.path());
}

#[test]
fn slag_edge_fetch_refuses_a_url_with_credentials() {
    let dir = tempfile::tempdir().unwrap();
    let out = slag_edge_command()
        .args(["fetch", "--from"])
        .arg(format!("http://robot:{SECRET}@127.0.0.1:9"))
        .args(["--scene", "grid", "--center", "0,0", "--store"])
        .arg(dir.path())
        .env_remove("SLAG_SHARD_TOKEN")
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(!err.contains(SECRET), "{err}");
    assert!(
        err.contains("***@127.0.0.1:9")
            && err.contains("hint:")
            && err.contains("--shard-token-file"),
        "{err}"
    );
    for (p, bytes) in files_under(dir.path()) {
        assert!(
            !contains(&bytes, SECRET),
            "secret stored in {}",
            p.display()
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_text_that_is_not_a_json_string_is_refused_naming_the_field() {
    let e = start(None).await;
    let post = |q: serde_json::Value| {
        send_json(
            e.client
                .post(format!("{}/query", e.url))
                .json(&serde_json::json!({ "queries": [q] })),
        )
    };
    for (text, kind) in [
        (serde_json::json!({"a": 1}), "an object"),
        (serde_json::json!(["chair"]), "an array"),
        (serde_json::json!(true), "a boolean"),
        (serde_json::json!(5), "a number"),
        (serde_json::Value::Null, "null"),
    ] {
        let (status, v) = post(serde_json::json!({ "text": text })).await;
        assert_eq!(status, 400, "{text}: {v}");
        let m = error_message(&v);
        assert!(
            m.contains("queries[0]") && m.contains("text") && m.contains(kind),
            "{m}"
        );
    }
    let (status, v) = post(serde_json::json!({"text": "t0", "top_k": 3})).await;
    assert_eq!(status, 200, "{v}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_query_string_that_is_not_utf8_is_refused_on_every_route() {
    let e = start(None).await;
    let addr = e.url.trim_start_matches("http://");
    for path in [
        "/query?text=%FF",
        "/query?text=caf%C3",
        "/query?top_k=3&text=a%80b",
        "/query.ply?text=%FF",
        "/query.ply?text=%C3%28&color=ff0000",
        "/query?%FF=1&text=t0",
        "/query?text=t0&text=t1",
    ] {
        let (status, head, body) = exchange(addr, &get(path, "")).await;
        assert_eq!(status, 400, "{path}: {body}");
        assert_json_error(400, &head, &body);
        let field = if path.contains("%FF=") {
            "query"
        } else {
            "text"
        };
        assert!(body.contains(field), "{path}: {body}");
    }
    // Valid UTF-8, `+` as a space, a literal `%`: answered.
    for path in [
        "/query?text=caf%C3%A9",
        "/query?text=t0+chair&top_k=2",
        "/query?text=100%25",
        "/query?text=50%",
        "/query.ply?text=t0",
    ] {
        let (status, _, body) = exchange(addr, &get(path, "")).await;
        assert_eq!(status, 200, "{path}: {body}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_authorization_headers_get_401() {
    let e = start(Some(EDGE_TOKEN)).await;
    let addr = e.url.trim_start_matches("http://");
    let one = format!("Authorization: Bearer {EDGE_TOKEN}\r\n");
    slag_common::testing::assert_two_authorizations_refused(addr, "/stats", &one).await;
}
