//! The `slag-encoder` command line: one module per subcommand, each turning its flags into the
//! library's typed configuration and calling it. `main.rs` only dispatches.

pub mod cluster;
pub mod encode;
pub mod eval;
pub mod eval_objects;
pub mod hints;
pub mod query;
pub mod render;
pub mod segment;
pub mod synthetic;

/// `--ep`: ONNX Runtime execution provider, the same value type in every binary.
pub use slag_common::cli::EpArg;

pub use slag_shards::cli::init_logging;
