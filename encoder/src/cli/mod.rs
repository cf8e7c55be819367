//! The `slag-encoder` command line: one module per subcommand. `main.rs` only dispatches.

pub mod cluster;
pub mod encode;
pub mod eval;
pub mod query;
pub mod render;
pub mod shards;
pub mod synthetic;

use slag_common::onnx::ExecutionProvider;

/// `--ep`: ONNX Runtime execution provider.
#[derive(Debug, Clone, Copy, clap::ValueEnum, PartialEq, Eq)]
pub enum EpArg {
    /// CPU (always available).
    Cpu,
    /// NVIDIA CUDA (needs an ONNX Runtime build with CUDA, e.g. onnxruntime-gpu's library).
    Cuda,
}

impl From<EpArg> for ExecutionProvider {
    fn from(e: EpArg) -> Self {
        match e {
            EpArg::Cpu => ExecutionProvider::Cpu,
            EpArg::Cuda => ExecutionProvider::Cuda,
        }
    }
}

/// Sets up `tracing` (respects `RUST_LOG`, default `info`) on stderr.
pub fn init_logging(verbose: bool) {
    let default = if verbose { "debug" } else { "info" };
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .try_init();
}
