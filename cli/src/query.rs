//! `slag-encoder query`: check a text prompt against an embeddings file, print the best Gaussians,
//! optionally write a copy of the scene `.ply` with the matches highlighted
//! ([`slag_encoder::query`]).

use std::path::PathBuf;

use clap::Args;
use slag_common::objects::{self, ObjectParams};
use slag_common::similarity;
use slag_encoder::args::SmoothArg;
use slag_encoder::query::{QueryOutput, QueryParams};

use crate::EpArg;

/// Arguments of `query`.
#[derive(Debug, Clone, Args)]
pub struct QueryArgs {
    /// The embeddings `encode` wrote: OUT/mixture.safetensors (the default output) or the dense
    /// OUT/embeddings.safetensors (`encode --dense`); a missing dense file names the mixture
    /// beside it.
    #[arg(long, value_name = "FILE")]
    pub embeddings: PathBuf,
    /// CLIP text tower ONNX (input_ids i64[B,77] -> [B,D]) of the same CLIP model.
    #[arg(long, alias = "text-model", value_name = "ONNX")]
    pub clip_textual: PathBuf,
    /// CLIP BPE tokenizer (tokenizer.json for the `tokenizers` crate).
    #[arg(long)]
    pub tokenizer: PathBuf,
    /// The prompt, e.g. "red" or "a chair" (not blank, at most 1000 bytes, as on slag-edge).
    #[arg(long)]
    pub text: String,
    /// Print at most this many matches.
    #[arg(long, value_name = "K", default_value_t = 100)]
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
    /// Objects printed, 1..=1000.
    #[arg(long, default_value_t = objects::DEFAULT_MAX_OBJECTS)]
    pub max_objects: usize,
    /// x,y,z (scene frame): sort objects by distance from this point instead of by score.
    #[arg(long, allow_hyphen_values = true, value_parser = parse_xyz)]
    pub near: Option<[f32; 3]>,
    #[command(flatten)]
    pub grouping: ObjectGroupingArgs,
    /// `segment`: score each Gaussian with its geometric segment's mean cosine (the
    /// open-vocabulary analogue of prediction filtering); `none`: its own.
    #[arg(long, value_enum, default_value_t = SmoothArg::None)]
    pub smooth: SmoothArg,
    /// Segments for --smooth segment; default segments.safetensors beside --embeddings.
    #[arg(long, value_name = "FILE")]
    pub segments: Option<PathBuf>,
}

/// How the matches are grouped into objects (`query`, `eval-objects`; [`slag_common::objects`]).
#[derive(Debug, Clone, Args)]
pub struct ObjectGroupingArgs {
    /// Single-linkage gap between an object's matches, scene units; default: 4 × the matches'
    /// median nearest-neighbour distance (the scene's own spacing).
    #[arg(long)]
    pub object_gap: Option<f32>,
    /// Smallest object, in matching Gaussians; smaller groups are dropped as stray matches.
    #[arg(long, default_value_t = objects::DEFAULT_MIN_GAUSSIANS)]
    pub object_min_gaussians: usize,
}

impl ObjectGroupingArgs {
    /// The grouping with at most `max_objects` objects, sorted by distance from `near` when
    /// given (else by score mass).
    pub fn params(&self, max_objects: usize, near: Option<[f32; 3]>) -> ObjectParams {
        ObjectParams {
            gap: self.object_gap,
            min_gaussians: self.object_min_gaussians,
            max_objects,
            near,
        }
    }
}

/// Three comma-separated numbers that all pass `valid`, else `expected` (what to write instead)
/// with the text given.
fn parse_triple(s: &str, valid: impl Fn(f32) -> bool, expected: &str) -> Result<[f32; 3], String> {
    let v: Vec<f32> = s
        .split(',')
        .map(|p| p.trim().parse::<f32>())
        .collect::<Result<_, _>>()
        .map_err(|e| e.to_string())?;
    match v[..] {
        [a, b, c] if v.iter().all(|&x| valid(x)) => Ok([a, b, c]),
        _ => Err(format!("expected {expected}, got {s:?}")),
    }
}

fn parse_xyz(s: &str) -> Result<[f32; 3], String> {
    parse_triple(s, f32::is_finite, "x,y,z (three finite numbers)")
}

fn parse_rgb(s: &str) -> Result<[f32; 3], String> {
    parse_triple(
        s,
        |c| (0.0..=1.0).contains(&c),
        "r,g,b with components in 0..1",
    )
}

impl From<&QueryArgs> for QueryParams {
    fn from(a: &QueryArgs) -> Self {
        QueryParams {
            embeddings: a.embeddings.clone(),
            clip_textual: a.clip_textual.clone(),
            tokenizer: a.tokenizer.clone(),
            text: a.text.clone(),
            top_k: a.top_k,
            threshold: a.threshold,
            ply: a.ply.clone(),
            highlight_out: a.highlight_out.clone(),
            highlight_rgb: a.highlight_rgb,
            ep: a.ep.into(),
            objects: a.grouping.params(a.max_objects, a.near),
            smooth: a.smooth.into(),
            segments: a.segments.clone(),
        }
    }
}

/// How to give a prompt to `slag-encoder query` (the hint of a refused prompt).
pub const PROMPT_HINT: &str = "pass --text \"a chair\"";

/// Runs `query`.
///
/// Errors: a blank prompt or one over [`slag_common::prompt::MAX_PROMPT_BYTES`] (the limit of
/// `slag-edge`; [`slag_common::Error::Query`], checked before anything is read), then
/// [`slag_encoder::query::run`]'s.
pub fn run(a: &QueryArgs) -> anyhow::Result<QueryOutput> {
    slag_common::prompt::check_prompt(&a.text, PROMPT_HINT)?;
    Ok(slag_encoder::query::run(&QueryParams::from(a))?)
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
            max_objects: objects::DEFAULT_MAX_OBJECTS,
            near: None,
            grouping: ObjectGroupingArgs {
                object_gap: None,
                object_min_gaussians: objects::DEFAULT_MIN_GAUSSIANS,
            },
            smooth: SmoothArg::None,
            segments: None,
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
