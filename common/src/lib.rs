//! slag-common: the pieces shared by the cloud encoder (`slag-encoder`) and the robot runtime
//! (`slag-edge`).
//!
//! | module | paper stage / concern |
//! |---|---|
//! | [`scene`] | inputs: the trained 3DGS `.ply` (INRIA layout) |
//! | [`camera`] | inputs: posed training images (COLMAP `sparse/0`, nerfstudio `transforms.json`) |
//! | [`onnx`] | ONNX Runtime sessions (`ort`, `load-dynamic`) with a selectable execution provider |
//! | [`text`] | CLIP text tower + tokenizer (queries) |
//! | [`similarity`] | cosine scoring of text against per-Gaussian embeddings |
//! | [`prompt`] | limits on text prompts shared by every query interface |
//! | [`embeddings`] | the per-Gaussian embeddings file (safetensors) |
//! | [`io`] | atomic file writes (`.partial`, fsync, rename), used by every format |
//! | [`fault`] | fault injection at durability boundaries (crash tests: `SLAG_FAULT_EXIT_AT`, `SLAG_FAULT_LIST`) |
//! | [`objects`] | objects in a query's answer: groups of matching Gaussians with their boxes |
//! | [`mixture`] | compressed embeddings: shared mask-embedding codebook + sparse per-Gaussian weights |
//! | `mask_record` | the masks' record of an encode (`mask-record.safetensors`), for the segmenter and the evaluation; cloud side only (feature `cloud`) |
//! | [`shards`] | Vector Database and Partitioning: spatial shards, manifest, tile R-tree |
//! | `cli` | the command line the binaries share: values (`--ep`), `--verbose`, logging and exit status, old spellings, the servers' options; behind the `clap` feature |
//! | `doc_flags` | checks the command lines the manual shows against the binaries' `--help` (feature `testing`) |
//! | `flag_names` | one name per thing on the three binaries' command lines, the table and its check (feature `testing`) |
//! | [`paths`] | locating `../shared` fixtures for tests and examples |
//! | [`rng`] | SplitMix64, the deterministic generator of synthetic data and randomised tests |
//! | [`table`] | Markdown and CSV tables of the study reports (rows measured, then written) |
//! | [`term`] | whether log lines may carry colour codes (a terminal, `NO_COLOR`) |
//! | `testing` | raw-socket clients for the HTTP servers' integration tests (feature `testing`) |
//! | `tls` | the servers' TLS certificate (PEM, reloadable) and the no-token-in-clear-text rule (feature `server`) |
//! | [`cache`] | a prefetch hint for passes that read large arrays at random places |
//! | [`util`] | the process's resident memory and the machine's available memory (`/proc`) |

pub mod auth;
pub mod cache;
pub mod camera;
#[cfg(feature = "clap")]
pub mod cli;
#[cfg(feature = "testing")]
pub mod doc_flags;
pub mod embeddings;
pub mod error;
pub mod fault;
#[cfg(feature = "testing")]
pub mod flag_names;
pub mod forms;
#[cfg(feature = "server")]
pub mod http;
pub mod io;
#[cfg(feature = "cloud")]
pub mod mask_record;
pub mod mixture;
pub mod objects;
#[cfg(feature = "onnx")]
pub mod onnx;
pub mod paths;
pub mod prompt;
pub mod rng;
mod safetensors_io;
pub mod scene;
pub mod segments;
pub mod shards;
pub mod similarity;
pub mod table;
pub mod term;
#[cfg(feature = "testing")]
pub mod testing;
#[cfg(feature = "onnx")]
pub mod text;
#[cfg(feature = "server")]
pub mod tls;
pub mod util;

pub use error::{Error, ErrorKind, Mismatched, Observation, Resource, Result, Untrusted};
