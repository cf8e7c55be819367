//! `slag-edge serve --config edge.toml`: the same settings as the command-line flags, as TOML
//! (keys = long flag names with `_`). Flags given on the command line win over the file.
//!
//! ```toml
//! store = "/var/lib/slag/store"
//! scene = "site"
//! addr = "0.0.0.0:8080"
//! text_model = "/opt/slag/models/clip-textual.onnx"
//! tokenizer = "/opt/slag/models/tokenizer.json"
//! ep = "cpu"            # or "cuda" with JetPack's ONNX Runtime
//! threshold = 0.28
//! token_file = "/etc/slag/token"
//! shard_token_file = "/etc/slag/shard-token"   # POST /fetch's token (else env SLAG_SHARD_TOKEN)
//! hnsw = false
//! hnsw_backend = "instant-distance"   # or "qdrant-edge" (binary built with --features qdrant-edge)
//! max_scans = 1         # scans at once (each uses every core)
//! scan_queue = 32       # waiting queries; one more gets 503 + Retry-After
//! ```

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
    /// Listen address, e.g. `0.0.0.0:8080`.
    pub addr: Option<String>,
    /// CLIP text tower ONNX.
    pub text_model: Option<PathBuf>,
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
    /// Build the HNSW index.
    pub hnsw: Option<bool>,
    /// Its backend: `instant-distance` or `qdrant-edge` (parsed by
    /// `slag_edge::scan::hnsw::HnswBackend::from_name`).
    pub hnsw_backend: Option<String>,
    /// Scans running at once (`slag_edge::serve::DEFAULT_MAX_SCANS` when absent).
    pub max_scans: Option<usize>,
    /// Queries that may wait for a scan (`slag_edge::serve::DEFAULT_SCAN_QUEUE` when absent).
    pub scan_queue: Option<usize>,
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

    #[test]
    fn example_config_parses_and_unknown_keys_are_rejected() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("edge.toml");
        std::fs::write(
            &p,
            "store = \"/s\"\nscene = \"site\"\naddr = \"0.0.0.0:8080\"\nthreshold = 0.3\nhnsw = true\n\
             hnsw_backend = \"qdrant-edge\"\n",
        )
        .unwrap();
        let c = ServeConfig::read(&p).unwrap();
        assert_eq!(c.scene.as_deref(), Some("site"));
        assert_eq!(c.threshold, Some(0.3));
        assert_eq!(c.hnsw, Some(true));
        assert_eq!(c.hnsw_backend.as_deref(), Some("qdrant-edge"));
        std::fs::write(&p, "scene = \"a\"\nradius = 3\n").unwrap();
        let e = ServeConfig::read(&p).unwrap_err().to_string();
        assert!(e.contains("radius"), "{e}");
        std::fs::write(&p, "").unwrap();
        assert!(read_token(&p).is_err());
    }

    #[test]
    fn the_shipped_jetson_config_parses_with_every_key() {
        let c: ServeConfig = toml::from_str(include_str!("../../jetson/edge.toml")).unwrap();
        assert!(c.store.is_some() && c.scene.is_some() && c.addr.is_some());
        assert!(c.text_model.is_some() && c.tokenizer.is_some() && c.token_file.is_some());
        assert_eq!(c.ep.as_deref(), Some("cpu"));
        assert_eq!(c.threshold, Some(0.28));
        assert_eq!(c.hnsw, Some(false));
        assert_eq!(c.hnsw_backend.as_deref(), Some("instant-distance"));
        assert_eq!(c.max_scans, Some(1));
        assert_eq!(c.scan_queue, Some(32));
    }
}
