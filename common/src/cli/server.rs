//! The options both HTTP servers take (`slag-shards serve`, `slag-edge serve`), declared once:
//! where to listen, the bearer token, TLS and the connection limits. A flag left out is `None`,
//! so the edge can fill it from its config file before the defaults apply.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use crate::http::ServerLimits;
use crate::tls::ServerTls;
use crate::{Error, Result};

/// The shard server's listen address when `--listen` is not given: loopback, on the port the
/// documentation's examples use for the shard server.
pub const DEFAULT_SHARD_LISTEN: &str = "127.0.0.1:8090";
/// `slag-edge serve`'s listen address when neither `--listen` nor the config file gives one.
pub const DEFAULT_EDGE_LISTEN: &str = "0.0.0.0:8080";

/// The server flags both HTTP servers take.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct ServerArgs {
    /// Listen address (default 127.0.0.1:8090 for the shard server, 0.0.0.0:8080 for
    /// slag-edge).
    #[arg(long, aliases = ["addr", "bind"], value_name = "HOST:PORT")]
    pub listen: Option<String>,
    /// File whose first line is the bearer token clients must send (also env SLAG_SHARD_TOKEN
    /// for the shard server, SLAG_EDGE_TOKEN for slag-edge); without either the server is open.
    #[arg(long, value_name = "FILE")]
    pub token_file: Option<PathBuf>,
    /// Serve HTTPS with this PEM certificate chain (the server's certificate first, then its
    /// intermediates); needs --tls-key. SIGHUP reads both files again (new connections get the
    /// new certificate; a file that does not load is refused and the old one stays).
    #[arg(long, value_name = "FILE")]
    pub tls_cert: Option<PathBuf>,
    /// The PEM private key of --tls-cert (PKCS#8, RSA or EC).
    #[arg(long, value_name = "FILE")]
    pub tls_key: Option<PathBuf>,
    /// Serve a bearer token over plain HTTP on a network (non-loopback) address, where anyone on
    /// the path can read it. Without it, a token with a non-loopback --listen needs --tls-cert.
    #[arg(long)]
    pub allow_plain_http: bool,
    /// Seconds a connection has to send a whole request head (and to finish its TLS
    /// handshake); also the idle keep-alive timeout (default 10).
    #[arg(long, value_name = "SECONDS")]
    pub header_timeout: Option<f64>,
    /// Seconds a write to a client may make no progress (a client that stopped reading) before
    /// its connection is closed (default 30).
    #[arg(long, value_name = "SECONDS")]
    pub write_timeout: Option<f64>,
    /// Connections open at once; further ones wait in the listen queue (default 512). Kept 64
    /// below the open-file limit (ulimit -n, LimitNOFILE), lowered with a warning where not.
    #[arg(long, value_name = "N")]
    pub max_connections: Option<usize>,
    /// Seconds a request body has to arrive after its head; later gets 408 and the connection
    /// is closed (default 10).
    #[arg(long, value_name = "SECONDS")]
    pub body_timeout: Option<f64>,
    /// Connections one remote address (IPv4 address, IPv6 /64) may hold at once; one more is
    /// answered 429 and closed (default 64).
    #[arg(long, value_name = "N")]
    pub max_connections_per_ip: Option<usize>,
}

impl ServerArgs {
    /// The address to listen on: `--listen`, else `default`.
    ///
    /// Errors: [`Error::Param`] `listen` for anything but `HOST:PORT` with a numeric host.
    pub fn listen_addr(&self, default: &str) -> Result<SocketAddr> {
        let text = self.listen.as_deref().unwrap_or(default);
        text.trim()
            .parse()
            .map_err(|_| Error::param("listen", text, "HOST:PORT, e.g. 0.0.0.0:8080"))
    }

    /// The connection limits these flags set, each one left out at its default
    /// ([`ServerLimits::default`]).
    ///
    /// Errors: [`Error::Param`] naming the flag's field for a timeout that is not a finite
    /// number of seconds > 0 or a connection limit of 0.
    pub fn limits(&self) -> Result<ServerLimits> {
        let d = ServerLimits::default();
        let secs = |v: Option<f64>, fallback: Duration, name: &'static str| match v {
            None => Ok(fallback),
            Some(v) => Duration::try_from_secs_f64(v)
                .ok()
                .filter(|d| !d.is_zero())
                .ok_or_else(|| Error::param(name, v, "seconds > 0")),
        };
        let limits = ServerLimits {
            header_timeout: secs(self.header_timeout, d.header_timeout, "header_timeout")?,
            write_timeout: secs(self.write_timeout, d.write_timeout, "write_timeout")?,
            body_timeout: secs(self.body_timeout, d.body_timeout, "body_timeout")?,
            max_connections: self.max_connections.unwrap_or(d.max_connections),
            max_connections_per_ip: self
                .max_connections_per_ip
                .unwrap_or(d.max_connections_per_ip),
        };
        limits.validate()?;
        Ok(limits)
    }

    /// The TLS certificate and key of `--tls-cert` / `--tls-key`, `None` without either.
    ///
    /// Errors: [`Error::Param`] `tls_cert` / `tls_key` when only one of the two is given; as
    /// [`ServerTls::load`] (unreadable files, no PEM certificate or key, a key of another
    /// certificate).
    pub fn tls(&self) -> Result<Option<Arc<ServerTls>>> {
        match (&self.tls_cert, &self.tls_key) {
            (None, None) => Ok(None),
            (Some(c), Some(k)) => Ok(Some(Arc::new(ServerTls::load(c, k)?))),
            (Some(c), None) => Err(Error::param(
                "tls_key",
                format!("none for {}", c.display()),
                "the certificate's private key",
            )),
            (None, Some(k)) => Err(Error::param(
                "tls_cert",
                format!("none for {}", k.display()),
                "the certificate chain of the key",
            )),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Server {
        #[command(flatten)]
        server: ServerArgs,
    }

    fn parse(args: &[&str]) -> ServerArgs {
        Server::try_parse_from(std::iter::once("x").chain(args.iter().copied()))
            .map(|s| s.server)
            .unwrap_or_else(|e| panic!("{args:?}: {e}"))
    }

    #[test]
    fn left_out_flags_take_the_defaults() {
        let a = parse(&[]);
        assert_eq!(a.limits().ok(), Some(ServerLimits::default()));
        assert_eq!(
            a.listen_addr(DEFAULT_SHARD_LISTEN).ok(),
            DEFAULT_SHARD_LISTEN.parse().ok()
        );
        assert!(matches!(a.tls(), Ok(None)));
    }

    #[test]
    fn flags_and_their_older_spellings_set_the_limits_and_address() {
        let a = parse(&["--bind", "0.0.0.0:9", "--header-timeout", "2.5"]);
        assert_eq!(
            a.listen_addr(DEFAULT_EDGE_LISTEN).ok(),
            "0.0.0.0:9".parse().ok()
        );
        let l = a.limits().ok();
        assert_eq!(
            l.map(|l| l.header_timeout),
            Some(Duration::from_millis(2500))
        );
    }

    #[test]
    fn bad_values_are_named_errors() {
        let zero = parse(&["--write-timeout", "0"]);
        assert!(matches!(
            zero.limits(),
            Err(Error::Param {
                name: "write_timeout",
                ..
            })
        ));
        let nan = parse(&["--body-timeout", "NaN"]);
        assert!(matches!(
            nan.limits(),
            Err(Error::Param {
                name: "body_timeout",
                ..
            })
        ));
        let host = parse(&["--listen", "localhost"]);
        assert!(matches!(
            host.listen_addr(""),
            Err(Error::Param { name: "listen", .. })
        ));
        let half = parse(&["--tls-cert", "c.pem"]);
        assert!(matches!(
            half.tls(),
            Err(Error::Param {
                name: "tls_key",
                ..
            })
        ));
    }
}
