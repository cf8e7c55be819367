//! Running a validated query: the prompt's embedding, one scoring pass over the store (exact,
//! smoothed or HNSW), the matches inside the query's boxes, and the answer (best `top_k`, the
//! summary of all matches, the objects) in the map or the scene frame.

use std::time::Instant;

use slag_common::objects::{self, ObjectParams, SceneObject};
use slag_common::shards::{MAP_FRAME, SCENE_FRAME, SceneToMap};
use slag_common::similarity::{Match, MatchSummary, summarise};
use slag_common::{Error, Result};

use super::{IndexKind, QueryParams, ScoreMode, Smooth, TextEmbedder, answer_frame};
use crate::scan::{self, ScanRequest, VectorStore};
use crate::view::DisplayAttrs;

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
    /// Embeddings of [`super::CANONICAL_NEGATIVES`] (`[4][D]`; used in relevancy mode).
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
    /// embeddings of [`super::CANONICAL_NEGATIVES`]) and, with smooth=segment, every row's own score
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
