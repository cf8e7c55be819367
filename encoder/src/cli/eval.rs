//! `slag-encoder eval-colors`: colour mIoU of an embeddings file with color-clip (the accuracy
//! instrument of every speed/accuracy trade).

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;
use slag_common::embeddings::Embeddings;
use slag_common::scene::{self, PlyLoadOptions};
use slag_common::text::TextEncoder;

use super::EpArg;
use crate::eval;

/// Arguments of `eval-colors`.
#[derive(Debug, Clone, Args)]
pub struct EvalArgs {
    /// Scene folder (its point_cloud.ply gives the ground truth colours), or use --ply.
    #[arg(long)]
    pub scene: PathBuf,
    /// The .ply the embeddings were made from; default <scene>/point_cloud.ply.
    #[arg(long)]
    pub ply: Option<PathBuf>,
    /// embeddings.safetensors written by `encode` with color-clip.
    #[arg(long)]
    pub embeddings: PathBuf,
    /// color-clip text tower; default <shared>/fixtures/clip/color-clip-textual.onnx.
    #[arg(long)]
    pub clip_textual: Option<PathBuf>,
    /// CLIP tokenizer; default <shared>/fixtures/clip/clip-tokenizer.json.
    #[arg(long)]
    pub tokenizer: Option<PathBuf>,
    /// color-clip class rule; default <shared>/fixtures/clip/color-clip.json.
    #[arg(long)]
    pub classes: Option<PathBuf>,
    /// ONNX Runtime execution provider.
    #[arg(long, value_enum, default_value_t = EpArg::Cpu)]
    pub ep: EpArg,
}

/// Runs `eval-colors` and returns the evaluation (serialisable to JSON).
pub fn run(a: &EvalArgs) -> anyhow::Result<eval::ColourEval> {
    let clip_dir = slag_common::paths::shared_dir()
        .join("fixtures")
        .join("clip");
    let or = |p: &Option<PathBuf>, name: &str| p.clone().unwrap_or_else(|| clip_dir.join(name));
    let classes = eval::ColorClasses::load(&or(&a.classes, "color-clip.json"))?;
    let ply = a
        .ply
        .clone()
        .unwrap_or_else(|| a.scene.join("point_cloud.ply"));
    let gaussians = scene::load_ply(&ply, PlyLoadOptions { colours: true })?;
    let emb = Embeddings::read(&a.embeddings)?;
    if emb.scene_gaussians != gaussians.len() as u64 {
        anyhow::bail!(
            "{} was made from a scene of {} Gaussians but {} has {}; pass the .ply used by encode (--ply)",
            a.embeddings.display(),
            emb.scene_gaussians,
            ply.display(),
            gaussians.len()
        );
    }
    let mut text = TextEncoder::new(
        &or(&a.clip_textual, "color-clip-textual.onnx"),
        &or(&a.tokenizer, "clip-tokenizer.json"),
        a.ep.into(),
    )?;
    let names: Vec<&str> = classes.names.iter().map(String::as_str).collect();
    let text_embeds = text.encode(&names).context("encoding the colour prompts")?;
    let gt = eval::ground_truth(&classes, &gaussians)?;
    let predicted = eval::assign(&emb, &text_embeds)?;
    Ok(eval::evaluate(&gt, &emb, &predicted, &classes.names)?)
}
