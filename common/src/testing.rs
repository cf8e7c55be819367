//! Raw-socket clients for the integration tests of the HTTP servers (`slag-edge serve`, the shard
//! server): one request on a fresh connection, the JSON error body, and waiting for the server
//! to close a connection; over TLS too, with a private CA and server certificates made at test
//! time ([`TestCa`]). Behind the `testing` feature, which only dev-dependencies turn on; these
//! helpers panic (with what went wrong) instead of returning errors.

use std::time::{Duration, Instant};

use std::sync::Arc;

use tokio::io::{AsyncRead, AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// Sends `raw` on a fresh connection to `addr` (`host:port`) and reads until the server closes
/// it (at most 30 s): (status, head, body). Status 0 when the answer has no status line.
///
/// Panics when the connection fails or stays open for 30 s.
pub async fn exchange(addr: &str, raw: &[u8]) -> (u16, String, String) {
    let mut s = TcpStream::connect(addr).await.expect("connect");
    s.write_all(raw).await.expect("send the request");
    read_answer(&mut s).await
}

/// [`exchange`], asserting that the answer is the servers' JSON error body with `status`
/// ([`assert_json_error`]).
///
/// Panics as [`exchange`], and when the answer is another.
pub async fn exchange_error(addr: &str, raw: &[u8], status: u16) {
    let (got, head, body) = exchange(addr, raw).await;
    assert_eq!(got, status, "{head}");
    assert_json_error(status, &head, &body);
}

/// [`exchange`] from the local address `source` (another loopback address such as 127.0.0.2 is
/// another client to the server's per-address share).
///
/// Panics as [`exchange`].
pub async fn exchange_from(
    source: std::net::IpAddr,
    addr: &str,
    raw: &[u8],
) -> (u16, String, String) {
    let mut s = connect_from(source, addr).await;
    s.write_all(raw).await.expect("send the request");
    read_answer(&mut s).await
}

/// A connection to `addr` (`ip:port`) from the local address `source` (any port).
///
/// Panics when `addr` is not `ip:port` or the connection fails.
pub async fn connect_from(source: std::net::IpAddr, addr: &str) -> TcpStream {
    let to: std::net::SocketAddr = addr.parse().expect("addr is ip:port");
    let sock = if source.is_ipv4() {
        tokio::net::TcpSocket::new_v4()
    } else {
        tokio::net::TcpSocket::new_v6()
    }
    .expect("socket");
    sock.bind(std::net::SocketAddr::new(source, 0))
        .expect("bind the source address");
    sock.connect(to).await.expect("connect")
}

/// Reads an answer until the server closes `s` (at most 30 s): (status, head, body). Status 0
/// when the answer has no status line.
///
/// Panics when the read fails or the connection stays open for 30 s.
pub async fn read_answer(s: &mut (impl AsyncRead + Unpin)) -> (u16, String, String) {
    let mut out = Vec::new();
    tokio::time::timeout(Duration::from_secs(30), s.read_to_end(&mut out))
        .await
        .expect("the server answers and closes within 30 s")
        .expect("read the answer");
    let text = String::from_utf8_lossy(&out).into_owned();
    let (head, body) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
    let status = head.split(' ').nth(1).unwrap_or("0").parse().unwrap_or(0);
    (status, head.to_string(), body.to_string())
}

/// An HTTP/1.1 `GET path` that asks the server to close the connection after its answer;
/// `extra` is more header lines, each ending in `\r\n`.
pub fn get_request(path: &str, extra: &str) -> Vec<u8> {
    format!("GET {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n{extra}\r\n").into_bytes()
}

/// `n` connections to `addr` (`host:port`) that each send only the request line
/// `GET {path} HTTP/1.1` and then nothing: stalled request heads, each holding a connection slot
/// until the server's header timeout closes it.
///
/// Panics when a connection or a send fails.
pub async fn stalled_heads(addr: &str, n: usize, path: &str) -> Vec<TcpStream> {
    let line = format!("GET {path} HTTP/1.1\r\n");
    let mut stalled = Vec::with_capacity(n);
    for _ in 0..n {
        let mut s = TcpStream::connect(addr).await.expect("connect");
        s.write_all(line.as_bytes())
            .await
            .expect("send the request line");
        stalled.push(s);
    }
    stalled
}

/// The connection limit under stalled clients: opens `n` [`stalled_heads`] to `addr`, asserts
/// that `GET path` on a fresh connection is still answered 200 with `expect` in its body, then
/// that the server closes every stalled connection within 30 s (its header timeout).
///
/// Panics as [`exchange`], and when an assertion fails.
pub async fn assert_answered_while_stalled(addr: &str, n: usize, path: &str, expect: &str) {
    let mut stalled = stalled_heads(addr, n, path).await;
    let (status, _, body) = exchange(addr, &get_request(path, "")).await;
    assert_eq!(status, 200, "{body}");
    assert!(body.contains(expect), "{body}");
    for s in &mut stalled {
        closed_within(s, Duration::from_secs(30)).await;
    }
}

/// One address flooding a server whose per-address share is below its connection limit: `n`
/// connections from 127.0.0.1 each send `unfinished` (a request cut short) and stay open; then
/// asserts that `GET path` from 127.0.0.2 is answered 200 within 20 s and that one more
/// connection from 127.0.0.1 is refused with the JSON 429. Returns the flood's connections and
/// the 429's head and body.
///
/// Panics when a connection fails or an assertion fails.
pub async fn flood_from_one_address(
    addr: &str,
    n: usize,
    unfinished: &[u8],
    path: &str,
) -> (Vec<TcpStream>, String, String) {
    let flood: std::net::IpAddr = "127.0.0.1".parse().expect("loopback");
    let other: std::net::IpAddr = "127.0.0.2".parse().expect("loopback");
    let mut stalled = Vec::with_capacity(n);
    for _ in 0..n {
        let mut s = connect_from(flood, addr).await;
        let _ = s.write_all(unfinished).await;
        stalled.push(s);
    }
    let (status, _, body) = tokio::time::timeout(
        Duration::from_secs(20),
        exchange_from(other, addr, &get_request(path, "")),
    )
    .await
    .expect("another address is answered while one address floods the server");
    assert_eq!(status, 200, "{body}");
    let mut s = connect_from(flood, addr).await;
    let (status, head, body) = read_answer(&mut s).await;
    assert_eq!(status, 429, "{head}\n{body}");
    assert_json_error(429, &head, &body);
    (stalled, head, body)
}

/// Asserts that the server at `addr` answers `GET path` carrying the header line `one` (an
/// accepted `Authorization` header, ending in `\r\n`) with 200, and answers 401 with the JSON
/// error body when the request carries two `Authorization` headers: `one` twice, or `one` with
/// a wrong one after or before it.
///
/// Panics as [`exchange`], and when an answer is not the one asserted.
pub async fn assert_two_authorizations_refused(addr: &str, path: &str, one: &str) {
    let (status, _, body) = exchange(addr, &get_request(path, one)).await;
    assert_eq!(status, 200, "{body}");
    for two in [
        format!("{one}{one}"),
        format!("{one}Authorization: Bearer wrong\r\n"),
        format!("Authorization: Bearer wrong\r\n{one}"),
    ] {
        let (status, head, body) = exchange(addr, &get_request(path, &two)).await;
        assert_eq!(status, 401, "{two}: {body}");
        assert_json_error(401, &head, &body);
    }
}

/// Asserts that a server started with the token variable `var` set blank refused to start: it
/// failed, and its stderr names `var`, says "blank" and gives a `hint:`.
pub fn assert_blank_token_refused(out: &std::process::Output, var: &str) {
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "started with a blank token: {err}");
    assert!(err.contains(var) && err.contains("blank"), "{err}");
    assert!(err.contains("hint:"), "{err}");
}

/// Asserts that an answer is the servers' JSON error body with `status`: a JSON content type,
/// `"status": status` and a non-empty `"error"`.
pub fn assert_json_error(status: u16, head: &str, body: &str) {
    assert!(
        head.to_ascii_lowercase()
            .contains("content-type: application/json"),
        "{status}: {head}"
    );
    let v: serde_json::Value = serde_json::from_str(body).unwrap_or_else(|e| panic!("{e}: {body}"));
    assert_eq!(v["status"], status, "{v}");
    assert!(v["error"].as_str().is_some_and(|e| !e.is_empty()), "{v}");
}

/// Waits (at most `bound`) until the server closes `s`, reading and dropping what it sends;
/// returns how long that took. Panics when the connection is still open after `bound`.
pub async fn closed_within(s: &mut (impl AsyncRead + Unpin), bound: Duration) -> Duration {
    let t0 = Instant::now();
    let mut buf = [0u8; 4096];
    loop {
        match tokio::time::timeout(bound.saturating_sub(t0.elapsed()), s.read(&mut buf)).await {
            Ok(Ok(0) | Err(_)) => return t0.elapsed(),
            Ok(Ok(_)) => {}
            Err(_) => panic!("the connection is still open after {bound:?}"),
        }
    }
}

/// A private certificate authority made at test time (ECDSA P-256), and server certificates it
/// issues for `localhost` and 127.0.0.1.
pub struct TestCa {
    issuer: rcgen::Issuer<'static, rcgen::KeyPair>,
    /// The CA's certificate, PEM (what `--ca-cert` is given).
    pub pem: String,
    /// The CA's certificate, DER.
    pub der: Vec<u8>,
}

/// A server certificate of a [`TestCa`]: PEM chain and key, and the certificate's DER (what a
/// client sees as the peer's certificate).
pub struct ServerCert {
    /// The certificate, PEM.
    pub cert_pem: String,
    /// Its private key, PEM (PKCS#8).
    pub key_pem: String,
    /// The certificate, DER.
    pub der: Vec<u8>,
}

impl TestCa {
    /// A new CA named `name`.
    ///
    /// Panics when rcgen fails.
    pub fn new(name: &str) -> TestCa {
        let key = rcgen::KeyPair::generate().expect("CA key");
        let mut params = rcgen::CertificateParams::new(Vec::<String>::new()).expect("CA params");
        params.is_ca = rcgen::IsCa::Ca(rcgen::BasicConstraints::Unconstrained);
        params
            .distinguished_name
            .push(rcgen::DnType::CommonName, name);
        params.key_usages = vec![
            rcgen::KeyUsagePurpose::KeyCertSign,
            rcgen::KeyUsagePurpose::CrlSign,
            rcgen::KeyUsagePurpose::DigitalSignature,
        ];
        let cert = params.self_signed(&key).expect("CA certificate");
        TestCa {
            pem: cert.pem(),
            der: cert.der().to_vec(),
            issuer: rcgen::Issuer::new(params, key),
        }
    }

    /// A server certificate for `localhost` and 127.0.0.1 with serial number `serial`.
    ///
    /// Panics when rcgen fails.
    pub fn server_cert(&self, serial: u64) -> ServerCert {
        let key = rcgen::KeyPair::generate().expect("server key");
        let mut params =
            rcgen::CertificateParams::new(vec!["localhost".to_string(), "127.0.0.1".to_string()])
                .expect("server params");
        params.serial_number = Some(rcgen::SerialNumber::from(serial));
        params
            .distinguished_name
            .push(rcgen::DnType::CommonName, "localhost");
        let cert = params
            .signed_by(&key, &self.issuer)
            .expect("server certificate");
        ServerCert {
            cert_pem: cert.pem(),
            key_pem: key.serialize_pem(),
            der: cert.der().to_vec(),
        }
    }
}

impl ServerCert {
    /// Writes the certificate and key to `cert.pem` and `key.pem` in `dir` (replacing them);
    /// returns both paths.
    ///
    /// Panics when a write fails.
    pub fn write(&self, dir: &std::path::Path) -> (std::path::PathBuf, std::path::PathBuf) {
        let (cert, key) = (dir.join("cert.pem"), dir.join("key.pem"));
        std::fs::write(&cert, &self.cert_pem).expect("write cert.pem");
        std::fs::write(&key, &self.key_pem).expect("write key.pem");
        (cert, key)
    }
}

/// A TLS client configuration of [`tls_client_config`] (for tests that do not depend on rustls).
pub type TlsClient = Arc<rustls::ClientConfig>;

/// A TLS client configuration (rustls, ring) that trusts only the CA certificate `ca_der`,
/// offers ALPN `http/1.1` and never resumes a session (every connection runs a full handshake
/// and sees the certificate the server presents now).
///
/// Panics when the certificate is not one.
pub fn tls_client_config(ca_der: &[u8]) -> Arc<rustls::ClientConfig> {
    let mut roots = rustls::RootCertStore::empty();
    roots
        .add(rustls::pki_types::CertificateDer::from(ca_der.to_vec()))
        .expect("a CA certificate");
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut config = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .expect("TLS versions")
        .with_root_certificates(roots)
        .with_no_client_auth();
    config.alpn_protocols = vec![b"http/1.1".to_vec()];
    config.resumption = rustls::client::Resumption::disabled();
    Arc::new(config)
}

/// A TLS connection to `addr` (`ip:port`) as server `localhost`.
///
/// Panics when the connection or the handshake fails.
pub async fn tls_connect(
    addr: &str,
    config: &Arc<rustls::ClientConfig>,
) -> tokio_rustls::client::TlsStream<TcpStream> {
    try_tls_connect(addr, config)
        .await
        .unwrap_or_else(|e| panic!("TLS handshake with {addr}: {e}"))
}

/// [`tls_connect`], the handshake's error returned.
///
/// Panics when the TCP connection fails.
pub async fn try_tls_connect(
    addr: &str,
    config: &Arc<rustls::ClientConfig>,
) -> std::io::Result<tokio_rustls::client::TlsStream<TcpStream>> {
    let tcp = TcpStream::connect(addr).await.expect("connect");
    let name = rustls::pki_types::ServerName::try_from("localhost").expect("server name");
    tokio_rustls::TlsConnector::from(config.clone())
        .connect(name, tcp)
        .await
}

/// The DER certificate the server presented on `s`.
///
/// Panics when it presented none.
pub fn peer_certificate(s: &tokio_rustls::client::TlsStream<TcpStream>) -> Vec<u8> {
    s.get_ref()
        .1
        .peer_certificates()
        .and_then(|c| c.first())
        .expect("the server presented a certificate")
        .to_vec()
}

/// [`exchange`] over TLS: (status, head, body) and the certificate the server presented.
///
/// Panics as [`exchange`] and [`tls_connect`].
pub async fn exchange_tls(
    addr: &str,
    config: &Arc<rustls::ClientConfig>,
    raw: &[u8],
) -> (u16, String, String, Vec<u8>) {
    let mut s = tls_connect(addr, config).await;
    let cert = peer_certificate(&s);
    s.write_all(raw).await.expect("send the request");
    let (status, head, body) = read_answer(&mut s).await;
    (status, head, body, cert)
}

/// Copies the folder `from` (files and subfolders, recursively) to `to`, creating it: a store
/// copied before each run of a test that changes it.
///
/// Panics when a file cannot be read or written.
pub fn copy_dir(from: &std::path::Path, to: &std::path::Path) {
    std::fs::create_dir_all(to).expect("create the copy's folder");
    for e in std::fs::read_dir(from).expect("list the folder") {
        let e = e.expect("read a folder entry");
        if e.file_type().expect("file type").is_dir() {
            copy_dir(&e.path(), &to.join(e.file_name()));
        } else {
            std::fs::copy(e.path(), to.join(e.file_name())).expect("copy a file");
        }
    }
}

/// The `host:port` a started `serve` (`slag-shards serve`, `slag-encoder serve`) listens on, from
/// the first line of its stdout (`serving on SCHEME://ADDR/v1/...`).
///
/// Panics when the child's stdout is not piped, cannot be read, or its first line holds no
/// address.
pub fn served_address(child: &mut std::process::Child) -> String {
    use std::io::BufRead;
    let mut line = String::new();
    std::io::BufReader::new(child.stdout.as_mut().expect("the child's stdout is piped"))
        .read_line(&mut line)
        .expect("read the server's first line");
    let rest = line
        .split("://")
        .nth(1)
        .unwrap_or_else(|| panic!("no address in {line:?}"));
    rest.split('/').next().unwrap_or_default().to_string()
}
