//! `slag-encoder segment`: the geometric segments of an existing scene's Gaussians
//! ([`slag_encoder::segments`]), without re-encoding, written as `segments.safetensors`.

use std::path::PathBuf;

use clap::Args;
use slag_common::mask_record::{self, MaskRecord};
use slag_encoder::segments::{SegmentParams, SegmentStats, segment};

use slag_encoder::args::SegmentArgs;

/// Arguments of `segment`.
#[derive(Debug, Clone, Args)]
pub struct SegmentCmdArgs {
    /// Scene folder holding point_cloud.ply, or use --ply.
    #[arg(
        long = "scene-dir",
        value_name = "DIR",
        required_unless_present = "ply"
    )]
    pub scene: Option<PathBuf>,
    /// The trained 3DGS .ply (INRIA layout); default <scene>/point_cloud.ply.
    #[arg(long)]
    pub ply: Option<PathBuf>,
    /// Output file, normally beside the embeddings: OUT/segments.safetensors (`partition` and
    /// `eval-colors --prediction-filtering` look for it there).
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
    /// The encode's masks' record (the segmentation's mask term); default
    /// mask-record.safetensors beside --out when it exists, else geometry only (with a warning).
    #[arg(long, value_name = "FILE", conflicts_with = "geometry_only")]
    pub mask_record: Option<PathBuf>,
    /// Segment from the geometry alone, even when a masks' record is beside --out.
    #[arg(long)]
    pub geometry_only: bool,
    #[command(flatten)]
    pub segment: SegmentArgs,
}

/// Runs `segment`: loads the `.ply`, segments it, writes `--out` atomically; returns the stats.
pub fn run(a: &SegmentCmdArgs) -> anyhow::Result<SegmentStats> {
    let ply = match (&a.ply, &a.scene) {
        (Some(p), _) => p.clone(),
        (None, Some(s)) => s.join("point_cloud.ply"),
        (None, None) => anyhow::bail!("pass --scene-dir DIR or --ply FILE"),
    };
    let g = slag_common::scene::load_ply(&ply, slag_common::scene::PlyLoadOptions::default())?;
    let params = SegmentParams::from(&a.segment);
    let record = mask_record(a)?.map(std::sync::Arc::new);
    let (segments, stats) = segment(&g, &params, &ply.display().to_string(), record)?;
    segments.write(&a.out)?;
    Ok(stats)
}

/// The masks' record `a` asks for: `--mask-record`, else the one beside `--out`, else none.
fn mask_record(a: &SegmentCmdArgs) -> anyhow::Result<Option<MaskRecord>> {
    if a.geometry_only {
        return Ok(None);
    }
    let path = match &a.mask_record {
        Some(p) => p.clone(),
        None => {
            let beside = a
                .out
                .parent()
                .unwrap_or(std::path::Path::new("."))
                .join(mask_record::FILE_NAME);
            if !beside.exists() {
                tracing::warn!(
                    "no {} beside {}: segments from the geometry alone (pass --mask-record FILE, \
                     or re-encode to get one)",
                    mask_record::FILE_NAME,
                    a.out.display()
                );
                return Ok(None);
            }
            beside
        }
    };
    Ok(Some(MaskRecord::read(&path)?))
}
