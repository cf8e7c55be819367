//! ONNX Runtime sessions through `ort` with `load-dynamic` (to be implemented).
//!
//! The runtime library is found through `ORT_DYLIB_PATH` (see `../shared/tools/install-onnxruntime.sh`).

/// Which ONNX Runtime execution provider runs a model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ExecutionProvider {
    /// The default CPU provider.
    #[default]
    Cpu,
    /// NVIDIA CUDA (only where the loaded ONNX Runtime build has it).
    Cuda,
}
