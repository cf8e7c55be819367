//! `slag-encoder eval-objects`: instance AP50 and box IoU of the objects in query answers on a
//! `synth-scene --objects` scene, against the placed boxes ([`slag_eval::instances`]).

use std::path::PathBuf;

use clap::Args;
use slag_common::objects::{self, ObjectParams};
use slag_encoder::args::SmoothArg;
use slag_eval::instances::{EvalObjectsConfig, ObjectsEval, evaluate_synthetic_objects};

use crate::EpArg;

/// Arguments of `eval-objects`.
#[derive(Debug, Clone, Args)]
pub struct EvalObjectsArgs {
    /// The scene folder written by `synth-scene --objects K` (objects.json, point_cloud.ply).
    #[arg(long)]
    pub scene: PathBuf,
    /// embeddings.safetensors of that scene, made with color-clip.
    #[arg(long)]
    pub embeddings: PathBuf,
    /// Folder holding color-clip-textual.onnx and clip-tokenizer.json; default
    /// `$SLAG_SHARED/fixtures/clip`.
    #[arg(long, value_name = "DIR")]
    pub color_clip: Option<PathBuf>,
    /// Matches closer than this (scene units) join one object.
    #[arg(long, default_value_t = objects::DEFAULT_GAP)]
    pub object_gap: f32,
    /// Objects of fewer matching Gaussians are dropped.
    #[arg(long, default_value_t = objects::DEFAULT_MIN_GAUSSIANS)]
    pub object_min_gaussians: usize,
    /// Score smoothing of the queries, one score per value (repeat the flag: `--smooth none
    /// --smooth segment`); `segment` scores each Gaussian with its geometric segment's mean.
    #[arg(long, value_enum, default_values_t = [SmoothArg::None])]
    pub smooth: Vec<SmoothArg>,
    /// Segments for --smooth segment; default segments.safetensors beside --embeddings.
    #[arg(long, value_name = "FILE")]
    pub segments: Option<PathBuf>,
    /// ONNX Runtime execution provider.
    #[arg(long, value_enum, default_value_t = EpArg::Cpu)]
    pub ep: EpArg,
}

/// Runs `eval-objects`.
///
/// Errors: `$SLAG_SHARED` unset without --color-clip, then
/// [`evaluate_synthetic_objects`]'s.
pub fn run(a: &EvalObjectsArgs) -> anyhow::Result<ObjectsEval> {
    let color_clip = match &a.color_clip {
        Some(d) => d.clone(),
        None => slag_common::paths::shared_dir()?
            .join("fixtures")
            .join("clip"),
    };
    Ok(evaluate_synthetic_objects(&EvalObjectsConfig {
        scene: a.scene.clone(),
        embeddings: a.embeddings.clone(),
        color_clip,
        objects: ObjectParams {
            gap: a.object_gap,
            min_gaussians: a.object_min_gaussians,
            max_objects: objects::DEFAULT_MAX_OBJECTS,
            near: None,
        },
        smooth: a.smooth.iter().map(|&s| s.into()).collect(),
        segments: a.segments.clone(),
        ep: a.ep.into(),
    })?)
}
