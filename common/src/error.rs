//! Typed errors shared by every slag crate.
//!
//! Every variant carries the offending path (where there is one) and a message that tells the user
//! what to do next. Library code never panics on bad input; it returns one of these.

use std::path::PathBuf;

/// Result alias used across slag.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// What went wrong, with enough context to fix it.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file or folder involved.
        path: PathBuf,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// A file exists but its content is malformed (truncated, wrong header, NaN values, ...).
    #[error("{path}: {message}")]
    Format {
        /// The file involved.
        path: PathBuf,
        /// What is wrong and how to fix it.
        message: String,
    },
    /// A valid file describes something slag does not support (e.g. a distorted camera model).
    #[error("{path}: unsupported: {message}")]
    Unsupported {
        /// The file involved.
        path: PathBuf,
        /// What is unsupported and what to do instead.
        message: String,
    },
    /// An ONNX model is missing, fails to load, or has the wrong signature for its role.
    #[error("model {path}: {message}")]
    Model {
        /// The `.onnx` file.
        path: PathBuf,
        /// What is wrong (expected vs found signature) and what to pass instead.
        message: String,
    },
    /// A model failed to load or run on its execution provider (out of GPU memory, a missing CUDA
    /// library, a driver/runtime mismatch, a provider the runtime lacks): names the model, the
    /// provider, the GPU and what to do (`onnx::remedy`).
    #[error("model {model} on {device}: {message}; {remedy}")]
    Inference {
        /// The `.onnx` file.
        model: PathBuf,
        /// The provider that failed (`cpu`, `cuda`, `tensorrt`).
        provider: String,
        /// Where: `cpu`, `cuda:0`, ...
        device: String,
        /// ONNX Runtime's / CUDA's message, with the step that failed.
        message: String,
        /// What to do about it.
        remedy: String,
    },
    /// A CLIP text tower from another model than the image tower that made the embeddings: their
    /// cosines would be meaningless, so the text side refuses it.
    #[error(
        "model {text_path}: this CLIP text tower is model `{text_model}` but the embeddings were \
         made with the image tower of `{embeddings_model}`; pass the text tower exported together \
         with that image tower (ONNX metadata `slag.clip_pair_id` = `{embeddings_model}`, or a \
         file named `{embeddings_model}-textual.onnx`)"
    )]
    ModelMismatch {
        /// The text tower's `.onnx` file.
        text_path: PathBuf,
        /// The text tower's model id.
        text_model: String,
        /// The model id recorded with the embeddings (shard manifest / embeddings file).
        embeddings_model: String,
    },
    /// A library parameter outside its domain (a scale, a count, a size, a choice): `name` is the
    /// parameter's library name (`raster_scale`, `every`, `max_per_shard`, `radius`, ...), `value`
    /// what was given, `expected` what is accepted. The user's to fix (HTTP 400); a command line
    /// maps `name` to its flag.
    #[error("{name} = {value}: expected {expected}")]
    Param {
        /// The parameter, as the library spells it (a field or argument name).
        name: &'static str,
        /// The value given.
        value: String,
        /// What is accepted, e.g. `a value in (0, 4], e.g. 0.5`.
        expected: String,
    },
    /// A query refused before it runs: a blank or too long prompt, a query field (`top_k`,
    /// `threshold`, `bbox`, `mode`, `index`, `frame`) outside its domain or not available here,
    /// or a prompt whose embedding has no direction. The caller's to fix (HTTP 400).
    #[error("{message}")]
    Query {
        /// The field as the query API spells it (`text` for the prompt; `query` for the query as
        /// a whole: not an object, an unknown key).
        field: &'static str,
        /// What is wrong and what is accepted.
        message: String,
    },
    /// Inputs that are each well-formed but do not belong together (an image and its camera of
    /// different sizes, a query vector of another width than the stored embeddings, embeddings
    /// of another scene): `what` says which property differs (HTTP 409).
    #[error("{message}")]
    Mismatch {
        /// The property that differs.
        what: Mismatched,
        /// Both sides, and which input to replace.
        message: String,
    },
    /// Any other input the user has to fix, in words (a folder in use by another process, an
    /// empty token file, ...) (HTTP 400). Cases a caller could act on get their own variant.
    #[error("invalid input: {0}")]
    Invalid(String),
    /// A shard that does not decode (truncated, corrupted, foreign, another format version): the
    /// typed cause, so a caller can re-download, skip or upgrade.
    #[error(transparent)]
    Shard(#[from] crate::shards::ShardError),
    /// The work needs more of a bounded resource than there is (a GPU buffer, a file-format
    /// field, memory): names the resource, what was needed and the limit. Library code states
    /// the limit; a command line adds the flag that lowers the need.
    #[error("{resource}: {needed} needed, the limit is {limit}")]
    Limit {
        /// What is bounded.
        resource: Resource,
        /// What this run needs, with its unit.
        needed: String,
        /// The bound, with its unit.
        limit: String,
    },
    /// An encode whose views observe none of the scene's Gaussians, or far fewer than they should:
    /// its map would be empty or mostly empty, so it is refused instead of written. `stage` says
    /// which count fell short; the scene, its cameras or the view and raster settings are the
    /// user's to change (HTTP 400).
    #[error("{stage}: {observed} of {gaussians} Gaussians observed, {expected}")]
    Unobserved {
        /// Where the Gaussians were counted.
        stage: Observation,
        /// Gaussians observed there.
        observed: u64,
        /// Gaussians of the scene.
        gaussians: u64,
        /// What was expected instead, in words (e.g. `at least 1`, `the chosen views see
        /// 812,000 in the coverage pass`).
        expected: String,
    },
    /// Something that must not happen did (a panicked worker task, a broken invariant): a bug in
    /// slag, never the user's input (HTTP 500).
    #[error(
        "internal fault: {0}; this is a slag bug, please report it with the command that failed"
    )]
    Internal(String),
    /// The GPU (wgpu) could not be used or a kernel failed.
    #[error("gpu: {0}")]
    Gpu(String),
    /// A shard manifest, its signature or a file it lists that the trusted publisher's key does
    /// not vouch for ([`crate::shards::signature`]): unsigned, signed by another key, changed
    /// after signing, a tile whose SHA-256 differs from the signed one, or an older generation
    /// than the one already accepted. `what` says which; nothing of it is used (HTTP 502).
    #[error("{origin}: refused, {what}: {message}")]
    Untrusted {
        /// Which check failed.
        what: Untrusted,
        /// The URL or file the refused bytes came from.
        origin: String,
        /// What differs, and what to do.
        message: String,
    },
    /// A network peer (shard server, Qdrant) could not be reached or answered with an error.
    #[error("{url}: {message}")]
    Network {
        /// The URL involved.
        url: String,
        /// The HTTP status the peer answered with, if it answered (401: it wants a token, 404:
        /// no such scene or shard).
        status: Option<u16>,
        /// What failed (connection, status, timeout) and what to check.
        message: String,
    },
}

impl Error {
    /// Wraps an I/O error with the path it concerns.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.into(),
            source,
        }
    }
    /// A malformed-content error for `path`.
    pub fn format(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        Error::Format {
            path: path.into(),
            message: message.into(),
        }
    }
    /// A network error for `url`.
    pub fn network(url: impl Into<String>, message: impl Into<String>) -> Self {
        Error::Network {
            url: url.into(),
            status: None,
            message: message.into(),
        }
    }
    /// A network error for `url` whose peer answered with HTTP `status`.
    pub fn http_status(url: impl Into<String>, status: u16, message: impl Into<String>) -> Self {
        Error::Network {
            url: url.into(),
            status: Some(status),
            message: message.into(),
        }
    }
    /// A parameter outside its domain ([`Error::Param`]): `name` (the library's name for it) is
    /// `value`, but `expected` is accepted.
    pub fn param(
        name: &'static str,
        value: impl std::fmt::Display,
        expected: impl Into<String>,
    ) -> Self {
        Error::Param {
            name,
            value: value.to_string(),
            expected: expected.into(),
        }
    }
    /// A refused query ([`Error::Query`]): `field` is wrong, `message` says how.
    pub fn query(field: &'static str, message: impl Into<String>) -> Self {
        Error::Query {
            field,
            message: message.into(),
        }
    }
    /// Inputs that do not belong together ([`Error::Mismatch`]).
    pub fn mismatch(what: Mismatched, message: impl Into<String>) -> Self {
        Error::Mismatch {
            what,
            message: message.into(),
        }
    }
    /// A resource-limit error ([`Error::Limit`]).
    pub fn limit(
        resource: Resource,
        needed: impl std::fmt::Display,
        limit: impl std::fmt::Display,
    ) -> Self {
        Error::Limit {
            resource,
            needed: needed.to_string(),
            limit: limit.to_string(),
        }
    }
    /// An internal fault ([`Error::Internal`]): `what` failed, e.g. a task that panicked.
    pub fn internal(what: impl std::fmt::Display) -> Self {
        Error::Internal(what.to_string())
    }
    /// Who has to act: the one exhaustive classification of the variants (a new variant must
    /// be placed here). Front ends map it: the edge's HTTP status, the CLIs' exit messages.
    pub fn kind(&self) -> ErrorKind {
        match self {
            Error::Param { .. }
            | Error::Query { .. }
            | Error::Invalid(_)
            | Error::Unobserved { .. } => ErrorKind::UserInput,
            Error::ModelMismatch { .. } | Error::Mismatch { .. } => ErrorKind::Conflict,
            Error::Network { .. } | Error::Untrusted { .. } => ErrorKind::Upstream,
            Error::Io { .. }
            | Error::Format { .. }
            | Error::Unsupported { .. }
            | Error::Model { .. }
            | Error::Inference { .. }
            | Error::Gpu(_)
            | Error::Shard(_)
            | Error::Limit { .. } => ErrorKind::Environment,
            Error::Internal(_) => ErrorKind::Internal,
        }
    }
    /// `true` for errors the user (or an HTTP client) caused and can fix by changing the input
    /// ([`ErrorKind::UserInput`]).
    pub fn is_user_input(&self) -> bool {
        self.kind() == ErrorKind::UserInput
    }
    /// A refusal of what a trusted key does not vouch for ([`Error::Untrusted`]).
    pub fn untrusted(
        what: Untrusted,
        origin: impl Into<String>,
        message: impl Into<String>,
    ) -> Self {
        Error::Untrusted {
            what,
            origin: origin.into(),
            message: message.into(),
        }
    }
    /// A model error for `path`.
    pub fn model(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        Error::Model {
            path: path.into(),
            message: message.into(),
        }
    }
}

/// Who has to act on an [`Error`] ([`Error::kind`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ErrorKind {
    /// The caller's input: a parameter, a prompt, a file that is not what it should be named
    /// (HTTP 400).
    UserInput,
    /// Inputs that are each valid but do not belong together, e.g. a CLIP text tower of another
    /// model than the embeddings, an image of another size than its camera (HTTP 409).
    Conflict,
    /// A peer slag talks to (shard server, Qdrant) failed or could not be reached (HTTP 502).
    Upstream,
    /// This machine's files, models, GPU or limits (HTTP 500).
    Environment,
    /// A bug in slag: a panicked task, a broken invariant (HTTP 500).
    Internal,
}

/// A bounded resource named by [`Error::Limit`]. A front end maps each to what lowers the need
/// (the encoder's command line: `--raster-scale` for the raster ones).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Resource {
    /// One GPU storage-buffer binding (wgpu `max_storage_buffer_binding_size`), bytes.
    GpuBinding,
    /// Workgroups per dispatch dimension (wgpu `max_compute_workgroups_per_dimension`).
    GpuDispatch,
    /// GPU memory (the device ran out while allocating a view's buffers).
    GpuMemory,
    /// Entries of one view's weight raster (`w_kp` pairs, or tile intersections), indexed with
    /// 32-bit offsets.
    RasterEntries,
    /// Pixels of one view's weight raster (at most 2^28).
    RasterPixels,
    /// Host memory (an allocation was refused, e.g. the edge's vector store growing).
    Memory,
    /// Gaussians in one shard (a 32-bit count in the shard header).
    ShardGaussians,
    /// Free space on the file system of a folder (bytes): the `needed` and `limit` texts name
    /// the folder.
    DiskSpace,
    /// Size of a shard manifest (bytes of JSON,
    /// [`crate::shards::MAX_MANIFEST_BYTES`]).
    ManifestBytes,
}

impl Resource {
    /// Every resource, in declaration order (for front ends that map each to a remedy, and their
    /// tests).
    pub const ALL: [Resource; 9] = [
        Self::GpuBinding,
        Self::GpuDispatch,
        Self::GpuMemory,
        Self::RasterEntries,
        Self::RasterPixels,
        Self::Memory,
        Self::ShardGaussians,
        Self::DiskSpace,
        Self::ManifestBytes,
    ];
}

/// The property on which two inputs disagree ([`Error::Mismatch`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mismatched {
    /// Embedding width: a query or text embedding against the stored embeddings, shards of one
    /// store, text towers against the image tower that made the embeddings. Replace the text
    /// model (or the shards) with those of one CLIP model.
    EmbeddingWidth,
    /// Storage type: a shard of another dtype than the store holding it.
    Dtype,
    /// Pixel size: an image against its camera, masks against their image, pixel weights against
    /// their camera, two images compared.
    ImageSize,
    /// The scene: embeddings, pixel weights, ground truth or a manifest made from another scene
    /// (another Gaussian count, an id beyond it). Use the inputs of one `.ply`.
    Scene,
}

/// Where an encode counted the Gaussians its views observe ([`Error::Unobserved`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Observation {
    /// The coverage pass over the candidate views, at its rule's blend-weight floor: with none
    /// seen, no view would be chosen.
    CoveragePass,
    /// The encode's reduction: the Gaussians with any blend weight in an encoded view's masks.
    Encode,
}

impl std::fmt::Display for Observation {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Observation::CoveragePass => "the coverage pass's candidate views",
            Observation::Encode => "the encoded views",
        })
    }
}

/// Which check of a signed manifest failed ([`Error::Untrusted`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Untrusted {
    /// No signature where a trusted key requires one (the server has none for the manifest).
    Unsigned,
    /// The signature names another key than the trusted one.
    OtherKey,
    /// The signature does not verify: the manifest bytes changed after signing, or the
    /// signature file is damaged.
    BadSignature,
    /// A signed manifest that does not name the SHA-256 of every file it lists, so the
    /// signature would not cover their content.
    Unhashed,
    /// A tile (or codebook) whose SHA-256 differs from the one the signed manifest names.
    ContentHash,
    /// A signed manifest of an older generation than the one the store already holds (a replay).
    Replay,
    /// A manifest, signature or file that fails one of the format's checks (a size, a length,
    /// a CRC-32, a parse) while a key is trusted: whichever check catches a change, it is a
    /// refusal.
    Malformed,
}

impl std::fmt::Display for Untrusted {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Untrusted::Unsigned => "no signature",
            Untrusted::OtherKey => "signed by another key",
            Untrusted::BadSignature => "bad signature",
            Untrusted::Unhashed => "signed manifest without SHA-256",
            Untrusted::ContentHash => "SHA-256 differs from the signed manifest",
            Untrusted::Replay => "older generation (replay)",
            Untrusted::Malformed => "fails a check of the shard format",
        })
    }
}

impl std::fmt::Display for Resource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Resource::GpuBinding => "GPU buffer binding size",
            Resource::GpuDispatch => "GPU workgroups per dispatch dimension",
            Resource::GpuMemory => "GPU memory",
            Resource::RasterEntries => "weight raster entries per view (32-bit offsets)",
            Resource::RasterPixels => "weight raster pixels per view",
            Resource::Memory => "host memory",
            Resource::ShardGaussians => "Gaussians per shard (32-bit count)",
            Resource::DiskSpace => "free disk space",
            Resource::ManifestBytes => "manifest size",
        })
    }
}

/// An error and its causes on one line, `outer: cause: cause`, each cause printed once: a cause
/// whose text the line already ends with (an error that prints its source in its own message,
/// as [`Error::Io`] does, and also returns it as its source) is not repeated. What the binaries
/// print after `error: `.
pub fn causes_once(e: &(dyn std::error::Error + 'static)) -> String {
    let mut line = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        let text = c.to_string();
        if !text.is_empty() && !line.ends_with(&text) {
            line.push_str(": ");
            line.push_str(&text);
        }
        cause = c.source();
    }
    line
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_new_variant_has_its_kind() {
        let param = Error::param("raster_scale", 5.0, "a value in (0, 4]");
        assert_eq!(param.kind(), ErrorKind::UserInput);
        assert!(param.is_user_input());
        assert_eq!(
            param.to_string(),
            "raster_scale = 5: expected a value in (0, 4]"
        );
        let query = Error::query("top_k", "top_k \"x\": use an integer");
        assert_eq!(query.kind(), ErrorKind::UserInput);
        assert_eq!(query.to_string(), "top_k \"x\": use an integer");
        for what in [
            Mismatched::EmbeddingWidth,
            Mismatched::Dtype,
            Mismatched::ImageSize,
            Mismatched::Scene,
        ] {
            let e = Error::mismatch(what, "a vs b");
            assert_eq!(e.kind(), ErrorKind::Conflict, "{what:?}");
            assert!(!e.is_user_input());
        }
        assert_eq!(Error::internal("x").kind(), ErrorKind::Internal);
        let http = Error::http_status("http://s/m", 401, "HTTP 401");
        assert_eq!(http.kind(), ErrorKind::Upstream);
        assert!(matches!(
            http,
            Error::Network {
                status: Some(401),
                ..
            }
        ));
        for r in Resource::ALL {
            let e = Error::limit(r, "2 G", "1 G");
            assert_eq!(e.kind(), ErrorKind::Environment);
            assert!(!e.to_string().contains("--"), "{e}");
        }
    }

    #[test]
    fn each_cause_is_printed_once() {
        let os = std::io::Error::from_raw_os_error(11);
        let os_text = os.to_string();
        let e = Error::io("/s/db", os);
        let line = causes_once(&e);
        assert_eq!(line.matches(&os_text).count(), 1, "{line}");
        assert!(line.starts_with("/s/db: "), "{line}");
        #[derive(Debug)]
        struct Outer(Error);
        impl std::fmt::Display for Outer {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str("opening the store")
            }
        }
        impl std::error::Error for Outer {
            fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
                Some(&self.0)
            }
        }
        let line = causes_once(&Outer(Error::io(
            "/s/db",
            std::io::Error::from_raw_os_error(11),
        )));
        assert_eq!(line, format!("opening the store: /s/db: {os_text}"));
    }
}
