//! The `slag-encoder` command line: one module per subcommand. `main.rs` only dispatches.

pub mod cluster;
pub mod encode;
pub mod eval;
pub mod hints;
pub mod query;
pub mod render;
pub mod synthetic;

/// `--ep`: ONNX Runtime execution provider, the same value type in every binary.
pub use slag_common::onnx::ExecutionProvider as EpArg;

pub use slag_shards::cli::init_logging;
