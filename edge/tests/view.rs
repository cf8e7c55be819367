//! `GET /query.ply` and the web page over loopback: the returned `.ply` parses with slag's own
//! `load_ply`, holds every loaded Gaussian in store order with its display attributes (or the
//! documented fallbacks), and paints exactly the Gaussians `GET /query` matches.
#![allow(clippy::unwrap_used)]

mod support;

use std::collections::HashSet;
use std::sync::Arc;

use slag_common::scene::{PlyLoadOptions, SH_C0, load_ply};
use slag_common::shards::{Dtype, decode_shard};
use slag_edge::serve::AppState;
use support::{
    BasisEmbedder, fetch_grid, grid_scene, grid_serve_options, header_number, match_ids, send,
    serve_on_loopback, shard_server,
};

struct Edge {
    url: String,
    client: reqwest::Client,
    /// Decoded stored shards in manifest tile order (the store's row order).
    shards: Vec<slag_common::shards::Shard>,
    _dir: tempfile::TempDir,
    web: tempfile::TempDir,
}

async fn start(token: Option<&str>) -> Edge {
    let scene = grid_scene("grid", 3, 2, 40, 8, Dtype::F16, 1);
    let server = shard_server(scene, None).await;
    let (dir, store) = fetch_grid(&server.url, 1000.0).await;
    let m = store.manifest("grid").unwrap().unwrap();
    let shards = m
        .tiles
        .iter()
        .filter_map(|t| store.shard_bytes("grid", t).unwrap())
        .map(|b| decode_shard(&b).unwrap())
        .collect();
    let web = tempfile::tempdir().unwrap();
    std::fs::create_dir(web.path().join("vendor")).unwrap();
    std::fs::write(web.path().join("vendor/three.module.js"), "export {};").unwrap();
    let state = AppState::new(
        store,
        Arc::new(BasisEmbedder::new(8)),
        grid_serve_options(token, false),
    )
    .unwrap()
    .with_web_dir(Some(web.path().to_path_buf()));
    Edge {
        url: serve_on_loopback(state).await,
        client: reqwest::Client::new(),
        shards,
        _dir: dir,
        web,
    }
}

impl Edge {
    /// `GET {url}{path}` with the bearer token when given.
    async fn get(&self, path: &str, token: Option<&str>) -> reqwest::Response {
        let req = self.client.get(format!("{}{path}", self.url));
        send(match token {
            Some(t) => req.bearer_auth(t),
            None => req,
        })
        .await
    }
}

fn rgb(dc: [f32; 3]) -> [f64; 3] {
    dc.map(|c| 0.5 + SH_C0 * c as f64)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn query_ply_paints_exactly_the_matches_in_store_order() {
    let e = start(None).await;
    let dir = tempfile::tempdir().unwrap();
    let ids: Vec<u32> = e.shards.iter().flat_map(|s| s.ids.clone()).collect();
    let mut any_match = false;
    for text in ["t0", "t3", "t5", "nothing-like-it"] {
        let r = e
            .get(&format!("/query?text={text}&top_k=10000"), None)
            .await;
        let json: serde_json::Value = r.json().await.unwrap();
        let want: HashSet<u32> = match_ids(&json).into_iter().collect();
        assert_eq!(
            want.len() as u64,
            json["summary"]["count"].as_u64().unwrap()
        );
        any_match |= !want.is_empty();
        let r = e.get(&format!("/query.ply?text={text}"), None).await;
        assert_eq!(r.status(), 200);
        let h = r.headers().clone();
        assert_eq!(h["content-type"], "application/octet-stream");
        assert_eq!(
            h["content-disposition"],
            "attachment; filename=\"query.ply\""
        );
        assert_eq!(h["x-slag-matches"], want.len().to_string().as_str());
        assert_eq!(h["x-slag-up"], "0,0,1");
        let bytes = r.bytes().await.unwrap();
        let p = dir.path().join(format!("{text}.ply"));
        std::fs::write(&p, &bytes).unwrap();
        let g = load_ply(&p, PlyLoadOptions { colours: true }).unwrap();
        assert_eq!(g.len(), ids.len());
        let sh = g.sh.as_ref().unwrap();
        let mut painted = HashSet::new();
        let mut row = 0;
        for s in &e.shards {
            for k in 0..s.ids.len() {
                assert_eq!(g.means[row], s.means[k]);
                let c = rgb(sh.dc(row));
                let magenta =
                    (c[0] - 1.0).abs() < 1e-5 && c[1].abs() < 1e-5 && (c[2] - 1.0).abs() < 1e-5;
                if magenta {
                    painted.insert(ids[row]);
                }
                match (&s.scales, &s.opacities, &s.rotations, &s.sh_dc) {
                    (Some(sc), Some(op), Some(rot), Some(dc)) => {
                        for (got, log) in g.scales[row].iter().zip(sc[k]) {
                            let want = log.exp();
                            assert!((got - want).abs() <= 1e-6 * want);
                        }
                        let o = 1.0 / (1.0 + (-op[k]).exp());
                        assert!((g.opacities[row] - o).abs() < 1e-6);
                        for (got, want) in g.rotations[row].iter().zip(rot[k]) {
                            assert!((got - want).abs() < 1e-6);
                        }
                        if !magenta {
                            assert_eq!(sh.dc(row), dc[k]);
                        }
                    }
                    _ => {
                        // Fallbacks: isotropic small scale, identity rotation, 0.95, gray.
                        let s0 = g.scales[row][0];
                        assert!(s0 > 0.0 && g.scales[row].iter().all(|&v| v == s0));
                        assert_eq!(g.rotations[row], [1.0, 0.0, 0.0, 0.0]);
                        assert!((g.opacities[row] - 0.95).abs() < 1e-5);
                        if !magenta {
                            assert_eq!(sh.dc(row), [0.0; 3]);
                        }
                    }
                }
                row += 1;
            }
        }
        assert_eq!(
            painted, want,
            "{text}: painted Gaussians differ from /query matches"
        );
    }
    assert!(any_match, "the fixture must produce matches");
    // Both kinds of shards are present.
    assert!(e.shards.iter().any(|s| s.rotations.is_some()));
    assert!(e.shards.iter().any(|s| s.rotations.is_none()));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn query_ply_validates_like_query_and_styles() {
    let e = start(None).await;
    for q in [
        "",
        "text=t1&top_k=0",
        "text=t1&color=zz",
        "text=t1&dim=2",
        "text=t1&bogus=1",
    ] {
        let r = e.get(&format!("/query.ply?{q}"), None).await;
        assert_eq!(r.status(), 400, "{q}");
        let j: serde_json::Value = r.json().await.unwrap();
        assert!(j["error"].is_string());
    }
    let r = e.get("/query.ply?text=t1&color=00ff00&dim=0", None).await;
    assert_eq!(r.status(), 200);
    let n = header_number(&r, "x-slag-matches") as usize;
    let p = e.web.path().join("g.ply");
    std::fs::write(&p, r.bytes().await.unwrap()).unwrap();
    let g = load_ply(&p, PlyLoadOptions { colours: true }).unwrap();
    let sh = g.sh.as_ref().unwrap();
    let (mut green, mut black) = (0, 0);
    for i in 0..g.len() {
        let c = rgb(sh.dc(i));
        if (c[1] - 1.0).abs() < 1e-5 && c[0].abs() < 1e-5 {
            green += 1;
        } else if c.iter().all(|v| v.abs() < 1e-5) {
            black += 1;
        }
    }
    assert!(n > 0);
    assert_eq!((green, black), (n, g.len() - n));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn page_is_public_and_data_needs_the_token() {
    let e = start(Some("s3cret")).await;
    let page = e.get("/", None).await;
    assert_eq!(page.status(), 200);
    assert!(
        page.headers()["content-type"]
            .to_str()
            .unwrap()
            .starts_with("text/html")
    );
    let html = page.text().await.unwrap();
    assert!(html.contains("/app.js") && html.contains("web-vendor.sh"));
    // (path, token, status, body): the page's script and vendor files need no token (the one
    // installed is served as written), a vendor file not installed is a 404 saying how to get it,
    // the data needs the token.
    let cases = [
        ("/app.js", None, 200, Body::Has("/query.ply")),
        ("/vendor/three.module.js", None, 200, Body::Is("export {};")),
        (
            "/vendor/gaussian-splats-3d.module.js",
            None,
            404,
            Body::Has("web-vendor.sh"),
        ),
        ("/query.ply?text=t1", None, 401, Body::Any),
        ("/query.ply?text=t1", Some("s3cret"), 200, Body::Any),
    ];
    for (path, token, status, body) in cases {
        let r = e.get(path, token).await;
        assert_eq!(r.status(), status, "{path} {token:?}");
        let text = r.text().await.unwrap();
        match body {
            Body::Is(want) => assert_eq!(text, want, "{path}"),
            Body::Has(part) => assert!(text.contains(part), "{path}: {text}"),
            Body::Any => {}
        }
    }
}

/// What a response body must be.
enum Body {
    Is(&'static str),
    Has(&'static str),
    Any,
}
