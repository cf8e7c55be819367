//! slag-shards: the shard stage (SLAG's "Vector Database and Partitioning"), apart from the
//! encoder so that serving files links neither wgpu, ONNX Runtime nor timely.
//!
//! Input: an embeddings file written by `slag-encoder encode` (`E_k` per Gaussian, scene frame).
//! [`partition`] cuts it into spatial shards (ground-plane k-d tiles, format in
//! [`slag_common::shards`]), [`store`] keeps shards and manifests in a sled database (one
//! generation per scene, written atomically), [`serve`] serves them over HTTP (ETag, Range, optional
//! bearer token), [`export`] writes `manifest.json` + shard files for any static host, [`qdrant`]
//! upserts the points into a Qdrant collection (optionally one snapshot per tile).
//!
//! [`stage`] runs a partition from its typed settings ([`stage::PartitionConfig`], as the
//! encoder has `EncodeConfig`). [`cli`] is the command-line surface (`partition`, `serve`,
//! `export`, `keygen`) shared by the `slag-shards` binary and `slag-encoder`'s subcommands of the
//! same names and flags: each turns its flags into the library's settings.
//!
//! Depends on `slag-common` only (house rule, ARCHITECTURE.md).

pub mod cli;
pub mod export;
pub mod partition;
pub mod qdrant;
pub mod serve;
pub mod stage;
pub mod store;
