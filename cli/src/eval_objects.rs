//! `slag-encoder eval-objects`: instance AP50 and box IoU of the objects in query answers on a
//! `synth-scene --objects` scene, against the placed boxes ([`slag_eval::instances`]).

use std::path::PathBuf;

use clap::Args;
use slag_common::objects;
use slag_encoder::args::{RasterArg, SmoothArg};
use slag_eval::instances::{EvalObjectsConfig, ObjectsEval, evaluate_synthetic_objects};
use slag_eval::object_truth::{ObjectTruthConfig, ObjectTruthEval, run_object_truth};

use crate::EpArg;
use crate::query::ObjectGroupingArgs;

/// Arguments of `eval-objects`.
#[derive(Debug, Clone, Args)]
pub struct EvalObjectsArgs {
    /// The scene folder written by `synth-scene --objects K` (objects.json, point_cloud.ply).
    #[arg(long = "scene-dir", value_name = "DIR")]
    pub scene: PathBuf,
    /// The embeddings of that scene, made with color-clip: OUT/mixture.safetensors (the default
    /// output) or the dense OUT/embeddings.safetensors.
    #[arg(long, value_name = "FILE")]
    pub embeddings: PathBuf,
    /// Folder holding color-clip-textual.onnx and clip-tokenizer.json; default
    /// `$SLAG_SHARED/fixtures/clip`.
    #[arg(long, value_name = "DIR")]
    pub color_clip: Option<PathBuf>,
    #[command(flatten)]
    pub grouping: ObjectGroupingArgs,
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
    /// Also score the held-out views and the Gaussians against the object truth (a scene of
    /// `synth-scene --objects K --room`, its truth.json): per-pixel and per-Gaussian mIoU of
    /// slag, the mixture and, with segments, every prediction-filtering variant
    /// (`object_truth` in the output).
    #[arg(long)]
    pub held_out: bool,
    /// With --held-out: more segmentations to filter with in the same pass (variants named
    /// `pf-…@<folder>/<stem>`).
    #[arg(long, value_name = "FILE", requires = "held_out")]
    pub more_segments: Vec<PathBuf>,
    /// With --held-out: the held-out step (the encoder's `--hold-out-every`, else its
    /// `--every`); default from the report.json beside --embeddings.
    #[arg(long = "hold-out-every", value_name = "N", requires = "held_out")]
    pub every: Option<usize>,
    /// With --held-out: write a picture of the first held-out view here (PNG: the photo, the
    /// rendered object-class map, slag's classes and pf-majority's, side by side).
    #[arg(long, value_name = "FILE", requires = "held_out")]
    pub picture: Option<PathBuf>,
    /// With --held-out: weight rasterizer of the held-out renders.
    #[arg(long, value_enum, default_value_t = RasterArg::Gpu)]
    pub rasterizer: RasterArg,
}

/// What `eval-objects` prints: the instance scores, and with --held-out the object-truth pass.
#[derive(Debug, Clone, serde::Serialize)]
pub struct EvalObjectsOutput {
    /// AP50, box IoU and the segments against the instances.
    #[serde(flatten)]
    pub objects: ObjectsEval,
    /// The held-out pass on the object truth (--held-out).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub object_truth: Option<ObjectTruthEval>,
}

/// Runs `eval-objects`.
///
/// Errors: `$SLAG_SHARED` unset without --color-clip, then
/// [`evaluate_synthetic_objects`]'s.
pub fn run(a: &EvalObjectsArgs) -> anyhow::Result<EvalObjectsOutput> {
    let color_clip = match &a.color_clip {
        Some(d) => d.clone(),
        None => slag_common::paths::shared_dir()?
            .join("fixtures")
            .join("clip"),
    };
    let objects = evaluate_synthetic_objects(&EvalObjectsConfig {
        scene: a.scene.clone(),
        embeddings: a.embeddings.clone(),
        color_clip: color_clip.clone(),
        objects: a.grouping.params(objects::DEFAULT_MAX_OBJECTS, None),
        smooth: a.smooth.iter().map(|&s| s.into()).collect(),
        segments: a.segments.clone(),
        ep: a.ep.into(),
    })?;
    let object_truth = if a.held_out {
        let mut segments: Vec<PathBuf> = a.segments.iter().cloned().collect();
        if segments.is_empty() && !a.more_segments.is_empty() {
            segments.push(
                a.embeddings
                    .parent()
                    .unwrap_or(std::path::Path::new("."))
                    .join(slag_common::segments::FILE_NAME),
            );
        }
        segments.extend(a.more_segments.iter().cloned());
        Some(run_object_truth(&ObjectTruthConfig {
            scene: a.scene.clone(),
            embeddings: a.embeddings.clone(),
            color_clip: color_clip.clone(),
            segments,
            every: a.every,
            rasterizer: a.rasterizer.into(),
            ep: a.ep.into(),
            picture: a.picture.clone(),
        })?)
    } else {
        None
    };
    Ok(EvalObjectsOutput {
        objects,
        object_truth,
    })
}
