//! TLS for both HTTP servers (`slag-edge serve`, `slag-shards serve`): the server's certificate
//! chain and private key from PEM files, swapped in place when they are read again, and the
//! rule that a bearer token never crosses a network in clear text (behind the cargo feature
//! `server`).
//!
//! rustls with the `ring` provider (pure Rust and `ring`: the aarch64 cross build needs no C
//! library beyond ring's own), TLS 1.2 and 1.3, ALPN `http/1.1`. The handshake runs inside the
//! servers' one connection loop ([`crate::http::serve_with_tls`]), so every connection limit and
//! timeout holds for TLS connections too; a handshake must end within the header-read timeout.
//!
//! # Certificates and reloading
//!
//! [`ServerTls::load`] reads a PEM chain (the server's certificate first, then the intermediates)
//! and a PEM private key (PKCS#8, PKCS#1 RSA or SEC1 EC) and checks that the key belongs to the
//! certificate. [`ServerTls::reload`] reads the same two files again: new connections get the new
//! certificate, open connections keep the one they were opened with. A file that does not load
//! (missing, not PEM, no certificate, a key of another certificate) is refused with the error and
//! the certificate in use stays. The servers reload on `SIGHUP` ([`reload_on_hangup`]), and
//! `slag-edge serve` also on `POST /reload`.

use std::path::{Path, PathBuf};
use std::sync::{Arc, RwLock};

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use rustls::server::{ClientHello, ResolvesServerCert};
use rustls::sign::CertifiedKey;

use crate::{Error, Result};

/// The protocol every server speaks over TLS (ALPN): HTTP/1.1.
pub const ALPN_HTTP1: &[u8] = b"http/1.1";

/// A server's TLS identity: its certificate chain and key, read from two PEM files and read
/// again by [`ServerTls::reload`] (module doc).
pub struct ServerTls {
    cert_path: PathBuf,
    key_path: PathBuf,
    current: Arc<Current>,
    config: Arc<rustls::ServerConfig>,
}

impl std::fmt::Debug for ServerTls {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ServerTls")
            .field("cert_path", &self.cert_path)
            .field("key_path", &self.key_path)
            .field("fingerprint", &self.fingerprint())
            .finish()
    }
}

/// The certificate new handshakes get, shared by [`ServerTls`] and its rustls configuration.
struct Current(RwLock<Arc<CertifiedKey>>);

impl std::fmt::Debug for Current {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Current")
    }
}

impl ResolvesServerCert for Current {
    fn resolve(&self, _hello: ClientHello<'_>) -> Option<Arc<CertifiedKey>> {
        Some(self.0.read().unwrap_or_else(|p| p.into_inner()).clone())
    }
}

impl ServerTls {
    /// Reads the PEM certificate chain at `cert` and the PEM private key at `key`.
    ///
    /// Errors: [`Error::Io`] when a file cannot be read; [`Error::Format`] naming the file when
    /// it holds no PEM certificate (or no PEM private key), a certificate that does not parse, a
    /// key of a type rustls cannot sign with, or a key that does not belong to the first
    /// certificate.
    pub fn load(cert: &Path, key: &Path) -> Result<ServerTls> {
        let certified = read_certified_key(cert, key)?;
        let current = Arc::new(Current(RwLock::new(Arc::new(certified))));
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let mut config = rustls::ServerConfig::builder_with_provider(provider)
            .with_protocol_versions(rustls::DEFAULT_VERSIONS)
            .map_err(|e| Error::internal(format!("TLS configuration: {e}")))?
            .with_no_client_auth()
            .with_cert_resolver(current.clone());
        config.alpn_protocols = vec![ALPN_HTTP1.to_vec()];
        Ok(ServerTls {
            cert_path: cert.to_path_buf(),
            key_path: key.to_path_buf(),
            current,
            config: Arc::new(config),
        })
    }

    /// Reads the certificate and key files again; new connections get the new certificate,
    /// open ones keep theirs. Returns the new certificate's SHA-256 fingerprint.
    ///
    /// Errors: as [`ServerTls::load`]; the certificate in use then stays.
    pub fn reload(&self) -> Result<String> {
        let certified = read_certified_key(&self.cert_path, &self.key_path)?;
        let fingerprint = certified
            .cert
            .first()
            .map(|c| fingerprint(c.as_ref()))
            .unwrap_or_default();
        *self.current.0.write().unwrap_or_else(|p| p.into_inner()) = Arc::new(certified);
        Ok(fingerprint)
    }

    /// The SHA-256 fingerprint of the certificate new connections get: 32 bytes as
    /// colon-separated upper-case hex (`AB:CD:…`), as `openssl x509 -fingerprint -sha256` shows it.
    pub fn fingerprint(&self) -> String {
        let current = self.current.0.read().unwrap_or_else(|p| p.into_inner());
        current
            .cert
            .first()
            .map(|c| fingerprint(c.as_ref()))
            .unwrap_or_default()
    }

    /// The certificate file.
    pub fn cert_path(&self) -> &Path {
        &self.cert_path
    }

    /// The acceptor that runs the server side of a handshake with the current certificate.
    pub fn acceptor(&self) -> tokio_rustls::TlsAcceptor {
        tokio_rustls::TlsAcceptor::from(self.config.clone())
    }
}

/// The SHA-256 fingerprint of a DER certificate, as [`ServerTls::fingerprint`] writes it.
pub fn fingerprint(der: &[u8]) -> String {
    let digest = ring::digest::digest(&ring::digest::SHA256, der);
    let hex: Vec<String> = digest.as_ref().iter().map(|b| format!("{b:02X}")).collect();
    hex.join(":")
}

/// Reads `path` whole.
fn read(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|e| Error::io(path, e))
}

fn read_certified_key(cert: &Path, key: &Path) -> Result<CertifiedKey> {
    let chain = read_chain(cert)?;
    let key_pem = read(key)?;
    let key_der = PrivateKeyDer::from_pem_slice(&key_pem).map_err(|e| {
        Error::format(
            key,
            format!(
                "no PEM private key ({e}): the key file must hold the certificate's private key \
                 as PEM (-----BEGIN PRIVATE KEY-----, RSA PRIVATE KEY or EC PRIVATE KEY)"
            ),
        )
    })?;
    let provider = rustls::crypto::ring::default_provider();
    CertifiedKey::from_der(chain, key_der, &provider).map_err(|e| match e {
        // The certificate itself does not parse: a damaged file names the certificate, not the
        // key.
        rustls::Error::InvalidCertificate(_) | rustls::Error::NoCertificatesPresented => {
            Error::format(
                cert,
                format!(
                    "not a valid X.509 certificate ({e}): the file is damaged or not the \
                     certificate as issued; put the issued certificate (PEM) back"
                ),
            )
        }
        rustls::Error::InconsistentKeys(_) => Error::format(
            key,
            format!(
                "this key cannot serve the certificate {}: {e}; pass the private key the \
                 certificate was issued for (an RSA, ECDSA P-256/P-384 or Ed25519 key)",
                cert.display()
            ),
        ),
        e => Error::format(
            key,
            format!(
                "the private key cannot be used ({e}): pass an RSA, ECDSA P-256/P-384 or \
                 Ed25519 key in PEM"
            ),
        ),
    })
}

/// The PEM certificates of `path`, the server's own first.
fn read_chain(path: &Path) -> Result<Vec<CertificateDer<'static>>> {
    let pem = read(path)?;
    let chain = CertificateDer::pem_slice_iter(&pem)
        .collect::<std::result::Result<Vec<_>, _>>()
        .map_err(|e| Error::format(path, format!("not a PEM certificate chain: {e}")))?;
    if chain.is_empty() {
        return Err(Error::format(
            path,
            "no PEM certificate (-----BEGIN CERTIFICATE-----): the certificate file must hold \
             the server's certificate, then its intermediates",
        ));
    }
    Ok(chain)
}

/// Reads the certificate again on every `SIGHUP` until `stop` completes, logging the new
/// certificate's fingerprint, or the error and that the old certificate stays. Spawned on the
/// current tokio runtime; on other platforms than Unix it does nothing.
pub fn reload_on_hangup(
    tls: Arc<ServerTls>,
    stop: impl std::future::Future<Output = ()> + Send + 'static,
) {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        let mut hangup = match signal(SignalKind::hangup()) {
            Ok(s) => s,
            Err(e) => {
                tracing::warn!("SIGHUP cannot reload the TLS certificate: {e}");
                return;
            }
        };
        tokio::spawn(async move {
            let mut stop = std::pin::pin!(stop);
            loop {
                tokio::select! {
                    s = hangup.recv() => if s.is_none() { break },
                    () = &mut stop => break,
                }
                let _ = log_reload(&tls, "SIGHUP");
            }
        });
    }
    #[cfg(not(unix))]
    {
        let _ = (tls, stop);
    }
}

/// [`ServerTls::reload`], logged: the new fingerprint, or the error and that the old
/// certificate stays. `why` says what asked for it (`SIGHUP`, `POST /reload`).
///
/// Errors: as [`ServerTls::reload`].
pub fn log_reload(tls: &ServerTls, why: &str) -> Result<String> {
    match tls.reload() {
        Ok(f) => {
            tracing::info!(
                "{why}: TLS certificate reloaded from {} (SHA-256 {f})",
                tls.cert_path.display()
            );
            Ok(f)
        }
        Err(e) => {
            tracing::error!(
                "{why}: TLS certificate not reloaded, the one in use stays (SHA-256 {}): {e}",
                tls.fingerprint()
            );
            Err(e)
        }
    }
}

/// Refuses a server with a bearer token that would listen in clear text on a network address:
/// the token would cross the network readable by anyone on the path. Allowed: no token, TLS, a
/// loopback address (127.0.0.0/8, ::1, IPv4-mapped loopback), or `allow_plain_http`.
///
/// Errors: [`Error::Param`] `plain_http` naming the address.
pub fn check_token_transport(
    addr: std::net::SocketAddr,
    token: bool,
    tls: bool,
    allow_plain_http: bool,
) -> Result<()> {
    if !token || tls || allow_plain_http || addr.ip().to_canonical().is_loopback() {
        return Ok(());
    }
    Err(Error::param(
        "plain_http",
        addr,
        "TLS (a certificate and its key), a loopback address (127.0.0.0/8, ::1), or plain HTTP \
         allowed explicitly: a server with a bearer token on a network address over plain HTTP \
         would send the token in clear text",
    ))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn a_token_over_plain_http_is_refused_off_loopback_only() {
        let a = |s: &str| s.parse::<std::net::SocketAddr>().unwrap();
        for ok in [
            "127.0.0.1:80",
            "127.9.9.9:80",
            "[::1]:80",
            "[::ffff:127.0.0.1]:80",
        ] {
            assert!(
                check_token_transport(a(ok), true, false, false).is_ok(),
                "{ok}"
            );
        }
        for bad in ["0.0.0.0:8080", "10.0.0.2:80", "[::]:80"] {
            let e = check_token_transport(a(bad), true, false, false).unwrap_err();
            assert!(
                matches!(
                    e,
                    Error::Param {
                        name: "plain_http",
                        ..
                    }
                ),
                "{bad}: {e}"
            );
            assert!(check_token_transport(a(bad), true, true, false).is_ok());
            assert!(check_token_transport(a(bad), true, false, true).is_ok());
            assert!(check_token_transport(a(bad), false, false, false).is_ok());
        }
    }

    #[test]
    fn files_without_a_certificate_or_key_are_refused_with_their_path() {
        let dir = tempfile::tempdir().unwrap();
        let junk = dir.path().join("junk.pem");
        std::fs::write(&junk, "not pem\n").unwrap();
        match ServerTls::load(&junk, &junk) {
            Err(Error::Format { path, .. }) => assert_eq!(path, junk),
            other => panic!("{other:?}"),
        }
        let absent = dir.path().join("absent.pem");
        assert!(matches!(
            ServerTls::load(&absent, &junk),
            Err(Error::Io { .. })
        ));
    }
}
