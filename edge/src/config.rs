//! `slag-edge serve --config edge.toml`: the same settings as the command-line flags, as TOML
//! (keys = long flag names with `_`). Flags given on the command line win over the file.
//!
//! ```toml
//! store = "/var/lib/slag/store"
//! scene = "site"
//! listen = "0.0.0.0:8080"
//! clip_textual = "/opt/slag/models/clip-textual.onnx"
//! tokenizer = "/opt/slag/models/tokenizer.json"
//! ep = "cpu"            # or "cuda" with JetPack's ONNX Runtime
//! threshold = 0.28
//! token_file = "/etc/slag/token"
//! shard_token_file = "/etc/slag/shard-token"   # POST /fetch's token (else env SLAG_SHARD_TOKEN)
//! trusted_key = "/etc/slag/manifest-key.pub.pem"  # POST /fetch refuses unsigned maps; check verifies
//! hnsw = false
//! hnsw_backend = "instant-distance"   # or "qdrant-edge" (binary built with --features qdrant-edge)
//! max_scans = 1         # scans at once (each uses every core)
//! scan_queue = 32       # waiting queries; one more gets 503 + Retry-After
//! ros2 = true           # also run the ROS 2 node (slag_edge::ros2) beside HTTP
//! ros2_node = "slag"    # its name; topics are <ros2_namespace>/<ros2_node>/{prompt,objects,…}
//! ros2_namespace = "/"
//! ros2_frame_id = "map" # header.frame_id of what it publishes
//! max_matches = 20000   # matches one request may ask for (sum of top_k over a batch)
//! header_timeout = 10   # seconds to send a request head; also the idle keep-alive timeout
//! write_timeout = 30    # seconds a write to a client may stall before it is dropped
//! max_connections = 512 # open connections; keep below LimitNOFILE - 64
//! body_timeout = 10     # seconds a request body has to arrive after its head
//! max_connections_per_ip = 64   # connections one address may hold; one more gets 429
//! tls_cert = "/etc/slag/tls/cert.pem"   # HTTPS: PEM chain; SIGHUP / POST /reload re-read it
//! tls_key = "/etc/slag/tls/key.pem"
//! allow_plain_http = false   # true: a token over plain HTTP on a non-loopback listen address
//! ca_cert = "/etc/slag/shard-ca.pem"    # POST /fetch: a private CA for an https:// server
//! ```
//!
//! The DDS domain is `ROS_DOMAIN_ID` from the environment, as for every ROS 2 node.

use std::path::{Path, PathBuf};

use slag_common::{Error, Result};

/// Settings read from the TOML file; every key optional.
#[derive(Debug, Clone, Default, PartialEq, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServeConfig {
    /// Store folder.
    pub store: Option<PathBuf>,
    /// Scene id.
    pub scene: Option<String>,
    /// Listen address, e.g. `0.0.0.0:8080` (also read under its older key `addr`).
    #[serde(alias = "addr")]
    pub listen: Option<String>,
    /// CLIP text tower ONNX (also read under its older key `text_model`).
    #[serde(alias = "text_model")]
    pub clip_textual: Option<PathBuf>,
    /// CLIP tokenizer (`tokenizer.json`).
    pub tokenizer: Option<PathBuf>,
    /// ONNX Runtime execution provider: `cpu` or `cuda`.
    pub ep: Option<String>,
    /// Default cosine threshold.
    pub threshold: Option<f32>,
    /// File holding the bearer token.
    pub token_file: Option<PathBuf>,
    /// File holding the shard server's bearer token, sent by `POST /fetch` (else env
    /// `SLAG_SHARD_TOKEN`).
    pub shard_token_file: Option<PathBuf>,
    /// The publisher's Ed25519 public key (PEM): `POST /fetch` accepts only manifests it signed
    /// (`crate::fetch::FetchParams::trusted_keys`; the file may hold several PEM blocks: a key
    /// rotation); `check` verifies the store with it, and every load hashes the stored tiles.
    pub trusted_key: Option<PathBuf>,
    /// Build the HNSW index.
    pub hnsw: Option<bool>,
    /// Its backend: `instant-distance` or `qdrant-edge` (parsed by
    /// `slag_edge::scan::hnsw::HnswBackend::from_name`).
    pub hnsw_backend: Option<String>,
    /// Scans running at once (`slag_edge::serve::DEFAULT_MAX_SCANS` when absent).
    pub max_scans: Option<usize>,
    /// Queries that may wait for a scan (`slag_edge::serve::DEFAULT_SCAN_QUEUE` when absent).
    pub scan_queue: Option<usize>,
    /// Run the ROS 2 node beside HTTP ([`crate::ros2`]).
    pub ros2: Option<bool>,
    /// ROS 2 node name ([`crate::ros2::DEFAULT_NODE_NAME`] when absent).
    pub ros2_node: Option<String>,
    /// ROS 2 namespace of the node ([`crate::ros2::DEFAULT_NAMESPACE`] when absent).
    pub ros2_namespace: Option<String>,
    /// `header.frame_id` of the node's messages ([`crate::ros2::DEFAULT_FRAME_ID`] when absent).
    pub ros2_frame_id: Option<String>,
    /// Matches one request may ask for in all, Σ `top_k` over a batch
    /// (`slag_edge::serve::DEFAULT_MAX_MATCHES`, 20,000, when absent).
    pub max_matches: Option<usize>,
    /// Header-read and idle keep-alive timeout, seconds
    /// (`slag_common::http::DEFAULT_HEADER_TIMEOUT`, 10 s, when absent).
    pub header_timeout: Option<f64>,
    /// Write timeout, seconds: a client that reads nothing for this long is dropped
    /// (`slag_common::http::DEFAULT_WRITE_TIMEOUT`, 30 s, when absent).
    pub write_timeout: Option<f64>,
    /// Connections open at once (`slag_common::http::DEFAULT_MAX_CONNECTIONS`, 512, when
    /// absent); lowered with a warning to the open-file limit minus 64.
    pub max_connections: Option<usize>,
    /// Body-read timeout, seconds: a request body must arrive within it of the request head
    /// (`slag_common::http::DEFAULT_BODY_TIMEOUT`, 10 s, when absent).
    pub body_timeout: Option<f64>,
    /// Connections one remote address may hold at once
    /// (`slag_common::http::DEFAULT_MAX_CONNECTIONS_PER_IP`, 64, when absent).
    pub max_connections_per_ip: Option<usize>,
    /// HTTPS: the PEM certificate chain (with `tls_key`).
    pub tls_cert: Option<PathBuf>,
    /// HTTPS: the PEM private key of `tls_cert`.
    pub tls_key: Option<PathBuf>,
    /// Allow a bearer token over plain HTTP on a non-loopback address (refused when absent or
    /// false: `slag_common::tls::check_token_transport`).
    pub allow_plain_http: Option<bool>,
    /// A private CA certificate (PEM) `POST /fetch` trusts for an `https://` shard server, in
    /// addition to the built-in roots.
    pub ca_cert: Option<PathBuf>,
}

impl ServeConfig {
    /// Reads and parses a config file.
    ///
    /// Errors: [`Error::Io`] when unreadable, [`Error::Format`] for bad TOML or unknown keys
    /// (the message names the key and line).
    pub fn read(path: &Path) -> Result<ServeConfig> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        toml::from_str(&text).map_err(|e| Error::format(path, format!("config: {e}")))
    }
}

/// Reads a bearer token from a file (first line, trimmed): [`slag_common::auth::read_token_file`].
pub use slag_common::auth::read_token_file as read_token;

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    /// [`ServeConfig::read`] of a file holding `text`.
    fn read_config(text: &str) -> Result<ServeConfig> {
        let file = tempfile::NamedTempFile::new().unwrap();
        std::fs::write(file.path(), text).unwrap();
        ServeConfig::read(file.path())
    }

    #[test]
    fn example_config_parses_and_unknown_keys_are_rejected() {
        let c = read_config(
            "store = \"/s\"\nscene = \"site\"\naddr = \"0.0.0.0:8080\"\nthreshold = 0.3\nhnsw = true\n\
             hnsw_backend = \"qdrant-edge\"\n",
        )
        .unwrap();
        assert_eq!(c.scene.as_deref(), Some("site"));
        // `addr` and `text_model` are the older keys of `listen` and `clip_textual`.
        assert_eq!(c.listen.as_deref(), Some("0.0.0.0:8080"));
        let old = read_config("text_model = \"t.onnx\"\n").unwrap();
        assert_eq!(old.clip_textual, Some(PathBuf::from("t.onnx")));
        assert_eq!(c.threshold, Some(0.3));
        assert_eq!(c.hnsw, Some(true));
        assert_eq!(c.hnsw_backend.as_deref(), Some("qdrant-edge"));
        let e = read_config("scene = \"a\"\nradius = 3\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("radius"), "{e}");
        // An empty token file is refused.
        let empty = tempfile::NamedTempFile::new().unwrap();
        assert!(read_token(empty.path()).is_err());
    }

    #[test]
    fn the_shipped_jetson_config_parses_with_every_key() {
        let c: ServeConfig = toml::from_str(include_str!("../../jetson/edge.toml")).unwrap();
        assert!(c.store.is_some() && c.scene.is_some() && c.listen.is_some());
        assert!(c.clip_textual.is_some() && c.tokenizer.is_some() && c.token_file.is_some());
        assert_eq!(c.ep.as_deref(), Some("cpu"));
        assert_eq!(c.threshold, Some(0.28));
        assert_eq!(c.hnsw, Some(false));
        assert_eq!(c.hnsw_backend.as_deref(), Some("instant-distance"));
        assert_eq!(c.max_scans, Some(1));
        assert_eq!(c.scan_queue, Some(32));
        assert_eq!(c.ros2, Some(false));
        assert_eq!(c.ros2_node.as_deref(), Some("slag"));
        assert_eq!(c.ros2_namespace.as_deref(), Some("/"));
        assert_eq!(c.ros2_frame_id.as_deref(), Some("map"));
        assert_eq!(c.max_matches, Some(20_000));
        assert_eq!(c.header_timeout, Some(10.0));
        assert_eq!(c.write_timeout, Some(30.0));
        assert_eq!(c.max_connections, Some(512));
        assert_eq!(c.body_timeout, Some(10.0));
        assert_eq!(c.max_connections_per_ip, Some(64));
        assert_eq!(c.allow_plain_http, Some(true));
        assert_eq!((c.tls_cert, c.tls_key, c.ca_cert), (None, None, None));
    }
}
