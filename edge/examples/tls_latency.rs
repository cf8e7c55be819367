//! Query latency of `slag-edge serve` over HTTPS against plain HTTP: one process, one store, the
//! same router and server loop (`slag_common::http::serve_with_tls`) on two loopback ports, one
//! with TLS (a CA and an ECDSA P-256 server certificate made at start, rustls with ring) and one
//! without. The same queries go to both, interleaved (plain, TLS, plain, …), one at a time, and
//! the medians are compared; a benchmark, not a test.
//!
//! ```sh
//! cargo run --release -p slag-edge --example tls_latency -- [QUERIES] [GAUSSIANS_PER_TILE] [DIM]
//! ```
//!
//! Workload: a synthetic 4 × 4-tile grid scene (`GAUSSIANS_PER_TILE`, default 1,000, so 16,000
//! Gaussians; `DIM` default 512; f16 shards), fetched into a temporary edge store, exact scan,
//! `GET /query?text=t<i>&top_k=10&threshold=none` with prompts `t0`, `t1`, … (embedded without a
//! model: basis vectors), `QUERIES` (default 400) per scheme. Two client modes: one kept-alive
//! connection reused for every query (the robot's client), and a new connection per query (TCP
//! connect, and for HTTPS the full TLS 1.3 handshake, counted in each query's time).
#![allow(clippy::unwrap_used, missing_docs)]

#[path = "../tests/support/mod.rs"]
mod support;

use std::sync::Arc;
use std::time::{Duration, Instant};

use slag_common::http::ServerLimits;
use slag_common::shards::Dtype;
use slag_common::testing::TestCa;
use slag_common::tls::ServerTls;
use slag_edge::serve::{AppState, ServeOptions};

/// Serves `state` on a new loopback port, over TLS with `tls`; returns `scheme://127.0.0.1:port`.
async fn serve(state: Arc<AppState>, tls: Option<Arc<ServerTls>>) -> String {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let scheme = if tls.is_some() { "https" } else { "http" };
    let router = slag_edge::serve::router(state);
    tokio::spawn(slag_common::http::serve_with_tls(
        listener,
        router,
        ServerLimits::default(),
        tls,
        std::future::pending(),
    ));
    format!("{scheme}://{addr}")
}

fn client(ca: &TestCa, keep_alive: bool) -> reqwest::Client {
    let mut b = reqwest::Client::builder()
        .add_root_certificate(reqwest::Certificate::from_pem(ca.pem.as_bytes()).unwrap())
        .http1_only();
    if !keep_alive {
        b = b.pool_max_idle_per_host(0);
    }
    b.build().unwrap()
}

/// One query's wall time (request sent to body read), seconds.
async fn query(client: &reqwest::Client, base: &str, i: usize, dim: usize) -> f64 {
    let url = format!(
        "{base}/query?text=t{}&top_k=10&threshold=none",
        i % (dim - 1)
    );
    let t0 = Instant::now();
    let r = client.get(url).send().await.unwrap();
    assert_eq!(r.status(), 200);
    let body = r.bytes().await.unwrap();
    assert!(!body.is_empty());
    t0.elapsed().as_secs_f64()
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let arg = |i: usize, default: usize| {
        std::env::args()
            .nth(i)
            .map_or(default, |a| a.parse().unwrap())
    };
    let (queries, per_tile, dim) = (arg(1, 400), arg(2, 1000), arg(3, 512));
    let shards = support::shard_server(
        support::grid_scene("grid", 4, 4, per_tile, dim, Dtype::F16, 1),
        None,
    )
    .await;
    let (_dir, store) = support::fetch_grid(&shards.url, 1e6).await;
    let embedder = Arc::new(support::BasisEmbedder::new(dim));
    let opts = ServeOptions {
        request_timeout: Duration::from_secs(60),
        ..ServeOptions::new("grid")
    };
    let state = Arc::new(AppState::new(store, embedder, opts).unwrap());

    let ca = TestCa::new("slag bench CA");
    let certs = tempfile::tempdir().unwrap();
    let (c, k) = ca.server_cert(1).write(certs.path());
    let tls = Arc::new(ServerTls::load(&c, &k).unwrap());
    let plain_url = serve(state.clone(), None).await;
    let tls_url = serve(state, Some(tls)).await;

    println!(
        "{} Gaussians, dim {dim}, f16, exact scan, top_k 10, {queries} queries per scheme, \
         one at a time, interleaved\n",
        16 * per_tile
    );
    println!("| connection | plain HTTP median (ms) | HTTPS median (ms) | HTTPS / plain |");
    println!("|---|---|---|---|");
    for keep_alive in [true, false] {
        let (plain_client, tls_client) = (client(&ca, keep_alive), client(&ca, keep_alive));
        // Warm-up: the first query of each scheme (connection, caches) is not timed.
        query(&plain_client, &plain_url, 0, dim).await;
        query(&tls_client, &tls_url, 0, dim).await;
        let (mut plain, mut https) = (Vec::new(), Vec::new());
        for i in 0..queries {
            plain.push(query(&plain_client, &plain_url, i, dim).await);
            https.push(query(&tls_client, &tls_url, i, dim).await);
        }
        let (p, t) = (median(plain) * 1e3, median(https) * 1e3);
        let mode = if keep_alive {
            "kept alive, reused"
        } else {
            "new per query"
        };
        println!("| {mode} | {p:.3} | {t:.3} | {:.3} |", t / p);
    }
}
