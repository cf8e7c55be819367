//! `slag-edge` and TLS, with a CA and server certificates made at test time: `serve` answers
//! queries over HTTPS and `POST /reload` (and, for the binary, `SIGHUP`) swaps the certificate for
//! new connections while an answer in flight completes (a bad file is refused and the
//! certificate in use stays); `fetch`
//! from an HTTPS shard server with a private CA (`--ca-cert`) and its refusal without it; a
//! bearer token refused over plain HTTP off loopback unless `--allow-plain-http`; a bad
//! certificate file refused at start-up.
#![allow(clippy::unwrap_used)]

mod support;

use std::sync::Arc;

use slag_common::Error;
use slag_common::shards::Dtype;
use slag_common::testing::TestCa;
use slag_common::tls::{ServerTls, fingerprint};
use slag_edge::fetch::{FetchParams, fetch};
use slag_edge::serve::{AppState, ServeOptions};
use support::{
    GateEmbedder, assert_success, fetch_args, fetch_grid, grid_fetch_params, grid_scene,
    grid_serve_options, output_blocking, serve_on_loopback, shard_server, shard_server_tls,
    slag_edge_with_log, temp_store, wait_until,
};

/// A client that trusts only `ca`, reports the server's certificate (`TlsInfo`) and, new for
/// every request, never resumes an older session.
fn https(ca: &TestCa) -> reqwest::Client {
    reqwest::Client::builder()
        .add_root_certificate(reqwest::Certificate::from_pem(ca.pem.as_bytes()).unwrap())
        .tls_built_in_root_certs(false)
        .tls_info(true)
        .build()
        .unwrap()
}

/// Sends `request`, which must get an answer (of any status).
async fn send(request: reqwest::RequestBuilder) -> reqwest::Response {
    request.send().await.unwrap()
}

/// The certificate (DER) the server presented for `r`.
fn peer(r: &reqwest::Response) -> Vec<u8> {
    let info = r.extensions().get::<reqwest::tls::TlsInfo>().unwrap();
    info.peer_certificate().unwrap().to_vec()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn post_reload_swaps_the_certificate_while_an_answer_in_flight_completes() {
    let ca = TestCa::new("slag edge test CA");
    let (first, second) = (ca.server_cert(1), ca.server_cert(2));
    let certs = tempfile::tempdir().unwrap();
    let (cert_file, key_file) = first.write(certs.path());
    let tls = Arc::new(ServerTls::load(&cert_file, &key_file).unwrap());
    let shards = shard_server(grid_scene("grid", 2, 2, 10, 8, Dtype::F16, 1), None).await;
    let (_dir, store) = fetch_grid(&shards.url, 100.0).await;
    let (gate, _open) = GateEmbedder::with_guard(8);
    let opts = ServeOptions {
        tls: Some(tls),
        ..grid_serve_options(None, false)
    };
    let state = AppState::new(store, gate.clone(), opts).unwrap();
    let url = serve_on_loopback(state)
        .await
        .replace("http://", "https://");
    let health = async || {
        let r = send(https(&ca).get(format!("{url}/health"))).await;
        assert_eq!(r.status(), 200);
        peer(&r)
    };
    assert_eq!(health().await, first.der);
    let reload = async || {
        let r = send(https(&ca).post(format!("{url}/reload"))).await;
        let status = r.status().as_u16();
        (status, r.json::<serde_json::Value>().await.unwrap())
    };

    // t1 waits at the gate: an answer in flight on a connection of the first certificate.
    let held = {
        let (client, u) = (https(&ca), format!("{url}/query?text=t1&top_k=3"));
        tokio::spawn(async move { client.get(u).send().await.unwrap() })
    };
    wait_until("t1 is scanning", async || gate.entered() == ["t1"]).await;

    second.write(certs.path());
    let (status, body) = reload().await;
    assert_eq!(status, 200);
    assert_eq!(
        body["tls_certificate_sha256"],
        fingerprint(&second.der),
        "{body}"
    );
    assert_eq!(health().await, second.der);

    gate.release(1);
    let answer = held.await.unwrap();
    assert_eq!(answer.status(), 200);
    assert_eq!(peer(&answer), first.der);
    let answer: serde_json::Value = answer.json().await.unwrap();
    assert_eq!(answer["matches"].as_array().unwrap().len(), 3, "{answer}");

    // A certificate file that does not load: refused, and the certificate in use stays.
    std::fs::write(&cert_file, "not a certificate\n").unwrap();
    let (status, body) = reload().await;
    assert_eq!(status, 500);
    let message = body["error"].as_str().unwrap();
    assert!(
        message.contains("stays") && message.contains("cert.pem"),
        "{message}"
    );
    assert_eq!(health().await, second.der);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fetch_over_https_trusts_the_ca_given_and_refuses_a_server_without_it() {
    let ca = TestCa::new("slag shard test CA");
    let certs = tempfile::tempdir().unwrap();
    let (cert_file, key_file) = ca.server_cert(7).write(certs.path());
    let tls = Arc::new(ServerTls::load(&cert_file, &key_file).unwrap());
    let shards = shard_server_tls(grid_scene("grid", 2, 2, 10, 8, Dtype::F16, 1), tls).await;
    let ca_file = certs.path().join("ca.pem");
    std::fs::write(&ca_file, &ca.pem).unwrap();

    let (_dir, store) = temp_store();
    let without = fetch(&store, &grid_fetch_params(&shards.url, 100.0)).await;
    match without {
        Err(Error::Network {
            status: None,
            message,
            ..
        }) => assert!(message.contains("TLS certificate"), "{message}"),
        other => panic!("fetched from an untrusted server: {other:?}"),
    }
    let p = FetchParams {
        ca_cert: Some(ca_file.clone()),
        ..grid_fetch_params(&shards.url, 100.0)
    };
    let summary = fetch(&store, &p).await.unwrap();
    assert_eq!(summary.selected, 4, "{summary:?}");
    assert_eq!(summary.downloaded, 4, "{summary:?}");

    // The command line: refused with the flag to pass, then fetched with it.
    let dir = tempfile::tempdir().unwrap();
    let edge_store = dir.path().join("store").display().to_string();
    let args = fetch_args(&shards.url, &edge_store, "100");
    let out = output_blocking(slag_edge_with_log(&args, "warn")).await;
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "fetched without the CA: {err}");
    assert!(err.contains("--ca-cert"), "{err}");
    let ca_arg = ca_file.display().to_string();
    let with_ca = [&args[..], &["--ca-cert", &ca_arg]].concat();
    assert_success(
        &output_blocking(slag_edge_with_log(&with_ca, "warn")).await,
        "fetch --ca-cert",
    );
}

/// `slag-edge serve` on `addr` with the bearer token `tok` (environment) and `extra` flags,
/// over a store that does not exist: what it printed when it stopped.
async fn serve_stderr(addr: &str, extra: &[&str]) -> String {
    let args = [
        &[
            "serve",
            "--scene",
            "grid",
            "--store",
            "/nonexistent/store",
            "--clip-textual",
            "m.onnx",
            "--tokenizer",
            "t.json",
            "--listen",
            addr,
        ][..],
        extra,
    ]
    .concat();
    let mut cmd = slag_edge_with_log(&args, "warn");
    cmd.env("SLAG_EDGE_TOKEN", "tok");
    let out = output_blocking(cmd).await;
    assert!(
        !out.status.success(),
        "served from a store that does not exist"
    );
    String::from_utf8_lossy(&out.stderr).into_owned()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_token_over_plain_http_off_loopback_needs_allow_plain_http() {
    let err = serve_stderr("0.0.0.0:0", &[]).await;
    for needed in ["0.0.0.0", "--tls-cert", "--tls-key", "--allow-plain-http"] {
        assert!(err.contains(needed), "{needed}: {err}");
    }
    // Allowed explicitly, or on loopback: it goes on to open the store.
    for (addr, extra) in [
        ("0.0.0.0:0", &["--allow-plain-http"][..]),
        ("127.0.0.1:0", &[]),
        ("[::1]:0", &[]),
    ] {
        let err = serve_stderr(addr, extra).await;
        assert!(!err.contains("plain_http"), "{addr} {extra:?}: {err}");
        assert!(
            err.contains("/nonexistent/store"),
            "{addr} {extra:?}: {err}"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bad_certificate_file_refuses_to_start_naming_the_file() {
    let ca = TestCa::new("slag edge test CA");
    let certs = tempfile::tempdir().unwrap();
    let (cert_file, key_file) = ca.server_cert(1).write(certs.path());
    std::fs::write(&key_file, "-----BEGIN PRIVATE KEY-----\nAAAA\n").unwrap();
    let (c, k) = (
        cert_file.display().to_string(),
        key_file.display().to_string(),
    );
    let err = serve_stderr("127.0.0.1:0", &["--tls-cert", &c, "--tls-key", &k]).await;
    assert!(err.contains(&k) && err.contains("private key"), "{err}");
    let err = serve_stderr("127.0.0.1:0", &["--tls-cert", &c]).await;
    assert!(err.contains("--tls-key"), "{err}");
}

/// The binary: `serve --tls-cert --tls-key` answers a query over HTTPS and `SIGHUP` gives new
/// connections the certificate written since. Needs ONNX Runtime (the color-clip text tower).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_binary_serves_https_and_reloads_its_certificate_on_sighup() {
    use std::io::{BufRead, BufReader};
    if support::skip_without_ort() {
        return;
    }
    let ca = TestCa::new("slag edge test CA");
    let (first, second) = (ca.server_cert(1), ca.server_cert(2));
    let certs = tempfile::tempdir().unwrap();
    let (c, k) = first.write(certs.path());
    let (c, k) = (c.display().to_string(), k.display().to_string());
    let shards = shard_server(grid_scene("grid", 2, 2, 10, 512, Dtype::F16, 1), None).await;
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store").display().to_string();
    let fetch = slag_edge_with_log(&fetch_args(&shards.url, &store, "100"), "warn");
    assert_success(&output_blocking(fetch).await, "fetch");
    let [tm, tok] = support::color_clip_text_model();
    let serve = support::text_model_args("serve", &store, "grid", [&tm, &tok]);
    let tls = ["--listen", "127.0.0.1:0", "--tls-cert", &c, "--tls-key", &k];
    let mut child = slag_edge_with_log(&[&serve[..], &tls].concat(), "info")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = child.stderr.take().unwrap();
    let url = tokio::task::spawn_blocking(move || {
        let mut lines = BufReader::new(stderr).lines().map_while(|l| l.ok());
        let line = lines
            .find(|l| l.contains("listening on https://"))
            .expect("serve logs its address");
        // Keep reading so that the child never blocks on a full pipe.
        std::thread::spawn(move || lines.for_each(drop));
        let at = line.find("https://").unwrap();
        line[at..].trim().to_string()
    })
    .await
    .unwrap();
    let r = send(https(&ca).get(format!("{url}/query?text=pink&top_k=2&threshold=none"))).await;
    assert_eq!(r.status(), 200);
    assert_eq!(peer(&r), first.der);

    second.write(certs.path());
    let hup = std::process::Command::new("kill")
        .args(["-HUP", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(hup.success());
    wait_until("SIGHUP reloads the certificate", async || {
        let r = send(https(&ca).get(format!("{url}/health"))).await;
        peer(&r) == second.der
    })
    .await;
    let _ = child.kill();
    let _ = child.wait();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_wrong_scheme_on_either_side_says_which_scheme_to_use() {
    let ca = TestCa::new("slag edge test CA");
    let certs = tempfile::tempdir().unwrap();
    let (cert_file, key_file) = ca.server_cert(1).write(certs.path());
    let tls = Arc::new(ServerTls::load(&cert_file, &key_file).unwrap());
    let secure = shard_server_tls(grid_scene("grid", 2, 2, 10, 8, Dtype::F16, 1), tls).await;
    let plain = shard_server(grid_scene("grid", 2, 2, 10, 8, Dtype::F16, 1), None).await;
    let (_dir, store) = temp_store();
    let http_to_tls = secure.url.replacen("https://", "http://", 1);
    let e = fetch(&store, &grid_fetch_params(&http_to_tls, 100.0))
        .await
        .unwrap_err();
    assert!(e.to_string().contains("use https://"), "{e}");
    let https_to_plain = plain.url.replacen("http://", "https://", 1);
    let e = fetch(&store, &grid_fetch_params(&https_to_plain, 100.0))
        .await
        .unwrap_err();
    assert!(e.to_string().contains("use http://"), "{e}");
}

#[test]
fn a_damaged_certificate_at_a_reload_is_named_as_the_certificate() {
    let ca = TestCa::new("slag edge test CA");
    let certs = tempfile::tempdir().unwrap();
    let (cert_file, key_file) = ca.server_cert(1).write(certs.path());
    let tls = ServerTls::load(&cert_file, &key_file).unwrap();
    // Base64 still, so still PEM, but the DER inside no longer parses.
    let pem = std::fs::read_to_string(&cert_file).unwrap();
    let mut lines: Vec<String> = pem.lines().map(str::to_string).collect();
    for l in lines.iter_mut().skip(2).take(4) {
        *l = "A".repeat(l.len());
    }
    std::fs::write(&cert_file, lines.join("\n") + "\n").unwrap();
    let e = slag_common::tls::log_reload(&tls, "SIGHUP").unwrap_err();
    let m = e.to_string();
    assert!(m.contains(&cert_file.display().to_string()), "{m}");
    assert!(m.contains("not a valid X.509 certificate"), "{m}");
    assert!(!m.contains("this key cannot serve"), "{m}");
}

/// A log line buffer for a test's tracing subscriber.
#[derive(Clone, Default)]
struct LogBuffer(Arc<std::sync::Mutex<Vec<u8>>>);

impl std::io::Write for LogBuffer {
    fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
        self.0.lock().unwrap().extend_from_slice(b);
        Ok(b.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

/// Sends a plain HTTP/1.1 GET of `path` to `addr` (`HOST:PORT`) and reads the answer to its end.
async fn plain_get(addr: &str, path: &str) -> String {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    let req = format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nUser-Agent: test\r\n\r\n");
    s.write_all(req.as_bytes()).await.unwrap();
    let mut answer = Vec::new();
    tokio::time::timeout(
        std::time::Duration::from_secs(10),
        s.read_to_end(&mut answer),
    )
    .await
    .expect("the server answers and closes")
    .unwrap();
    String::from_utf8_lossy(&answer).into_owned()
}

/// The server side of a wrong scheme: `http://` to the TLS port of `serve` and of the shard
/// server gets a plain 400 whose JSON body names the `https://` URL to use, the server logs it,
/// and HTTPS still answers on the same port. (The current-thread runtime runs the servers'
/// tasks on this thread, where the log subscriber is set.)
#[tokio::test]
async fn plain_http_to_a_tls_port_is_answered_400_naming_https_and_logged() {
    let log = LogBuffer::default();
    let writer = log.clone();
    let _guard = tracing::subscriber::set_default(
        tracing_subscriber::fmt()
            .with_ansi(false)
            .with_max_level(tracing::Level::WARN)
            .with_writer(move || writer.clone())
            .finish(),
    );
    let ca = TestCa::new("slag edge test CA");
    let certs = tempfile::tempdir().unwrap();
    let (cert_file, key_file) = ca.server_cert(1).write(certs.path());
    let tls = Arc::new(ServerTls::load(&cert_file, &key_file).unwrap());
    let shards =
        shard_server_tls(grid_scene("grid", 2, 2, 10, 8, Dtype::F16, 1), tls.clone()).await;
    let plain = shard_server(grid_scene("grid", 2, 2, 10, 8, Dtype::F16, 1), None).await;
    let (_dir, store) = fetch_grid(&plain.url, 100.0).await;
    let (gate, _open) = GateEmbedder::with_guard(8);
    let opts = ServeOptions {
        tls: Some(tls),
        ..grid_serve_options(None, false)
    };
    let edge = serve_on_loopback(AppState::new(store, gate, opts).unwrap()).await;
    for (url, path) in [
        (edge.as_str(), "/health"),
        (shards.url.as_str(), "/v1/scenes/grid/manifest"),
    ] {
        let addr = url.split("://").nth(1).unwrap().trim_end_matches('/');
        let answer = plain_get(addr, &format!("{path}?x=1")).await;
        assert!(answer.starts_with("HTTP/1.1 400 "), "{url}: {answer}");
        assert!(
            answer.contains(&format!("use https://{addr}{path}\"")),
            "{url}: {answer}"
        );
        let body = answer.split("\r\n\r\n").nth(1).unwrap();
        let json: serde_json::Value = serde_json::from_str(body).unwrap();
        assert_eq!(json["status"], 400, "{body}");
        let https_url = format!("https://{addr}{path}");
        assert_eq!(send(https(&ca).get(https_url)).await.status(), 200, "{url}");
    }
    let logged = String::from_utf8(log.0.lock().unwrap().clone()).unwrap();
    let lines: Vec<&str> = logged
        .lines()
        .filter(|l| l.contains("plain HTTP request (GET /health) on this HTTPS port"))
        .collect();
    assert_eq!(lines.len(), 1, "{logged}");
    assert!(
        lines[0].contains("WARN") && lines[0].contains("use https://"),
        "{logged}"
    );
    assert!(
        logged.contains("plain HTTP request (GET /v1/scenes/grid/manifest) on this HTTPS port"),
        "{logged}"
    );
}
