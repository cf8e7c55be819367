//! Text queries against the stored per-Gaussian embeddings (SLAG's query step).
//!
//! A prompt is embedded by the CLIP text tower ([`TextEmbedder`]), then every stored Gaussian is
//! scored in one pass over memory ([`crate::scan`]):
//! - [`ScoreMode::Cosine`] (default): `s_k = cos(E_k, φ_q)`, matches are `s_k ≥ threshold`
//!   (paper default [`PAPER_THRESHOLD`] = 0.28);
//! - [`ScoreMode::Relevancy`]: LERF's relevancy (Kerr et al., ICCV 2023, eq. 1, with the
//!   reference implementation's temperature τ = 10) against the canonical negatives
//!   [`CANONICAL_NEGATIVES`]: `r_k = min_i exp(τ s_k) / (exp(τ s_k) + exp(τ n_ik))
//!   = 1 / (1 + exp(τ (max_i n_ik − s_k)))` with `n_ik = cos(E_k, φ_canon_i)`
//!   ([`crate::scan::lerf_relevancy`]); 0.5 means "as close to the prompt as to the closest
//!   negative", default threshold [`RELEVANCY_THRESHOLD`].
//!
//! The answer lists the best `top_k` matches (Gaussian id, world position, score), a summary of
//! all matches (count, AABB, centroid) and the matches grouped into `objects` (centroid, AABB,
//! oriented box, count, scores; [`slag_common::objects`]) a planner can navigate to, in the robot's map frame when
//! the manifest has a scene-to-map transform (`frame=map`, the default then) or in the scene frame
//! (`frame=scene`); the answer's `frame` field says which.

mod answer;
mod request;
#[cfg(test)]
mod tests;

pub use answer::{
    QueryAnswer, QueryContext, Timings, answer_objects, run_query, run_query_framed,
    unit_prompt_embedding,
};
pub use request::RawQuery;

use std::sync::Mutex;

use slag_common::objects::ObjectParams;
use slag_common::shards::SceneToMap;
#[cfg(doc)]
use slag_common::similarity::PAPER_THRESHOLD;
use slag_common::text::TextEncoder;
use slag_common::{Error, Result};

/// LERF's canonical negative phrases.
pub const CANONICAL_NEGATIVES: [&str; 4] = ["object", "things", "stuff", "texture"];
/// Default relevancy threshold (the prompt beats every negative).
pub const RELEVANCY_THRESHOLD: f32 = 0.5;
/// Default number of matches returned.
pub const DEFAULT_TOP_K: usize = 100;
/// Largest `top_k` accepted.
pub const MAX_TOP_K: usize = 10_000;
/// Longest prompt accepted, in bytes (CLIP reads 77 tokens anyway): the limit every slag
/// interface shares, [`slag_common::prompt::MAX_PROMPT_BYTES`].
pub const MAX_TEXT_BYTES: usize = slag_common::prompt::MAX_PROMPT_BYTES;

/// Which interface a query came through: each refusal of a prompt ends with that interface's own
/// hint (an HTTP one here; the command line adds its flag where it reports the error).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Interface {
    /// `GET /query?text=…` (and `GET /query.ply`).
    HttpGet,
    /// An item of `POST /query`.
    HttpPost,
    /// `slag-edge query --text …`.
    Cli,
}

impl Interface {
    /// How to give a prompt through this interface.
    pub fn prompt_hint(self) -> &'static str {
        match self {
            Interface::HttpGet => "use /query?text=chair",
            Interface::HttpPost => "send {\"text\": \"chair\"}",
            Interface::Cli => "",
        }
    }
}

/// Which frame an answer's coordinates (and a query's `bbox`) are in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FrameChoice {
    /// The map frame when the manifest has a scene-to-map transform, else the scene frame.
    #[default]
    Auto,
    /// The robot's map frame (metres); an error when the manifest has no transform.
    Map,
    /// The scene (reconstruction) frame, scene units.
    Scene,
}

/// The transform to apply to answers for `choice`, given the manifest's scene-to-map transform:
/// `Some` = answer in the map frame.
///
/// Errors: [`Error::Query`] `frame` for [`FrameChoice::Map`] when the scene has no map frame.
pub fn answer_frame(
    choice: FrameChoice,
    to_map: Option<&SceneToMap>,
) -> Result<Option<&SceneToMap>> {
    match (choice, to_map) {
        (FrameChoice::Scene, _) => Ok(None),
        (FrameChoice::Auto, t) => Ok(t),
        (FrameChoice::Map, Some(t)) => Ok(Some(t)),
        (FrameChoice::Map, None) => Err(Error::query(
            "frame",
            "frame map: this scene has no map frame (its manifest has no scene-to-map transform; \
             partition it with one), or ask frame=scene",
        )),
    }
}

/// Something that turns prompts into unit vectors of the stored embeddings' width.
pub trait TextEmbedder: Send + Sync {
    /// L2-normalised embeddings, one per text, in order.
    ///
    /// Errors: [`Error::Model`] when the model fails.
    fn embed(&self, texts: &[&str]) -> Result<Vec<Vec<f32>>>;
    /// Model name for answers and logs.
    fn name(&self) -> String;
    /// Prompts held in the cache of recent prompts.
    fn cached(&self) -> usize;
    /// Refuses a text model of another CLIP model than the one that made the stored embeddings
    /// (`embedding_model`, the manifest's model id). The default accepts any (test embedders).
    ///
    /// Errors: [`Error::ModelMismatch`] naming both model ids.
    fn check_pair(&self, embedding_model: &str) -> Result<()> {
        let _ = embedding_model;
        Ok(())
    }
}

/// The CLIP text tower through ONNX Runtime ([`TextEncoder`], LRU cache of 256 prompts).
pub struct OnnxTextEmbedder {
    inner: Mutex<TextEncoder>,
    name: String,
}

impl OnnxTextEmbedder {
    /// Wraps a loaded encoder; `name` is reported in answers (e.g. the model file stem).
    pub fn new(encoder: TextEncoder, name: String) -> Self {
        OnnxTextEmbedder {
            inner: Mutex::new(encoder),
            name,
        }
    }
}

impl TextEmbedder for OnnxTextEmbedder {
    fn embed(&self, texts: &[&str]) -> Result<Vec<Vec<f32>>> {
        self.inner
            .lock()
            .map_err(|_| Error::internal("text encoder poisoned by an earlier panic"))?
            .encode(texts)
    }
    fn name(&self) -> String {
        self.name.clone()
    }
    fn cached(&self) -> usize {
        self.inner.lock().map(|e| e.cached()).unwrap_or(0)
    }
    fn check_pair(&self, embedding_model: &str) -> Result<()> {
        self.inner
            .lock()
            .map_err(|_| Error::internal("text encoder poisoned by an earlier panic"))?
            .check_pair(embedding_model)
    }
}

/// How Gaussians are scored.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ScoreMode {
    /// Cosine similarity with the prompt.
    Cosine,
    /// LERF relevancy against [`CANONICAL_NEGATIVES`].
    Relevancy,
}

/// Which index answers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum IndexKind {
    /// Exact scan over every stored Gaussian.
    Exact,
    /// The approximate HNSW index (top-k only; needs `serve --hnsw`).
    Hnsw,
}

/// How a Gaussian's score is formed before the threshold and the ranking.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Smooth {
    /// Each Gaussian's own score (the paper's query).
    #[default]
    None,
    /// Each Gaussian scores the mean score of its geometric segment over every loaded Gaussian
    /// of that segment (the open-vocabulary analogue of the paper's prediction filtering,
    /// [`slag_common::segments::rank_smoothed`], as `slag-encoder query --smooth segment`), so a
    /// segment matches or not as a whole. Needs shards with segments (format version 3 or 4);
    /// Gaussians of shards without segments keep their own score.
    Segment,
}

/// A validated query.
#[derive(Debug, Clone, PartialEq)]
pub struct QueryParams {
    /// Prompt (1..=[`MAX_TEXT_BYTES`] bytes, not blank).
    pub text: String,
    /// Matches returned (1..=[`MAX_TOP_K`]).
    pub top_k: usize,
    /// Score threshold; `None` = rank everything (summary then covers the returned matches).
    pub threshold: Option<f32>,
    /// Scoring mode.
    pub mode: ScoreMode,
    /// Only Gaussians whose mean lies in this box (inclusive, in the answer's frame):
    /// `[min, max]`.
    pub bbox: Option<[[f32; 3]; 2]>,
    /// Index to use.
    pub index: IndexKind,
    /// Frame of the answer's coordinates and of `bbox`.
    pub frame: FrameChoice,
    /// How the matches are grouped into the answer's `objects` (gap, minimum size, order,
    /// number; [`slag_common::objects`]).
    pub objects: ObjectParams,
    /// Score smoothing within geometric segments (default none).
    pub smooth: Smooth,
}
