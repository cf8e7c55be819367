//! slag-edge: the robot-side runtime of slag (SLAG's query side, for an NVIDIA Jetson Orin).
//!
//! - [`fetch`]: download the shards within a radius of the robot (manifest → `rstar` tile
//!   selection → resumable, verified downloads);
//! - [`store`]: the embedded `sled` store of verified shards;
//! - [`scan`]: the exact scan kernels over f32/f16/int8 embeddings and the approximate HNSW index;
//! - [`query`]: prompt → CLIP text embedding → cosine or LERF relevancy scores → matches + summary;
//! - [`engine`]: a loaded scene (manifest, vector store, display columns, HNSW index);
//! - [`serve`]: the HTTP API (`GET /query?text=chair`, `/health`, `/stats`, `POST /query`), and in
//!   [`serve::web`] `GET /query.ply` and the web page `GET /` that renders it;
//! - [`view`]: the answer shown to a person: the loaded Gaussians as a 3DGS `.ply` with the
//!   matches painted;
//! - [`ros2`]: the ROS 2 node of `serve --ros2` (prompts in; objects, matches and RViz
//!   markers out);
//! - [`config`]: the TOML config file of `serve` (`jetson/edge.toml`).

pub mod config;
pub mod engine;
pub mod fetch;
pub mod query;
pub mod ros2;
pub mod scan;
pub mod serve;
pub mod store;
pub mod view;
