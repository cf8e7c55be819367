//! The command line the binaries share (the `clap` feature): values whose library types derive
//! no command-line traits (each maps to one with `From`), the options every binary takes and the
//! process's logging and exit status ([`process`]), the old flag spellings still accepted
//! ([`deprecated`]), and the HTTP servers' options ([`server`], with the `server` feature).

pub mod deprecated;
pub mod process;
#[cfg(feature = "server")]
pub mod server;

#[cfg(feature = "onnx")]
use crate::onnx::ExecutionProvider;

/// `--ep`: the ONNX Runtime execution provider ([`ExecutionProvider`]), the same value in every
/// binary (`cpu`, `cuda`, `tensorrt`, `auto`).
#[cfg(feature = "onnx")]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum EpArg {
    /// The default CPU provider.
    #[default]
    Cpu,
    /// NVIDIA CUDA (only where the loaded ONNX Runtime build has it: PyPI's `onnxruntime-gpu`,
    /// `scripts/setup.sh --gpu`).
    ///
    /// Requesting CUDA from a runtime without it is an error ([`Error::Inference`]), never a
    /// silent fallback to the CPU: a run that was meant for a GPU should not quietly take hours.
    Cuda,
    /// NVIDIA TensorRT (where TensorRT 10 and the runtime's TensorRT provider are installed),
    /// fp16 engines cached beside the model (`<model>.trt-cache/`); nodes TensorRT cannot take
    /// fall back to CUDA. An error where TensorRT does not register.
    #[value(name = "tensorrt")]
    TensorRt,
    /// CUDA when the loaded runtime has it and it registers on the GPU, otherwise the CPU, with one
    /// log line per process saying why.
    Auto,
}

#[cfg(all(doc, feature = "onnx"))]
use crate::Error;

#[cfg(feature = "onnx")]
impl From<EpArg> for ExecutionProvider {
    fn from(a: EpArg) -> Self {
        match a {
            EpArg::Cpu => ExecutionProvider::Cpu,
            EpArg::Cuda => ExecutionProvider::Cuda,
            EpArg::TensorRt => ExecutionProvider::TensorRt,
            EpArg::Auto => ExecutionProvider::Auto,
        }
    }
}
