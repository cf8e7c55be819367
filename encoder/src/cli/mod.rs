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
    /// CUDA when the loaded ONNX Runtime has it and a GPU answers, else the CPU (one line says
    /// why).
    Auto,
    /// CPU (always available).
    Cpu,
    /// NVIDIA CUDA (needs an ONNX Runtime build with CUDA: `bash scripts/setup.sh --gpu`).
    Cuda,
    /// NVIDIA TensorRT (needs TensorRT 10 and an ONNX Runtime with its TensorRT provider; fp16
    /// engines cached beside each model).
    Tensorrt,
}

impl From<EpArg> for ExecutionProvider {
    fn from(e: EpArg) -> Self {
        match e {
            EpArg::Auto => ExecutionProvider::Auto,
            EpArg::Cpu => ExecutionProvider::Cpu,
            EpArg::Cuda => ExecutionProvider::Cuda,
            EpArg::Tensorrt => ExecutionProvider::TensorRt,
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
