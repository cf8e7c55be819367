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
//!   ([`scan::lerf_relevancy`]); 0.5 means "as close to the prompt as to the closest negative",
//!   default threshold [`RELEVANCY_THRESHOLD`].
//!
//! The answer lists the best `top_k` matches (Gaussian id, world position, score), a summary of
//! all matches (count, AABB, centroid) and the matches grouped into `objects` (centroid, AABB,
//! oriented box, count, scores; [`slag_common::objects`]) a planner can navigate to, in the robot's map frame when
//! the manifest has a scene-to-map transform (`frame=map`, the default then) or in the scene frame
//! (`frame=scene`); the answer's `frame` field says which.

use std::sync::Mutex;
use std::time::Instant;

use slag_common::objects::{self, ObjectParams, SceneObject};
use slag_common::shards::{MAP_FRAME, SCENE_FRAME, SceneToMap};
#[cfg(doc)]
use slag_common::similarity::PAPER_THRESHOLD;
use slag_common::similarity::{Match, MatchSummary, summarise};
use slag_common::text::TextEncoder;
use slag_common::{Error, Result};

use crate::scan::{self, ScanRequest, VectorStore};
use crate::view::DisplayAttrs;

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

/// Raw query fields as they arrive (`GET /query?text=…&top_k=…` or a `POST /query` JSON item).
#[derive(Debug, Clone, Default, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawQuery {
    /// Prompt.
    pub text: Option<String>,
    /// Integer 1..=10000.
    pub top_k: Option<String>,
    /// Number, or `none`.
    pub threshold: Option<String>,
    /// `cosine` | `relevancy`.
    pub mode: Option<String>,
    /// `minx,miny,minz,maxx,maxy,maxz`.
    pub bbox: Option<String>,
    /// `exact` | `hnsw`.
    pub index: Option<String>,
    /// `map` | `scene` (default: map when the scene has a map frame).
    pub frame: Option<String>,
    /// Objects returned, integer 1..=1000 (default 20).
    pub max_objects: Option<String>,
    /// `x,y,z` in the answer's frame: objects sorted by distance of their centroid from it.
    pub near: Option<String>,
    /// Single-linkage gap of the objects, answer-frame units (metres in the map frame), > 0
    /// (default: derived from the matches' spacing, `slag_common::objects::derived_gap`).
    pub object_gap: Option<String>,
    /// Smallest object in matching Gaussians, integer ≥ 1 (default 10).
    pub object_min_gaussians: Option<String>,
    /// `none` | `segment`: score each Gaussian with its geometric segment's mean score
    /// ([`Smooth`]; default none).
    pub smooth: Option<String>,
}

/// A JSON value that may be a number or a string (for `POST /query` bodies).
fn json_field(v: &serde_json::Value) -> Option<String> {
    match v {
        serde_json::Value::Null => None,
        serde_json::Value::String(s) => Some(s.clone()),
        other => Some(other.to_string()),
    }
}

/// The prompt of a JSON query: a JSON string only. Anything else (an object, an array, a
/// number, a boolean, null) is refused rather than turned into text and answered: the client
/// meant something else, and the answer would be for a prompt nobody typed.
///
/// Errors: [`Error::Query`] `text` naming the JSON type that was sent.
fn text_field(v: &serde_json::Value) -> Result<String> {
    let kind = match v {
        serde_json::Value::String(s) => return Ok(s.clone()),
        serde_json::Value::Null => "null",
        serde_json::Value::Bool(_) => "a boolean",
        serde_json::Value::Number(_) => "a number",
        serde_json::Value::Array(_) => "an array",
        serde_json::Value::Object(_) => "an object",
    };
    Err(Error::query(
        "text",
        format!("text is {kind}; send the prompt as a JSON string, like \"text\": \"chair\""),
    ))
}

/// A JSON array of numbers as the comma-separated form the query string uses (`[1, 2, 3]` →
/// `"1,2,3"`); `None` for anything else.
fn comma_list(v: &serde_json::Value) -> Option<String> {
    v.as_array().map(|a| {
        a.iter()
            .map(|x| x.to_string())
            .collect::<Vec<_>>()
            .join(",")
    })
}

impl RawQuery {
    /// From a JSON object; numbers and strings are both accepted, unknown keys rejected.
    ///
    /// Errors: [`Error::Query`] naming the offending key.
    pub fn from_json(v: &serde_json::Value) -> Result<RawQuery> {
        let obj = v.as_object().ok_or_else(|| {
            Error::query(
                "query",
                "each query must be a JSON object like {\"text\": \"chair\"}",
            )
        })?;
        let mut q = RawQuery::default();
        for (k, v) in obj {
            let val = json_field(v);
            match k.as_str() {
                "text" => q.text = Some(text_field(v)?),
                "top_k" => q.top_k = val,
                "threshold" => q.threshold = val,
                "mode" => q.mode = val,
                "bbox" => q.bbox = comma_list(v).or(val),
                "index" => q.index = val,
                "frame" => q.frame = val,
                "max_objects" => q.max_objects = val,
                "near" => q.near = comma_list(v).or(val),
                "object_gap" => q.object_gap = val,
                "object_min_gaussians" => q.object_min_gaussians = val,
                "smooth" => q.smooth = val,
                other => {
                    return Err(Error::query(
                        "query",
                        format!(
                            "unknown query field {other:?}; use text, top_k, threshold, mode, \
                             bbox, index, frame, max_objects, near, object_gap, \
                             object_min_gaussians, smooth"
                        ),
                    ));
                }
            }
        }
        Ok(q)
    }

    /// Validates every field as `GET /query` does ([`Self::validate_for`] with
    /// [`Interface::HttpGet`]).
    ///
    /// Errors: as [`Self::validate_for`].
    pub fn validate(&self, cosine_default: f32) -> Result<QueryParams> {
        self.validate_for(cosine_default, Interface::HttpGet)
    }

    /// Validates every field; `cosine_default` is the threshold used in cosine mode when none is
    /// given (the paper's [`PAPER_THRESHOLD`] unless the server is configured otherwise). A blank
    /// or too long prompt ([`slag_common::prompt`]) is refused with `via`'s hint.
    ///
    /// Errors: [`Error::Query`] with the field, and a message naming the value and the allowed
    /// range.
    pub fn validate_for(&self, cosine_default: f32, via: Interface) -> Result<QueryParams> {
        let bad = |field: &'static str, m: String| Err(Error::query(field, m));
        let text = self.text.clone().unwrap_or_default();
        slag_common::prompt::check_prompt(&text, via.prompt_hint())?;
        let mode = match self.mode.as_deref().map(str::trim) {
            None | Some("cosine") => ScoreMode::Cosine,
            Some("relevancy") => ScoreMode::Relevancy,
            Some(m) => return bad("mode", format!("mode {m:?}: use cosine or relevancy")),
        };
        let top_k = self.parse_top_k()?;
        let threshold = self.parse_threshold(mode, cosine_default)?;
        let bbox = self.parse_bbox()?;
        let index = match self.index.as_deref().map(str::trim) {
            None | Some("exact") => IndexKind::Exact,
            Some("hnsw") => IndexKind::Hnsw,
            Some(i) => return bad("index", format!("index {i:?}: use exact or hnsw")),
        };
        let frame = match self.frame.as_deref().map(str::trim) {
            None | Some("auto") => FrameChoice::Auto,
            Some("map") => FrameChoice::Map,
            Some("scene") => FrameChoice::Scene,
            Some(f) => return bad("frame", format!("frame {f:?}: use map or scene")),
        };
        let objects = self.object_params()?;
        let smooth = match self.smooth.as_deref().map(str::trim) {
            None | Some("none") => Smooth::None,
            Some("segment") => Smooth::Segment,
            Some(m) => return bad("smooth", format!("smooth {m:?}: use none or segment")),
        };
        if smooth == Smooth::Segment && index == IndexKind::Hnsw {
            return bad(
                "smooth",
                "smooth=segment needs every Gaussian's score (a segment's mean), which the \
                 approximate index does not give; use index=exact"
                    .into(),
            );
        }
        Ok(QueryParams {
            text,
            top_k,
            threshold,
            mode,
            bbox,
            index,
            frame,
            objects,
            smooth,
        })
    }

    /// `top_k`: [`DEFAULT_TOP_K`] when absent.
    ///
    /// Errors: [`Error::Query`] `top_k` for anything but an integer in `1..=MAX_TOP_K`.
    fn parse_top_k(&self) -> Result<usize> {
        match self.top_k.as_deref().map(str::trim) {
            None => Ok(DEFAULT_TOP_K),
            Some(s) => match s.parse::<usize>() {
                Ok(k) if (1..=MAX_TOP_K).contains(&k) => Ok(k),
                _ => Err(Error::query(
                    "top_k",
                    format!("top_k {s:?}: use an integer in 1..={MAX_TOP_K}"),
                )),
            },
        }
    }

    /// `threshold` for `mode`'s scores: `cosine_default` (cosine) or [`RELEVANCY_THRESHOLD`]
    /// when absent, `None` for `none`.
    ///
    /// Errors: [`Error::Query`] `threshold` for a value outside `-1..=1` (cosine) or `0..=1`
    /// (relevancy), or not a number.
    fn parse_threshold(&self, mode: ScoreMode, cosine_default: f32) -> Result<Option<f32>> {
        let (lo, hi, default) = match mode {
            ScoreMode::Cosine => (-1.0, 1.0, cosine_default),
            ScoreMode::Relevancy => (0.0, 1.0, RELEVANCY_THRESHOLD),
        };
        match self.threshold.as_deref().map(str::trim) {
            None => Ok(Some(default)),
            Some("none") => Ok(None),
            Some(s) => match s.parse::<f32>() {
                Ok(t) if t.is_finite() && (lo..=hi).contains(&t) => Ok(Some(t)),
                _ => Err(Error::query(
                    "threshold",
                    format!(
                        "threshold {s:?}: use a number in {lo}..={hi} for {mode:?} scores, or \
                         none"
                    ),
                )),
            },
        }
    }

    /// `bbox`: `[[minx, miny, minz], [maxx, maxy, maxz]]` in the answer's frame, `None` when
    /// absent.
    ///
    /// Errors: [`Error::Query`] `bbox` for anything but 6 finite numbers with min ≤ max.
    fn parse_bbox(&self) -> Result<Option<[[f32; 3]; 2]>> {
        let Some(s) = self.bbox.as_deref() else {
            return Ok(None);
        };
        let v: Vec<f32> = s
            .split(',')
            .map(|p| p.trim().parse::<f32>())
            .collect::<std::result::Result<_, _>>()
            .map_err(|_| {
                Error::query(
                    "bbox",
                    format!(
                        "bbox {s:?}: use minx,miny,minz,maxx,maxy,maxz (in the answer's frame)"
                    ),
                )
            })?;
        match v[..] {
            [a, b, c, d, e, f] if v.iter().all(|x| x.is_finite()) && a <= d && b <= e && c <= f => {
                Ok(Some([[a, b, c], [d, e, f]]))
            }
            _ => Err(Error::query(
                "bbox",
                format!(
                    "bbox {s:?}: need 6 finite numbers minx,miny,minz,maxx,maxy,maxz with min ≤ \
                     max"
                ),
            )),
        }
    }
}

impl RawQuery {
    /// The object fields (`max_objects`, `near`, `object_gap`, `object_min_gaussians`), defaults
    /// [`slag_common::objects::ObjectParams::default`].
    ///
    /// Errors: [`Error::Query`] naming the field, the value and the allowed range.
    fn object_params(&self) -> Result<ObjectParams> {
        let mut p = ObjectParams::default();
        if let Some(s) = self.max_objects.as_deref().map(str::trim) {
            p.max_objects = s
                .parse::<usize>()
                .ok()
                .filter(|k| (1..=objects::MAX_OBJECTS_LIMIT).contains(k))
                .ok_or_else(|| {
                    Error::query(
                        "max_objects",
                        format!(
                            "max_objects {s:?}: use an integer in 1..={}",
                            objects::MAX_OBJECTS_LIMIT
                        ),
                    )
                })?;
        }
        if let Some(s) = self.near.as_deref() {
            let v: Option<Vec<f32>> = s.split(',').map(|p| p.trim().parse::<f32>().ok()).collect();
            p.near = match v.as_deref() {
                Some(&[x, y, z]) if [x, y, z].iter().all(|c| c.is_finite()) => Some([x, y, z]),
                _ => {
                    return Err(Error::query(
                        "near",
                        format!(
                            "near {s:?}: use x,y,z, three finite numbers in the answer's frame \
                             (the robot's position)"
                        ),
                    ));
                }
            };
        }
        if let Some(s) = self.object_gap.as_deref().map(str::trim) {
            p.gap = s
                .parse::<f32>()
                .map(Some)
                .ok()
                .filter(|g| g.is_some_and(|g| g.is_finite() && g > 0.0))
                .ok_or_else(|| {
                    Error::query(
                        "object_gap",
                        format!(
                            "object_gap {s:?}: use a distance > 0 in the answer's frame (metres \
                             in the map frame)"
                        ),
                    )
                })?;
        }
        if let Some(s) = self.object_min_gaussians.as_deref().map(str::trim) {
            p.min_gaussians = s.parse::<usize>().ok().filter(|k| *k >= 1).ok_or_else(|| {
                Error::query(
                    "object_min_gaussians",
                    format!("object_min_gaussians {s:?}: use an integer ≥ 1"),
                )
            })?;
        }
        Ok(p)
    }
}

/// `serde` skips a count of 0 ([`QueryAnswer::tiles_pending_verification`]).
fn is_zero(n: &usize) -> bool {
    *n == 0
}

/// The answer to one query (JSON of `GET /query`).
#[derive(Debug, Clone, serde::Serialize)]
pub struct QueryAnswer {
    /// The prompt.
    pub query: String,
    /// Embedding model of the stored Gaussians (from the manifest).
    pub embedding_model: String,
    /// Text model used for the prompt.
    pub text_model: String,
    /// Scoring mode.
    pub mode: ScoreMode,
    /// Threshold applied (`null`: none).
    pub threshold: Option<f32>,
    /// `top_k` asked for.
    pub top_k: usize,
    /// Index that answered.
    pub index: IndexKind,
    /// Score smoothing applied: `"none"`, or `"segment"` (every score, `matches`, `summary` and
    /// `objects` included, is its geometric segment's mean score).
    pub smooth: Smooth,
    /// Frame of every coordinate in this answer (match positions, summary AABB and centroid)
    /// and of the query's `bbox`: `"map"` (the robot's map frame, metres, through the manifest's
    /// scene-to-map transform) or `"scene"` (the reconstruction's frame, scene units).
    pub frame: &'static str,
    /// Best matches, score descending (ties: lower row first).
    pub matches: Vec<Match>,
    /// All matches above the threshold (or the returned ones without a threshold).
    pub summary: MatchSummary,
    /// The matches grouped into objects ([`slag_common::objects::group_objects`]), built over
    /// the same matches as `summary`: every match above the threshold, not only the returned
    /// `top_k`; without a threshold (`threshold=none`, where every Gaussian "matches") over the
    /// returned `top_k` best. Sorted by score mass (`score_mass`), or by distance from `near`;
    /// at most `max_objects`.
    pub objects: Vec<SceneObject>,
    /// Per entry of `matches`: the index in `objects` of its object (`None`: in no returned
    /// object). Not serialised; `GET /query.ply?color_by=object` paints with it.
    #[serde(skip)]
    pub match_objects: Vec<Option<u32>>,
    /// Best score over the searched Gaussians when nothing reached the threshold (else `null`).
    pub best_score_below_threshold: Option<f32>,
    /// Gaussians searched.
    pub searched: usize,
    /// Tiles of the served generation whose SHA-256 is still being checked in the background
    /// (a server with a trusted key, just started): none of their Gaussians was searched, and
    /// they join the answers once verified. Left out of the JSON when 0.
    #[serde(skip_serializing_if = "is_zero")]
    pub tiles_pending_verification: usize,
    /// True when `tiles_pending_verification` > 0: the answer covers the verified tiles only.
    /// Left out of the JSON when false.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub partial: bool,
    /// Server-side time: text encoding and scan, milliseconds.
    pub timings_ms: Timings,
}

/// Where a query's time went.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct Timings {
    /// CLIP text tower (0 for cached prompts apart from lookup).
    pub text: f64,
    /// Scoring and selection.
    pub scan: f64,
}

/// The prompt embedding `phi` scaled to unit L2 norm
/// ([`slag_common::similarity::unit_query`]: norm in f64, f32 reciprocal), so that scores are
/// cosines whatever the [`TextEmbedder`] returns (a no-op up to rounding for the CLIP text tower,
/// which already normalises).
///
/// Errors: [`Error::Query`] (HTTP 400) when the norm is below 1e-12 or not finite (a zero,
/// subnormal, NaN or infinite embedding): it has no direction, and scanning with it would rank
/// every Gaussian at score 0 (or NaN). One rule for every normalisation in slag
/// (`slag_common::similarity::normalize_in_place`).
pub fn unit_prompt_embedding(phi: Vec<f32>) -> Result<Vec<f32>> {
    slag_common::similarity::unit_query(&phi)
}

/// Runs a validated query against `store`, answering in the scene frame (no map frame known):
/// [`run_query_framed`] without a transform or display columns.
///
/// Errors: as [`run_query_framed`].
pub fn run_query(
    store: &VectorStore,
    embedding_model: &str,
    text: &dyn TextEmbedder,
    negatives: &[Vec<f32>],
    hnsw: Option<&scan::hnsw::ApproxIndex>,
    q: &QueryParams,
) -> Result<QueryAnswer> {
    let cx = QueryContext {
        store,
        embedding_model,
        to_map: None,
        text,
        negatives,
        hnsw,
        display: None,
    };
    run_query_framed(&cx, q)
}

/// What a validated query runs against: one loaded scene's rows and what goes with them, and
/// the prompt side. [`crate::engine::Engine::context`] builds it for a loaded generation.
#[derive(Clone, Copy)]
pub struct QueryContext<'a> {
    /// The Gaussians' embeddings (`[N][D]`) and means (scene frame).
    pub store: &'a VectorStore,
    /// CLIP model of the stored embeddings (the manifest's), named in the answer.
    pub embedding_model: &'a str,
    /// The manifest's scene-to-map transform (`Frames::scene_to_map`), `None` where the scene
    /// has none: answers are then in the scene frame.
    pub to_map: Option<&'a SceneToMap>,
    /// The text model that embeds the prompt (`[D]`, the stored width).
    pub text: &'a dyn TextEmbedder,
    /// Embeddings of [`CANONICAL_NEGATIVES`] (`[4][D]`; used in relevancy mode).
    pub negatives: &'a [Vec<f32>],
    /// The approximate index over `store`'s rows (either backend: same row ids and scores as the
    /// exact scan, possibly missing rows), `None` without one.
    pub hnsw: Option<&'a scan::hnsw::ApproxIndex>,
    /// Display columns of the same rows (opacities weight the objects' centroids); `None`:
    /// every row weighs 1.
    pub display: Option<&'a DisplayAttrs>,
}

/// `lo ≤ p ≤ hi` on every axis.
fn in_box(p: [f32; 3], b: &[[f32; 3]; 2]) -> bool {
    (0..3).all(|a| p[a] >= b[0][a] && p[a] <= b[1][a])
}

/// Runs a validated query against `cx.store` (means in the scene frame).
///
/// With `cx.to_map`, and `q.frame` auto or map, every coordinate of the answer is mapped into
/// the map frame and `q.bbox` is read in the map frame (the scan keeps the scene box around the
/// map box's corners, then the exact map box is applied to each kept row). `cx.negatives` are
/// used in relevancy mode; `cx.hnsw` answers `index=hnsw`.
///
/// Errors: text encoding ([`Error::Model`]), a prompt embedding of another width than the store
/// ([`Error::Mismatch`]) or without a direction (zero / non-finite norm, [`unit_prompt_embedding`];
/// [`Error::Query`]), `frame=map` without a transform ([`answer_frame`]), `index=hnsw` without an
/// index or with a relevancy or too large top-k query ([`Error::Query`] `index`).
pub fn run_query_framed(cx: &QueryContext<'_>, q: &QueryParams) -> Result<QueryAnswer> {
    let store = cx.store;
    let map = answer_frame(q.frame, cx.to_map)?;
    let t0 = Instant::now();
    let phi = prompt_embedding(store, cx.embedding_model, cx.text, &q.text)?;
    let t_text = t0.elapsed().as_secs_f64() * 1e3;
    let t1 = Instant::now();
    let scoring = Scoring::new(store, &phi, cx.negatives, q)?;
    let boxes = QueryBoxes::new(store.means(), map, q.bbox);
    let hits = select_hits(store, cx.hnsw, &phi, &scoring, &boxes, q)?;
    let found = assemble_matches(store, &scoring, &boxes, &hits, cx.display, q)?;
    Ok(QueryAnswer {
        query: q.text.clone(),
        embedding_model: cx.embedding_model.to_string(),
        text_model: cx.text.name(),
        mode: q.mode,
        threshold: q.threshold,
        top_k: q.top_k,
        index: q.index,
        smooth: q.smooth,
        frame: boxes.frame(),
        matches: found.matches,
        summary: found.summary,
        objects: found.objects,
        match_objects: found.match_objects,
        best_score_below_threshold: found.best_score_below_threshold,
        searched: store.len(),
        tiles_pending_verification: 0,
        partial: false,
        timings_ms: Timings {
            text: t_text,
            scan: t1.elapsed().as_secs_f64() * 1e3,
        },
    })
}

/// The prompt's unit embedding, `[D]` with `D = store.dim()`: `text` embeds `prompt`, an
/// embedding of another width than the stored Gaussians is refused, then the embedding is
/// scaled to unit norm ([`unit_prompt_embedding`]).
///
/// Errors: as [`run_query_framed`] for the text encoding ([`Error::Model`]), the width
/// ([`Error::Mismatch`]) and the norm ([`Error::Query`]).
fn prompt_embedding(
    store: &VectorStore,
    embedding_model: &str,
    text: &dyn TextEmbedder,
    prompt: &str,
) -> Result<Vec<f32>> {
    let phi = text
        .embed(&[prompt])?
        .into_iter()
        .next()
        .ok_or_else(|| Error::internal("text encoder returned nothing"))?;
    if phi.len() != store.dim() {
        return Err(Error::mismatch(
            slag_common::Mismatched::EmbeddingWidth,
            format!(
                "the text model gives {}-d embeddings but the stored Gaussians are {}-d ({}); \
                 serve with the CLIP text tower of the same model",
                phi.len(),
                store.dim(),
                embedding_model
            ),
        ));
    }
    unit_prompt_embedding(phi)
}

/// How one query scores the store's rows.
struct Scoring<'a> {
    /// The scan's query vectors, `[D]` each: the unit prompt, then in relevancy mode the
    /// canonical negatives.
    queries: Vec<&'a [f32]>,
    /// Combines a row's dot products into its score (`None`: the cosine with the prompt;
    /// relevancy: [`scan::lerf_relevancy`]).
    combine: Option<scan::Combiner<'a>>,
    /// With smooth=segment: every row's own score and segment.
    smoothing: Option<SegmentScores<'a>>,
}

/// What smooth=segment smooths: every row's own score (`[N]`, cosine or relevancy) and every
/// row's geometric segment id (`[N]`).
struct SegmentScores<'a> {
    raw: Vec<f32>,
    segments: &'a [u32],
}

impl<'a> Scoring<'a> {
    /// The scan's queries and combiner for `q.mode` (`phi` the unit prompt, `negatives` the
    /// embeddings of [`CANONICAL_NEGATIVES`]) and, with smooth=segment, every row's own score
    /// (one pass over the store).
    ///
    /// Errors: [`Error::Query`] `smooth` when smooth=segment and the shards carry no segments;
    /// as [`scan::scores`].
    fn new(
        store: &'a VectorStore,
        phi: &'a [f32],
        negatives: &'a [Vec<f32>],
        q: &QueryParams,
    ) -> Result<Self> {
        let mut queries: Vec<&[f32]> = vec![phi];
        let relevancy: scan::Combiner<'_> = &scan::lerf_relevancy;
        let combine = match q.mode {
            ScoreMode::Cosine => None,
            ScoreMode::Relevancy => {
                queries.extend(negatives.iter().map(Vec::as_slice));
                Some(relevancy)
            }
        };
        let smoothing = match q.smooth {
            Smooth::None => None,
            Smooth::Segment => {
                let segments = store.segments().ok_or_else(|| {
                    Error::query(
                        "smooth",
                        "smooth=segment: this scene's shards carry no geometric segments; \
                         partition the scene with its segments.safetensors (`slag-encoder \
                         encode` writes it, `slag-encoder partition` picks it up beside \
                         --embeddings: shard format version 3) and fetch again, or leave smooth \
                         out",
                    )
                })?;
                let raw = scan::scores(store, &queries, combine)?;
                Some(SegmentScores { raw, segments })
            }
        };
        Ok(Scoring {
            queries,
            combine,
            smoothing,
        })
    }
}

/// A query's boxes and answer frame.
struct QueryBoxes<'a> {
    /// The store's row means, `[N]`, scene frame.
    means: &'a [[f32; 3]],
    /// The answer frame's scene-to-map transform (`None`: answers in the scene frame).
    to_map: Option<&'a SceneToMap>,
    /// The box the scan keeps, `[lo, hi]` in the scene frame: the query's `bbox`, or with a map
    /// transform the scene box around the map box's corners, widened by one ulp.
    scene_box: Option<[[f32; 3]; 2]>,
    /// The query's `bbox` in the map frame (with a map transform only), applied exactly to each
    /// row the scan keeps.
    map_box: Option<[[f32; 3]; 2]>,
}

impl<'a> QueryBoxes<'a> {
    /// The boxes of the query's `bbox` (in the answer frame) over rows with scene-frame `means`,
    /// answering in the map frame through `to_map` when given.
    fn new(
        means: &'a [[f32; 3]],
        to_map: Option<&'a SceneToMap>,
        bbox: Option<[[f32; 3]; 2]>,
    ) -> Self {
        let (scene_box, map_box) = match (bbox, to_map) {
            (None, _) => (None, None),
            (Some(b), None) => (Some(b), None),
            (Some(b), Some(t)) => {
                let (lo, hi) = t.map_box_in_scene(b[0].map(f64::from), b[1].map(f64::from));
                let lo = lo.map(|v| (v as f32).next_down());
                let hi = hi.map(|v| (v as f32).next_up());
                (Some([lo, hi]), Some(b))
            }
        };
        QueryBoxes {
            means,
            to_map,
            scene_box,
            map_box,
        }
    }

    /// The answer frame's name ([`MAP_FRAME`] or [`SCENE_FRAME`]).
    fn frame(&self) -> &'static str {
        if self.to_map.is_some() {
            MAP_FRAME
        } else {
            SCENE_FRAME
        }
    }

    /// Position of store row `row` in the answer frame.
    fn position(&self, row: usize) -> [f32; 3] {
        let m = self.means[row];
        match self.to_map {
            Some(t) => t.to_map_f32(m),
            None => m,
        }
    }

    /// The scan's scene-frame box as a [`ScanRequest`] takes it, `(lo, hi)`.
    fn scan_box(&self) -> Option<([f32; 3], [f32; 3])> {
        self.scene_box.map(|[lo, hi]| (lo, hi))
    }

    /// Whether row `row`'s mean lies in the scan's scene-frame box (true without a box).
    fn in_scene_box(&self, row: usize) -> bool {
        self.scene_box.is_none_or(|b| in_box(self.means[row], &b))
    }

    /// Whether row `row`'s position lies in the exact map-frame box (true without a map box).
    fn in_map_box(&self, row: usize) -> bool {
        self.map_box.is_none_or(|b| in_box(self.position(row), &b))
    }

    /// Whether row `row` lies in both boxes.
    fn inside(&self, row: usize) -> bool {
        self.in_scene_box(row) && self.in_map_box(row)
    }

    /// Whether a hit the scan kept (inside the scene box) lies in the map box too.
    fn keep(&self, hit: &scan::Hit) -> bool {
        self.in_map_box(hit.row)
    }
}

/// The query's hits, best first: smooth=segment's smoothed scores, else the exact scan or the
/// approximate index. Threshold queries collect every match for the summary; ranked-only ones
/// keep a bounded top-k heap.
///
/// Errors: as [`smoothed_hits`], [`exact_hits`] and [`hnsw_hits`].
fn select_hits(
    store: &VectorStore,
    hnsw: Option<&scan::hnsw::ApproxIndex>,
    phi: &[f32],
    scoring: &Scoring<'_>,
    boxes: &QueryBoxes<'_>,
    q: &QueryParams,
) -> Result<Vec<scan::Hit>> {
    let ranked_k = if q.threshold.is_some() {
        None
    } else {
        Some(q.top_k)
    };
    match (&scoring.smoothing, q.index) {
        (Some(s), _) => smoothed_hits(s, boxes, ranked_k, q.threshold),
        (None, IndexKind::Exact) => exact_hits(store, scoring, boxes, ranked_k, q.threshold),
        (None, IndexKind::Hnsw) => hnsw_hits(store, hnsw, phi, boxes, q),
    }
}

/// The exact scan's hits, ranked, honouring the map box: rows are kept by the scan's scene box
/// (and `top_k` / `threshold`), then by the map box; a top-k-only scan then collects every row
/// of the scene box (threshold −inf) so the map box cannot leave it short, and the top-k is cut
/// after.
///
/// Errors: as [`scan::scan`].
fn exact_hits(
    store: &VectorStore,
    scoring: &Scoring<'_>,
    boxes: &QueryBoxes<'_>,
    top_k: Option<usize>,
    threshold: Option<f32>,
) -> Result<Vec<scan::Hit>> {
    let (top_k_scan, thr_scan) = match (boxes.map_box, threshold) {
        (None, _) => (top_k, threshold),
        (Some(_), Some(t)) => (None, Some(t)),
        (Some(_), None) => (None, Some(f32::NEG_INFINITY)),
    };
    let req = ScanRequest {
        queries: &scoring.queries,
        top_k: top_k_scan,
        threshold: thr_scan,
        bbox: boxes.scan_box(),
        combine: scoring.combine,
    };
    let mut hits = scan::scan(store, &req)?;
    if boxes.map_box.is_some() {
        hits.retain(|h| boxes.keep(h));
        hits.sort_by(scan::select::rank_cmp);
        if let Some(k) = top_k {
            hits.truncate(k);
        }
    }
    Ok(hits)
}

/// smooth=segment's hits, ranked: each row scores its segment's mean over every loaded row of
/// the segment (so the boxes do not change a segment's score), then the boxes, the `threshold`
/// and the `top_k` apply to the smoothed scores.
///
/// Errors: as [`slag_common::segments::rank_smoothed`].
fn smoothed_hits(
    s: &SegmentScores<'_>,
    boxes: &QueryBoxes<'_>,
    top_k: Option<usize>,
    threshold: Option<f32>,
) -> Result<Vec<scan::Hit>> {
    let inside = |row: usize| boxes.inside(row);
    Ok(
        slag_common::segments::rank_smoothed(&s.raw, s.segments, threshold, top_k, inside)?
            .into_iter()
            .map(|(row, score)| scan::Hit { row, score })
            .collect(),
    )
}

/// The approximate index's hits: the prompt's top-k neighbours, then those at or above the
/// threshold and inside both boxes.
///
/// Errors: [`Error::Query`] `index`, checked in this order, when the rows are codebook
/// mixtures, the server has no index, the query is not cosine, or the top-k exceeds the index's
/// ef_search; as the index's query.
fn hnsw_hits(
    store: &VectorStore,
    hnsw: Option<&scan::hnsw::ApproxIndex>,
    phi: &[f32],
    boxes: &QueryBoxes<'_>,
    q: &QueryParams,
) -> Result<Vec<scan::Hit>> {
    if store.is_mixture() {
        return Err(Error::query(
            "index",
            "index=hnsw is not available for this scene: its rows are codebook \
             mixtures, over which no HNSW index is built; use index=exact (the exact \
             mixture scan)",
        ));
    }
    let index = hnsw.ok_or_else(|| {
        Error::query(
            "index",
            "index=hnsw needs the approximate index, which this server was started \
             without; use index=exact",
        )
    })?;
    if q.mode != ScoreMode::Cosine {
        return Err(Error::query(
            "index",
            "index=hnsw answers cosine queries only; use index=exact for relevancy",
        ));
    }
    if q.top_k > index.ef_search() {
        return Err(Error::query(
            "index",
            format!(
                "index=hnsw answers top_k ≤ {} (its ef_search); ask fewer or use \
                 index=exact",
                index.ef_search()
            ),
        ));
    }
    let mut hits = index.query(phi, q.top_k)?;
    hits.retain(|h| q.threshold.is_none_or(|t| h.score >= t) && boxes.inside(h.row));
    Ok(hits)
}

/// The matched part of an answer; positions in the answer frame.
struct AnswerMatches {
    matches: Vec<Match>,
    summary: MatchSummary,
    objects: Vec<SceneObject>,
    match_objects: Vec<Option<u32>>,
    best_score_below_threshold: Option<f32>,
}

/// The answer's matches from the ranked `hits`: every hit as a match (position in the answer
/// frame), the summary and the objects over all of them, then the matches (and their object
/// indices) cut to the top-k; when none is left, the best score below the threshold
/// ([`best_score`]).
///
/// Errors: as [`answer_objects`], then as [`best_score`].
fn assemble_matches(
    store: &VectorStore,
    scoring: &Scoring<'_>,
    boxes: &QueryBoxes<'_>,
    hits: &[scan::Hit],
    display: Option<&DisplayAttrs>,
    q: &QueryParams,
) -> Result<AnswerMatches> {
    let all: Vec<Match> = hits
        .iter()
        .map(|h| Match {
            id: store.ids()[h.row],
            position: boxes.position(h.row),
            score: h.score,
        })
        .collect();
    let summary = summarise(&all);
    let grouped = answer_objects(hits, &all, display, &q.objects)?;
    let mut matches = all;
    matches.truncate(q.top_k);
    let mut match_objects = grouped.member_of;
    match_objects.truncate(matches.len());
    let best_score_below_threshold = if matches.is_empty() {
        best_score(store, scoring, boxes, q.index)?
    } else {
        None
    };
    Ok(AnswerMatches {
        matches,
        summary,
        objects: grouped.objects,
        match_objects,
        best_score_below_threshold,
    })
}

/// The best score over the searched Gaussians inside the boxes, whatever the threshold (for an
/// answer without matches): smooth=segment's or the exact scan's top 1; `None` for the
/// approximate index.
///
/// Errors: as [`smoothed_hits`] and [`exact_hits`].
fn best_score(
    store: &VectorStore,
    scoring: &Scoring<'_>,
    boxes: &QueryBoxes<'_>,
    index: IndexKind,
) -> Result<Option<f32>> {
    let best = match (&scoring.smoothing, index) {
        (Some(s), _) => smoothed_hits(s, boxes, Some(1), None)?,
        (None, IndexKind::Exact) => exact_hits(store, scoring, boxes, Some(1), None)?,
        (None, IndexKind::Hnsw) => return Ok(None),
    };
    Ok(best.first().map(|h| h.score))
}

/// The objects of a query's matches: `hits` (store rows) and `all` (the same matches, answer
/// frame) grouped by [`objects::group_objects`] with the opacity of each row from `display`
/// (the sigmoid of the stored pre-sigmoid opacity; 1 for rows whose shard has none, or all rows
/// without `display`: the centroid is then weighted by score). Objects are spatial groups: the
/// segments, where the scene has them, act through the scores (`smooth=segment`).
///
/// Errors: as [`objects::group_objects`].
pub fn answer_objects(
    hits: &[scan::Hit],
    all: &[Match],
    display: Option<&DisplayAttrs>,
    p: &ObjectParams,
) -> Result<objects::Objects> {
    let positions: Vec<[f32; 3]> = all.iter().map(|m| m.position).collect();
    let ids: Vec<u32> = all.iter().map(|m| m.id).collect();
    let scores: Vec<f32> = all.iter().map(|m| m.score).collect();
    let opacities: Option<Vec<f32>> = display.map(|d| {
        hits.iter()
            .map(|h| d.opacity(h.row).unwrap_or(1.0))
            .collect()
    });
    objects::group_objects(
        &objects::Matches {
            ids: &ids,
            positions: &positions,
            scores: &scores,
            opacities: opacities.as_deref(),
        },
        p,
    )
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use slag_common::similarity::PAPER_THRESHOLD;

    fn raw(pairs: &[(&str, &str)]) -> RawQuery {
        let v: serde_json::Map<String, serde_json::Value> = pairs
            .iter()
            .map(|(k, v)| (k.to_string(), serde_json::Value::String(v.to_string())))
            .collect();
        RawQuery::from_json(&serde_json::Value::Object(v)).unwrap()
    }

    #[test]
    fn defaults_follow_the_paper_and_lerf() {
        let q = raw(&[("text", "chair")]).validate(PAPER_THRESHOLD).unwrap();
        assert_eq!(q.threshold, Some(PAPER_THRESHOLD));
        assert_eq!(q.top_k, DEFAULT_TOP_K);
        assert_eq!(q.mode, ScoreMode::Cosine);
        let q = raw(&[("text", "chair"), ("mode", "relevancy")])
            .validate(PAPER_THRESHOLD)
            .unwrap();
        assert_eq!(q.threshold, Some(RELEVANCY_THRESHOLD));
        let q = raw(&[("text", "chair"), ("threshold", "none")])
            .validate(PAPER_THRESHOLD)
            .unwrap();
        assert_eq!(q.threshold, None);
    }

    #[test]
    fn bad_parameters_are_typed_errors_naming_the_field() {
        for (pairs, needle) in [
            (vec![], "missing query text"),
            (vec![("text", "   ")], "missing query text"),
            (vec![("text", "a"), ("top_k", "0")], "top_k"),
            (vec![("text", "a"), ("top_k", "10001")], "top_k"),
            (vec![("text", "a"), ("top_k", "-3")], "top_k"),
            (vec![("text", "a"), ("threshold", "NaN")], "threshold"),
            (vec![("text", "a"), ("threshold", "2")], "threshold"),
            (
                vec![("text", "a"), ("mode", "relevancy"), ("threshold", "-0.1")],
                "threshold",
            ),
            (vec![("text", "a"), ("mode", "fuzzy")], "mode"),
            (vec![("text", "a"), ("bbox", "1,2,3")], "bbox"),
            (vec![("text", "a"), ("bbox", "1,1,1,0,0,0")], "bbox"),
            (vec![("text", "a"), ("bbox", "0,0,0,inf,1,1")], "bbox"),
            (vec![("text", "a"), ("index", "ivf")], "index"),
        ] {
            let e = raw(&pairs)
                .validate(PAPER_THRESHOLD)
                .unwrap_err()
                .to_string();
            assert!(e.contains(needle), "{pairs:?}: {e}");
        }
        let long = "x".repeat(MAX_TEXT_BYTES + 1);
        assert!(raw(&[("text", &long)]).validate(PAPER_THRESHOLD).is_err());
        let e = RawQuery::from_json(&serde_json::json!({"text": "a", "topk": 3})).unwrap_err();
        assert!(e.to_string().contains("topk"));
        assert!(RawQuery::from_json(&serde_json::json!(["a"])).is_err());
    }

    #[test]
    fn json_numbers_and_arrays_are_accepted() {
        let q = RawQuery::from_json(&serde_json::json!({
            "text": "red", "top_k": 5, "threshold": 0.1, "bbox": [0, 0, 0, 1, 2, 3]
        }))
        .unwrap()
        .validate(PAPER_THRESHOLD)
        .unwrap();
        assert_eq!(q.top_k, 5);
        assert_eq!(q.threshold, Some(0.1));
        assert_eq!(q.bbox, Some([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]]));
    }

    #[test]
    fn relevancy_matches_lerf_formula() {
        // Independent form: min over negatives of the pairwise softmax at temperature 10.
        let dots = [0.3f32, 0.1, 0.25, -0.2, 0.2];
        let e = |x: f32| (10.0 * x).exp();
        let want = dots[1..]
            .iter()
            .map(|&n| e(dots[0]) / (e(dots[0]) + e(n)))
            .fold(f32::INFINITY, f32::min);
        assert!((scan::lerf_relevancy(&dots) - want).abs() < 1e-6);
        // Prompt equal to the closest negative: exactly 0.5.
        assert!((scan::lerf_relevancy(&[0.4, 0.4, 0.0]) - 0.5).abs() < 1e-7);
        // Extremes stay finite and within (0, 1).
        let r = scan::lerf_relevancy(&[-1.0, 1.0]);
        assert!(r > 0.0 && r < 0.5);
    }
}
