//! slag-bench: reproducible studies of slag, one module per study.
//!
//! - [`tradeoffs`]: the speed/accuracy trade study on a real scene with color-clip (ground truth
//!   known): the knobs a user turns (mask source, image subsampling, raster resolution,
//!   contributors kept per pixel, stored precision, exact scan vs HNSW) against encode time,
//!   query latency, bytes per Gaussian and accuracy; writes `tradeoffs.{md,csv}` (the plot is
//!   drawn from the CSV by `scripts/lab/plot_tradeoffs.py`).
//!
//! - [`stages`]: each encoder stage's time per image against its floor (FLOPs at the measured
//!   matrix rate, bytes at the measured bandwidths) on the machine it runs on.
//! - [`scaling`]: the same encode on 1, 2, 4 … GPUs of one host: speed-up and efficiency.
//! - [`models`]: each ONNX model of the encode (CLIP tower, SAM encoder and decoder) timed alone
//!   as the encoder runs it, and model variants checked against the first on the same inputs.
//! - [`reduce`]: the reduction over images (the encoder's serial tail) in its two loop orders,
//!   against each other in one run, plus the embeddings write.
//!
//! The binary `slag-bench` exposes each study as a subcommand (`slag-bench tradeoffs …`).
//! `stages` and `scaling` take `slag-encoder encode`'s flags: `slag_encoder::args::EncodeArgs`,
//! the encoder's own flag definition, converted into a `slag_encoder::config::EncodeConfig`.

pub mod machine;
pub mod models;
pub mod reduce;
pub mod scaling;
pub mod stages;
pub mod tradeoffs;
