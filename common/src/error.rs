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
    /// A parameter or combination of inputs is invalid (e.g. camera/image size mismatch): the
    /// user's to fix (HTTP 400).
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
    /// Something that must not happen did (a panicked worker task, a broken invariant): a bug in
    /// slag, never the user's input (HTTP 500).
    #[error(
        "internal fault: {0}; this is a slag bug, please report it with the command and its --verbose log"
    )]
    Internal(String),
    /// The GPU (wgpu) could not be used or a kernel failed.
    #[error("gpu: {0}")]
    Gpu(String),
    /// A network peer (shard server, Qdrant) could not be reached or answered with an error.
    #[error("{url}: {message}")]
    Network {
        /// The URL involved.
        url: String,
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
            Error::Invalid(_) => ErrorKind::UserInput,
            Error::ModelMismatch { .. } => ErrorKind::Conflict,
            Error::Network { .. } => ErrorKind::Upstream,
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
    /// model than the embeddings (HTTP 409).
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
}

impl std::fmt::Display for Resource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Resource::GpuBinding => "GPU buffer binding size",
            Resource::GpuDispatch => "GPU workgroups per dispatch dimension",
            Resource::GpuMemory => "GPU memory",
            Resource::RasterEntries => "weight raster entries per view (32-bit offsets)",
        })
    }
}
