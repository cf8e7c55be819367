//! The shard server over HTTPS (`slag-shards serve --tls-cert --tls-key`), with a CA and server
//! certificates made at test time: answers over TLS, the connection limits and timeouts of the
//! plain server also for TLS (a stalled handshake is closed and frees its slot; an address over
//! its share gets its 429 over TLS), SIGHUP swapping the certificate for new connections while
//! an open one keeps working, a bad file refused at start-up and at reload, and a bearer token
//! refused over plain HTTP off loopback unless `--allow-plain-http`.
#![allow(clippy::unwrap_used)]

mod support;

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use slag_common::http::ServerLimits;
use slag_common::testing::{
    TestCa, TlsClient, assert_json_error, closed_within, exchange_tls, get_request as get,
    peer_certificate, read_answer, served_address, tls_client_config, tls_connect,
};
use slag_common::tls::ServerTls;
use tokio::io::AsyncWriteExt;

/// The lab store served over TLS with `tls` under `limits`; returns `127.0.0.1:port`.
async fn start(tls: Arc<ServerTls>, limits: ServerLimits) -> (String, tempfile::TempDir) {
    support::serve_lab(None, limits, Some(tls)).await
}

/// The lab store served over TLS under `limits` with a certificate of a new CA: the address, a
/// client trusting that CA, the certificate (DER), and the folders to keep.
async fn start_certified(
    limits: ServerLimits,
) -> (String, TlsClient, Vec<u8>, [tempfile::TempDir; 2]) {
    let ca = TestCa::new("slag test CA");
    let cert = ca.server_cert(1);
    let certs = tempfile::tempdir().unwrap();
    let (c, k) = cert.write(certs.path());
    let tls = Arc::new(ServerTls::load(&c, &k).unwrap());
    let (addr, dir) = start(tls, limits).await;
    (addr, tls_client_config(&ca.der), cert.der, [certs, dir])
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn https_answers_and_a_stalled_handshake_is_closed_and_frees_its_slot() {
    let (addr, client, der, _dirs) = start_certified(support::limits(1, 1, 1)).await;
    let (status, _, body, cert) = exchange_tls(&addr, &client, &get("/v1/scenes", "")).await;
    assert_eq!(status, 200, "{body}");
    assert!(body.contains("lab"), "{body}");
    assert_eq!(cert, der, "the server presents its certificate");
    let s = tls_connect(&addr, &client).await;
    assert_eq!(s.get_ref().1.alpn_protocol(), Some(&b"http/1.1"[..]));
    drop(s);

    // A client that connects and never starts its handshake holds the only slot until the
    // header timeout; then the next client is served.
    let mut silent = tokio::net::TcpStream::connect(&addr).await.unwrap();
    tokio::time::sleep(Duration::from_millis(100)).await;
    let t0 = Instant::now();
    let (status, _, body, _) = exchange_tls(&addr, &client, &get("/v1/scenes", "")).await;
    assert_eq!(status, 200, "{body}");
    assert!(
        t0.elapsed() >= Duration::from_millis(500),
        "answered while the stalled handshake held the only slot"
    );
    closed_within(&mut silent, Duration::from_secs(10)).await;

    // After a handshake, a connection that sends no request head is closed after the header
    // timeout too.
    let mut idle = tls_connect(&addr, &client).await;
    closed_within(&mut idle, Duration::from_secs(10)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_address_over_its_share_gets_its_429_over_tls() {
    let (addr, client, _, _dirs) = start_certified(support::limits(30, 8, 2)).await;
    let _held = [
        tls_connect(&addr, &client).await,
        tls_connect(&addr, &client).await,
    ];
    let mut third = tls_connect(&addr, &client).await;
    let (status, head, body) = read_answer(&mut third).await;
    assert_eq!(status, 429, "{head}\n{body}");
    assert_json_error(429, &head, &body);
}

/// `slag-shards ARGS` started with stdout and stderr piped.
fn shards(args: &[&str], env: &[(&str, &str)]) -> Child {
    let mut c = Command::new(env!("CARGO_BIN_EXE_slag-shards"));
    c.args(args)
        .env_remove("SLAG_SHARD_TOKEN")
        .env("RUST_LOG", "info")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    for (k, v) in env {
        c.env(k, v);
    }
    c.spawn().unwrap()
}

/// `slag-shards serve` of `store` on a free loopback port over TLS with `cert` and `key` (PEM
/// paths), started as [`shards`] starts it.
fn serve_tls_on_loopback(store: &str, cert: &str, key: &str) -> Child {
    let args = ["serve", "--shard-store", store, "--listen", "127.0.0.1:0"];
    shards(
        &[&args[..], &["--tls-cert", cert, "--tls-key", key]].concat(),
        &[],
    )
}

/// Sends `SIGHUP` to `child`.
fn hang_up(child: &Child) {
    let ok = Command::new("kill")
        .args(["-HUP", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(ok.success());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sighup_swaps_the_certificate_for_new_connections_and_a_bad_file_keeps_the_old_one() {
    let (dir, store) = support::lab_store();
    drop(store);
    let ca = TestCa::new("slag test CA");
    let (first, second) = (ca.server_cert(1), ca.server_cert(2));
    let certs = tempfile::tempdir().unwrap();
    let (c, k) = first.write(certs.path());
    let (c, k) = (c.display().to_string(), k.display().to_string());
    let store = dir.path().display().to_string();
    let mut child = serve_tls_on_loopback(&store, &c, &k);
    let addr = served_address(&mut child);
    let stderr = child.stderr.take().unwrap();
    let (log_tx, log_rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            let _ = log_tx.send(line);
        }
    });
    let client = tls_client_config(&ca.der);
    // A connection opened with the first certificate, kept alive across the reloads.
    let mut open = tls_connect(&addr, &client).await;
    assert_eq!(peer_certificate(&open), first.der);

    second.write(certs.path());
    hang_up(&child);
    let t0 = Instant::now();
    loop {
        let s = tls_connect(&addr, &client).await;
        if peer_certificate(&s) == second.der {
            break;
        }
        assert_eq!(peer_certificate(&s), first.der);
        assert!(
            t0.elapsed() < Duration::from_secs(20),
            "SIGHUP did not reload"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // The connection opened before the reload still answers, with its certificate.
    open.write_all(&get("/v1/scenes", "")).await.unwrap();
    let (status, _, body) = read_answer(&mut open).await;
    assert_eq!(status, 200, "{body}");
    assert_eq!(peer_certificate(&open), first.der);

    // A file that does not load is refused (logged) and the certificate in use stays.
    std::fs::write(&c, "not a certificate\n").unwrap();
    hang_up(&child);
    let refused = wait_for_log(&log_rx, "not reloaded");
    assert!(refused.contains(&c), "{refused}");
    let (status, _, body, cert) = exchange_tls(&addr, &client, &get("/v1/scenes", "")).await;
    assert_eq!(status, 200, "{body}");
    assert_eq!(cert, second.der);
    let _ = child.kill();
    let _ = child.wait();
}

/// The first log line containing `needle` (at most 20 s).
fn wait_for_log(log: &std::sync::mpsc::Receiver<String>, needle: &str) -> String {
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        match log.recv_timeout(left) {
            Ok(line) if line.contains(needle) => return line,
            Ok(_) => {}
            Err(e) => panic!("no log line with {needle:?}: {e}"),
        }
    }
}

#[test]
fn a_bad_certificate_file_refuses_to_start_naming_the_file() {
    let ca = TestCa::new("slag test CA");
    let certs = tempfile::tempdir().unwrap();
    let (c, k) = ca.server_cert(1).write(certs.path());
    // Another certificate's key: a typed error naming the key file.
    let other = ca.server_cert(2);
    let wrong_key = certs.path().join("other-key.pem");
    std::fs::write(&wrong_key, &other.key_pem).unwrap();
    match ServerTls::load(&c, &wrong_key) {
        Err(slag_common::Error::Format { path, .. }) => assert_eq!(path, wrong_key),
        other => panic!("{other:?}"),
    }
    std::fs::write(&c, "-----BEGIN CERTIFICATE-----\nAAAA\n").unwrap();
    let dir = tempfile::tempdir().unwrap();
    let (c, k) = (c.display().to_string(), k.display().to_string());
    let out = serve_tls_on_loopback(&dir.path().display().to_string(), &c, &k)
        .wait_with_output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success(),
        "started with a bad certificate: {err}"
    );
    assert!(err.contains(&c) && err.contains("certificate"), "{err}");
}

#[test]
fn a_token_over_plain_http_off_loopback_needs_allow_plain_http() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().display().to_string();
    let token = [("SLAG_SHARD_TOKEN", "s3cret")];
    let serve = |bind: &str, extra: &[&str]| {
        let args = [&["serve", "--shard-store", &store, "--listen", bind][..], extra].concat();
        shards(&args, &token)
    };
    let out = serve("0.0.0.0:0", &[]).wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "served a token in clear text: {err}");
    for flag in ["--tls-cert", "--tls-key", "--allow-plain-http", "0.0.0.0"] {
        assert!(err.contains(flag), "{flag}: {err}");
    }
    // Allowed explicitly, and on loopback, it starts.
    for (bind, extra) in [
        ("0.0.0.0:0", &["--allow-plain-http"][..]),
        ("127.0.0.1:0", &[]),
    ] {
        let mut child = serve(bind, extra);
        let addr = served_address(&mut child);
        assert!(addr.ends_with(|c: char| c.is_ascii_digit()), "{addr}");
        let _ = child.kill();
        let _ = child.wait();
    }
}
