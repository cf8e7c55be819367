//! Raw query fields as they arrive (HTTP `GET`/`POST`, the CLI, ROS 2) and their checks into a
//! [`QueryParams`]: every bad field is a typed error naming the field and what it accepts.

use slag_common::objects::{self, ObjectParams};
use slag_common::{Error, Result};

use super::{
    DEFAULT_TOP_K, FrameChoice, IndexKind, Interface, MAX_TOP_K, QueryParams, RELEVANCY_THRESHOLD,
    ScoreMode, Smooth,
};

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
