//! `slag-encoder segment`: the geometric segments of an existing scene's Gaussians
//! ([`slag_encoder::segments`]), without re-encoding, written as `segments.safetensors`.

use std::path::PathBuf;

use clap::Args;
use slag_encoder::segments::{SegmentParams, SegmentStats, segment};

use slag_encoder::args::SegmentArgs;

/// Arguments of `segment`.
#[derive(Debug, Clone, Args)]
pub struct SegmentCmdArgs {
    /// Scene folder holding point_cloud.ply, or use --ply.
    #[arg(long, required_unless_present = "ply")]
    pub scene: Option<PathBuf>,
    /// The trained 3DGS .ply (INRIA layout); default <scene>/point_cloud.ply.
    #[arg(long)]
    pub ply: Option<PathBuf>,
    /// Output file, normally beside the embeddings: OUT/segments.safetensors (`partition` and
    /// `eval-colors --prediction-filtering` look for it there).
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
    #[command(flatten)]
    pub segment: SegmentArgs,
}

/// Runs `segment`: loads the `.ply`, segments it, writes `--out` atomically; returns the stats.
pub fn run(a: &SegmentCmdArgs) -> anyhow::Result<SegmentStats> {
    let ply = match (&a.ply, &a.scene) {
        (Some(p), _) => p.clone(),
        (None, Some(s)) => s.join("point_cloud.ply"),
        (None, None) => anyhow::bail!("pass --scene DIR or --ply FILE"),
    };
    let g = slag_common::scene::load_ply(&ply, slag_common::scene::PlyLoadOptions::default())?;
    let params = SegmentParams::from(&a.segment);
    let (segments, stats) = segment(&g, &params, &ply.display().to_string())?;
    segments.write(&a.out)?;
    Ok(stats)
}
