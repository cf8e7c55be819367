//! Check a text prompt against an embeddings file (`slag-encoder query`): the best Gaussians,
//! optionally a copy of the scene `.ply` with the matches highlighted.

use std::path::{Path, PathBuf};

use slag_common::Result;
use slag_common::embeddings::Embeddings;
use slag_common::objects::{self, ObjectParams, SceneObject};
use slag_common::onnx::ExecutionProvider;
use slag_common::similarity::{self, Match, MatchSummary};
use slag_common::text::TextEncoder;

/// One prompt against one embeddings file.
#[derive(Debug, Clone, PartialEq)]
pub struct QueryParams {
    /// The encoder's embeddings, either form ([`slag_common::forms::read_rows`]):
    /// `mixture.safetensors` (the default output, expanded to its rows) or the dense
    /// `embeddings.safetensors`.
    pub embeddings: PathBuf,
    /// CLIP text tower ONNX (`input_ids i64[B,77] -> [B,D]`) of the same CLIP model.
    pub clip_textual: PathBuf,
    /// CLIP BPE tokenizer (tokenizer.json for the `tokenizers` crate).
    pub tokenizer: PathBuf,
    /// The prompt, e.g. "red" or "a chair" (not blank, at most
    /// [`slag_common::prompt::MAX_PROMPT_BYTES`] bytes, as on slag-edge).
    pub text: String,
    /// Return at most this many matches (the command line's default: 20).
    pub top_k: usize,
    /// Cosine threshold (the paper uses [`similarity::PAPER_THRESHOLD`], 0.28); matches below
    /// it are dropped.
    pub threshold: f32,
    /// Write a copy of this .ply with every match above the threshold painted `highlight_rgb`
    /// (together with `highlight_out`).
    pub ply: Option<PathBuf>,
    /// Where to write the highlighted .ply.
    pub highlight_out: Option<PathBuf>,
    /// Highlight colour, r,g,b in 0..1.
    pub highlight_rgb: [f32; 3],
    /// ONNX Runtime execution provider of the text tower.
    pub ep: ExecutionProvider,
    /// How the matches are grouped into objects (gap in scene units here: the embeddings file
    /// is in the scene frame; [`slag_common::objects`]).
    pub objects: ObjectParams,
    /// Score smoothing within geometric segments (the open-vocabulary analogue of prediction
    /// filtering); default none.
    pub smooth: Smooth,
    /// Segments for [`Smooth::Segment`]; `None`: `segments.safetensors` beside the embeddings.
    pub segments: Option<PathBuf>,
}

/// Whether a Gaussian's score is its own or smoothed within its segment.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Smooth {
    /// Each Gaussian's own cosine (the paper's query).
    #[default]
    None,
    /// Each Gaussian scores the mean cosine of its geometric segment
    /// ([`slag_common::segments::segment_mean`]), so a segment matches or not as a whole.
    Segment,
}

impl QueryParams {
    /// `text` against `embeddings` with the text tower `clip_textual` and its `tokenizer`: the
    /// command line's defaults (top 20, the paper's threshold, no highlight, the CPU).
    pub fn new(
        embeddings: impl Into<PathBuf>,
        clip_textual: impl Into<PathBuf>,
        tokenizer: impl Into<PathBuf>,
        text: impl Into<String>,
    ) -> Self {
        QueryParams {
            embeddings: embeddings.into(),
            clip_textual: clip_textual.into(),
            tokenizer: tokenizer.into(),
            text: text.into(),
            top_k: 20,
            threshold: similarity::PAPER_THRESHOLD,
            ply: None,
            highlight_out: None,
            highlight_rgb: [1.0, 0.0, 1.0],
            ep: ExecutionProvider::Cpu,
            objects: ObjectParams::default(),
            smooth: Smooth::None,
            segments: None,
        }
    }
}

/// What `query` prints (JSON).
#[derive(Debug, serde::Serialize)]
pub struct QueryOutput {
    /// The prompt.
    pub query: String,
    /// CLIP model id of the embeddings.
    pub model: String,
    /// The cosine threshold applied.
    pub threshold: f32,
    /// The score smoothing applied (`none` or `segment`).
    pub smooth: Smooth,
    /// Gaussians above the threshold (all of them, for the summary).
    pub summary: MatchSummary,
    /// Every match above the threshold grouped into objects, scene frame
    /// ([`slag_common::objects::group_objects`], opacity-weighted centroids when the embeddings'
    /// scene `.ply` is given as `ply`, else score-weighted).
    pub objects: Vec<SceneObject>,
    /// Per object of `objects` (same order), the ids of its member Gaussians, ascending (not
    /// printed: the instance scores of `slag_eval::instances` compare them with the truth).
    #[serde(skip)]
    pub object_members: Vec<Vec<u32>>,
    /// The best `top_k` matches above the threshold, best first.
    pub matches: Vec<Match>,
    /// When nothing reaches the threshold: the `top_k` best-scoring Gaussians anyway, so the user
    /// sees how close the scene came (empty otherwise).
    pub nearest_below_threshold: Vec<Match>,
    /// The highlighted .ply, if written.
    pub highlighted_ply: Option<PathBuf>,
}

/// Ranks the Gaussians of [`QueryParams::embeddings`] (the dense file or the mixture) against the
/// prompt.
///
/// Errors: a blank prompt or one over [`slag_common::prompt::MAX_PROMPT_BYTES`] (the limit of
/// `slag-edge`; [`slag_common::Error::Query`], checked before anything is read), unreadable
/// embeddings or models, a text tower of another CLIP model than the embeddings'.
pub fn run(a: &QueryParams) -> Result<QueryOutput> {
    slag_common::prompt::check_prompt(&a.text, "")?;
    a.objects.validate()?;
    // Either stored form: the mixture (the encode's default output) is expanded to its rows.
    let emb = slag_common::forms::read_rows(&a.embeddings)?;
    let mut text = TextEncoder::new(&a.clip_textual, &a.tokenizer, a.ep)?;
    text.check_pair(&emb.model)?;
    let q = text.encode(&[a.text.as_str()])?.remove(0);
    let (all, summary) = match a.smooth {
        Smooth::None => rank(&emb, &q, None, Some(a.threshold))?,
        Smooth::Segment => rank_smoothed(a, &emb, &q)?,
    };
    if let (Some(src), Some(dst)) = (&a.ply, &a.highlight_out) {
        write_highlight(src, dst, a.highlight_rgb, &emb, &all)?;
    }
    let (objects, object_members) = group_matches(a, &all)?;
    let nearest_below_threshold = if all.is_empty() {
        rank(&emb, &q, Some(a.top_k), None)?.0
    } else {
        Vec::new()
    };
    Ok(QueryOutput {
        query: a.text.clone(),
        model: emb.model.clone(),
        threshold: a.threshold,
        smooth: a.smooth,
        summary,
        objects,
        object_members,
        matches: all.into_iter().take(a.top_k).collect(),
        nearest_below_threshold,
        highlighted_ply: a.highlight_out.clone(),
    })
}

/// The rows of `emb` ranked by cosine with the text embedding `q` ([`similarity::rank`]): at
/// most `top_k` of them, those ≥ `threshold`, best first.
fn rank(
    emb: &Embeddings,
    q: &[f32],
    top_k: Option<usize>,
    threshold: Option<f32>,
) -> Result<(Vec<Match>, MatchSummary)> {
    similarity::rank(
        &emb.ids,
        &emb.means,
        &emb.vectors,
        emb.dim,
        q,
        top_k,
        threshold,
    )
}

/// Writes a copy of the scene `src` to `dst` with every Gaussian of `matches` painted `rgb`.
fn write_highlight(
    src: &Path,
    dst: &Path,
    rgb: [f32; 3],
    emb: &Embeddings,
    matches: &[Match],
) -> Result<()> {
    let largest_id = emb.ids.iter().map(|&i| i as u64 + 1).max().unwrap_or(0);
    let mut hit = vec![false; emb.scene_gaussians.max(largest_id) as usize];
    matches.iter().for_each(|m| hit[m.id as usize] = true);
    slag_common::scene::write_highlighted_ply(src, dst, |i| {
        hit.get(i).copied().unwrap_or(false).then_some(rgb)
    })
}

/// The matches grouped into objects ([`objects::group_objects`] with [`QueryParams::objects`],
/// weighted by opacity when the scene `.ply` is given, else by score), and per object the ids of
/// its member Gaussians, ascending.
fn group_matches(a: &QueryParams, all: &[Match]) -> Result<(Vec<SceneObject>, Vec<Vec<u32>>)> {
    let opacities = match &a.ply {
        Some(src) => {
            let g = slag_common::scene::load_ply(
                src,
                slag_common::scene::PlyLoadOptions { colours: false },
            )?;
            // Already the sigmoid of the stored opacity.
            let of = |m: &Match| g.opacities.get(m.id as usize).copied().unwrap_or(1.0);
            Some(all.iter().map(of).collect::<Vec<f32>>())
        }
        None => None,
    };
    let ids: Vec<u32> = all.iter().map(|m| m.id).collect();
    let positions: Vec<[f32; 3]> = all.iter().map(|m| m.position).collect();
    let scores: Vec<f32> = all.iter().map(|m| m.score).collect();
    let grouped = objects::group_objects(
        &objects::Matches {
            ids: &ids,
            positions: &positions,
            scores: &scores,
            opacities: opacities.as_deref(),
        },
        &a.objects,
    )?;
    let mut object_members = vec![Vec::new(); grouped.objects.len()];
    for (&id, k) in ids.iter().zip(&grouped.member_of) {
        if let Some(m) = k.and_then(|k| object_members.get_mut(k as usize)) {
            m.push(id);
        }
    }
    object_members.iter_mut().for_each(|m| m.sort_unstable());
    Ok((grouped.objects, object_members))
}

/// Every Gaussian scored with its segment's mean cosine, those ≥ the threshold ranked best first
/// (ties: lower row first).
fn rank_smoothed(
    a: &QueryParams,
    emb: &Embeddings,
    q: &[f32],
) -> Result<(Vec<Match>, MatchSummary)> {
    let path = a.segments.clone().unwrap_or_else(|| {
        a.embeddings
            .parent()
            .unwrap_or(Path::new("."))
            .join(slag_common::segments::FILE_NAME)
    });
    let rows = slag_common::segments::Segments::read(&path)?.gather(&emb.ids)?;
    let raw = similarity::cosine_scores(&emb.vectors, emb.dim, q)?;
    let ranked =
        slag_common::segments::rank_smoothed(&raw, &rows, Some(a.threshold), None, |_| true)?;
    let matches: Vec<Match> = ranked
        .into_iter()
        .map(|(i, score)| Match {
            id: emb.ids[i],
            position: emb.means[i],
            score,
        })
        .collect();
    let summary = similarity::summarise(&matches);
    Ok((matches, summary))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn blank_prompts_are_refused_before_anything_is_read() {
        let q = QueryParams::new("does-not-exist.safetensors", "m.onnx", "t.json", " ");
        let e = run(&q).unwrap_err();
        assert!(
            matches!(e, slag_common::Error::Query { field: "text", .. }),
            "{e}"
        );
        let m = e.to_string();
        assert!(m.contains("missing query text") && !m.contains("--"), "{m}");
        // A valid prompt gets past the check (then fails on the missing file).
        let q = QueryParams::new("does-not-exist.safetensors", "m.onnx", "t.json", "a chair");
        assert!(run(&q).unwrap_err().to_string().contains("does-not-exist"));
    }
}
