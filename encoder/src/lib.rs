//! slag-encoder: the SLAG Semantic Embedding stage (Szilagyi, Engelmann, Bohg, RA-L 2025).
//!
//! For each posed training image: [`masks`] (SAM automatic masks or a graph segmenter) →
//! [`clip`] (CLIP embedding of each mask's white-background bounding-box crop) → [`raster`]
//! (3DGS forward pass yielding per-pixel blend weights `w_kp = α·T`) → [`aggregate`]
//! (`a_kj = Σ_{p∈M_j} w_kp`, then `E_k = Σ a_kj E_j / Σ a_kj` over all images).
//! [`config::EncodeConfig`] holds every setting of a run, grouped by those stages;
//! [`pipeline::Encoder`] checks and runs it over a scene, [`report`] records what ran.
//! [`distributed::ClusterEncoder`] runs the same map/reduce over several processes (timely
//! dataflow cluster). [`query`] checks a text prompt against the result; [`synthetic`] makes
//! scenes of any size (with placed objects and their true boxes) for scale tests and benches.
//! [`views`] chooses which training views an encode uses (all, uniformly thinned, or by
//! coverage) and which views the 2D held-out protocol keeps back.
//!
//! Evaluation (colour mIoU, 2D held-out, instance AP50, segment quality) is the crate
//! `slag-eval` (`eval/`), which depends on this library, never the other way. The `slag-encoder`
//! binary is the package `slag-encoder-cli` (`cli/`): its subcommands only turn their
//! flags into these types and slag-eval's. [`args`] holds the flags that other binaries share
//! (`encode`'s) and the flag values mapped to the library's types.
//!
//! Vector Database and Partitioning lives in its own crate, `slag-shards` (`shards`):
//! `slag-encoder partition|serve|export` are its subcommands, re-exposed by the
//! `slag-encoder` binary.

pub mod aggregate;
pub mod args;
mod check;
pub mod clip;
pub mod config;
mod disjoint_sets;
pub mod distributed;
pub mod masks;
mod memory;
pub mod object_scene;
pub mod pipeline;
pub mod prediction_filtering;
pub mod preprocess;
pub mod query;
pub mod raster;
pub mod report;
pub mod segments;
pub mod synthetic;
pub mod views;
