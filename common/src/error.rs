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
    /// provider, the GPU and what to do ([`crate::onnx::remedy`]).
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
    /// A parameter or combination of inputs is invalid (e.g. camera/image size mismatch).
    #[error("invalid input: {0}")]
    Invalid(String),
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
    /// A model error for `path`.
    pub fn model(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        Error::Model {
            path: path.into(),
            message: message.into(),
        }
    }
}
