//! slag-encoder: the SLAG Semantic Embedding stage (Szilagyi, Engelmann, Bohg, RA-L 2025).
//!
//! For each posed training image: [`masks`] (SAM automatic masks or a graph segmenter) →
//! [`clip`] (CLIP embedding of each mask's white-background bounding-box crop) → [`raster`]
//! (3DGS forward pass yielding per-pixel blend weights `w_kp = α·T`) → [`aggregate`]
//! (`a_kj = Σ_{p∈M_j} w_kp`, then `E_k = Σ a_kj E_j / Σ a_kj` over all images).
//! [`config::EncodeConfig`] holds every setting of a run, grouped by those stages;
//! [`pipeline::Encoder`] checks and runs it over a scene, [`report`] records what ran.
//! [`distributed::ClusterEncoder`] runs the same map/reduce over several processes (timely
//! dataflow cluster). [`query`] checks a text prompt against the result; [`eval`] holds evaluation
//! and research apart from the stages: colour mIoU with color-clip per Gaussian,
//! [`eval::heldout`] per pixel of views never encoded (2D held-out), [`eval::colors`] runs both
//! on an embeddings file, [`eval::synthetic`] makes scenes for scale tests. [`views`] chooses
//! which training views an encode uses (all, uniformly thinned, or by coverage).
//!
//! The `slag-encoder` binary's subcommands (in `src/cli/`, private to the binary) only turn
//! their flags into these types: everything they run is here. [`args`] holds the flags that
//! other binaries share (`encode`'s) and the flag values mapped to the library's types.
//!
//! Vector Database and Partitioning lives in its own crate, `slag-shards` (`encoder/shards`):
//! `slag-encoder partition|serve|export` are its subcommands, re-exposed here.

pub mod aggregate;
pub mod args;
mod check;
pub mod clip;
pub mod config;
mod disjoint_sets;
pub mod distributed;
pub mod eval;
pub mod masks;
pub mod pipeline;
pub mod prediction_filtering;
pub mod preprocess;
pub mod query;
pub mod raster;
pub mod report;
pub mod segments;
pub mod views;
