//! `slag-encoder query`: check a text prompt against an embeddings file, print the best Gaussians,
//! optionally write a copy of the scene `.ply` with the matches highlighted.

use std::path::PathBuf;

use clap::Args;
use slag_common::embeddings::Embeddings;
use slag_common::similarity::{self, Match, MatchSummary};
use slag_common::text::TextEncoder;

use super::EpArg;

/// Arguments of `query`.
#[derive(Debug, Clone, Args)]
pub struct QueryArgs {
    /// embeddings.safetensors written by `encode`.
    #[arg(long)]
    pub embeddings: PathBuf,
    /// CLIP text tower ONNX (input_ids i64[B,77] -> [B,D]) of the same CLIP model.
    #[arg(long)]
    pub clip_textual: PathBuf,
    /// CLIP BPE tokenizer (tokenizer.json for the `tokenizers` crate).
    #[arg(long)]
    pub tokenizer: PathBuf,
    /// The prompt, e.g. "red" or "a chair" (not blank, at most 1000 bytes, as on slag-edge).
    #[arg(long)]
    pub text: String,
    /// Print at most this many matches.
    #[arg(long, default_value_t = 20)]
    pub top_k: usize,
    /// Cosine threshold (the paper uses 0.28); matches below it are dropped.
    #[arg(long, default_value_t = similarity::PAPER_THRESHOLD)]
    pub threshold: f32,
    /// Write a copy of this .ply with every match above the threshold painted --highlight-rgb.
    #[arg(long, requires = "highlight_out")]
    pub ply: Option<PathBuf>,
    /// Where to write the highlighted .ply.
    #[arg(long, requires = "ply")]
    pub highlight_out: Option<PathBuf>,
    /// Highlight colour, r,g,b in 0..1.
    #[arg(long, default_value = "1,0,1", value_parser = parse_rgb)]
    pub highlight_rgb: [f32; 3],
    /// ONNX Runtime execution provider.
    #[arg(long, value_enum, default_value_t = EpArg::Cpu)]
    pub ep: EpArg,
}

fn parse_rgb(s: &str) -> Result<[f32; 3], String> {
    let v: Vec<f32> = s
        .split(',')
        .map(|p| p.trim().parse::<f32>())
        .collect::<Result<_, _>>()
        .map_err(|e| e.to_string())?;
    match v[..] {
        [r, g, b] if v.iter().all(|c| (0.0..=1.0).contains(c)) => Ok([r, g, b]),
        _ => Err(format!("expected r,g,b with components in 0..1, got {s:?}")),
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
    /// Gaussians above the threshold (all of them, for the summary).
    pub summary: MatchSummary,
    /// The best `top_k` matches above the threshold, best first.
    pub matches: Vec<Match>,
    /// When nothing reaches the threshold: the `top_k` best-scoring Gaussians anyway, so the user
    /// sees how close the scene came (empty otherwise).
    pub nearest_below_threshold: Vec<Match>,
    /// The highlighted .ply, if written.
    pub highlighted_ply: Option<PathBuf>,
}

/// How to give a prompt to `slag-encoder query` (the hint of a refused prompt).
pub const PROMPT_HINT: &str = "pass --text \"a chair\"";

/// Runs `query`.
///
/// Errors: a blank prompt or one over [`slag_common::prompt::MAX_PROMPT_BYTES`] (the limit of
/// `slag-edge`; [`slag_common::Error::Query`], checked before anything is read), unreadable
/// embeddings or models.
pub fn run(a: &QueryArgs) -> anyhow::Result<QueryOutput> {
    slag_common::prompt::check_prompt(&a.text, PROMPT_HINT)?;
    let emb = Embeddings::read(&a.embeddings)?;
    let mut text = TextEncoder::new(&a.clip_textual, &a.tokenizer, a.ep)?;
    text.check_pair(&emb.model)?;
    let q = text.encode(&[a.text.as_str()])?.remove(0);
    let (all, summary) = similarity::rank(
        &emb.ids,
        &emb.means,
        &emb.vectors,
        emb.dim,
        &q,
        None,
        Some(a.threshold),
    )?;
    if let (Some(src), Some(dst)) = (&a.ply, &a.highlight_out) {
        let mut hit = vec![
            false;
            emb.scene_gaussians
                .max(emb.ids.iter().map(|&i| i as u64 + 1).max().unwrap_or(0))
                as usize
        ];
        all.iter().for_each(|m| hit[m.id as usize] = true);
        let rgb = a.highlight_rgb;
        slag_common::scene::write_highlighted_ply(src, dst, |i| {
            hit.get(i).copied().unwrap_or(false).then_some(rgb)
        })?;
    }
    let nearest_below_threshold = if all.is_empty() {
        similarity::rank(
            &emb.ids,
            &emb.means,
            &emb.vectors,
            emb.dim,
            &q,
            Some(a.top_k),
            None,
        )?
        .0
    } else {
        Vec::new()
    };
    Ok(QueryOutput {
        query: a.text.clone(),
        model: emb.model.clone(),
        threshold: a.threshold,
        summary,
        matches: all.into_iter().take(a.top_k).collect(),
        nearest_below_threshold,
        highlighted_ply: a.highlight_out.clone(),
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn args(text: &str) -> QueryArgs {
        QueryArgs {
            embeddings: "does-not-exist.safetensors".into(),
            clip_textual: "m.onnx".into(),
            tokenizer: "t.json".into(),
            text: text.into(),
            top_k: 5,
            threshold: similarity::PAPER_THRESHOLD,
            ply: None,
            highlight_out: None,
            highlight_rgb: [1.0, 0.0, 1.0],
            ep: EpArg::Cpu,
        }
    }

    #[test]
    fn blank_and_too_long_prompts_are_typed_errors_with_the_cli_hint() {
        let long = "x".repeat(slag_common::prompt::MAX_PROMPT_BYTES + 1);
        for (text, needle) in [
            ("", "missing query text"),
            (" \t", "missing query text"),
            (long.as_str(), "at most 1000"),
        ] {
            let e = run(&args(text)).unwrap_err();
            let typed = e.downcast_ref::<slag_common::Error>();
            assert!(
                matches!(typed, Some(slag_common::Error::Query { field: "text", .. })),
                "{e:#}"
            );
            let m = format!("{e:#}");
            assert!(
                m.contains(needle) && m.contains("--text") && !m.contains("/query?"),
                "{m}"
            );
        }
        // A valid prompt gets past the check (then fails on the missing file, not the prompt).
        let m = format!("{:#}", run(&args("a chair")).unwrap_err());
        assert!(m.contains("does-not-exist"), "{m}");
    }
}
