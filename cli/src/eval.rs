//! `slag-encoder eval-colors`: colour mIoU of an embeddings file with color-clip (the accuracy
//! instrument of every speed/accuracy trade), per Gaussian or with `--held-out` per pixel of the
//! views the encoder never saw ([`slag_eval::colors`]).

use std::path::PathBuf;

use clap::Args;
use slag_encoder::args::RasterArg;
use slag_eval::colors::EvalColorsConfig;

use crate::EpArg;

/// Arguments of `eval-colors`.
#[derive(Debug, Clone, Args)]
pub struct EvalArgs {
    /// Scene folder (its point_cloud.ply gives the ground truth colours), or use --ply.
    #[arg(long = "scene-dir", value_name = "DIR")]
    pub scene: PathBuf,
    /// The .ply the embeddings were made from; default <scene>/point_cloud.ply.
    #[arg(long)]
    pub ply: Option<PathBuf>,
    /// The dense embeddings.safetensors written by `encode --dense` with color-clip (the scores
    /// use each Gaussian's Σa, which the mixture does not store).
    #[arg(long, value_name = "FILE")]
    pub embeddings: PathBuf,
    /// Folder holding color-clip (`color-clip-textual.onnx`, `clip-tokenizer.json`,
    /// `color-clip.json`); default `$SLAG_SHARED/fixtures/clip`. The three flags below override
    /// single files.
    #[arg(long, value_name = "DIR")]
    pub color_clip: Option<PathBuf>,
    /// color-clip text tower; default <color-clip>/color-clip-textual.onnx.
    #[arg(long, alias = "text-model", value_name = "ONNX")]
    pub clip_textual: Option<PathBuf>,
    /// CLIP tokenizer; default <color-clip>/clip-tokenizer.json.
    #[arg(long)]
    pub tokenizer: Option<PathBuf>,
    /// color-clip class rule; default <color-clip>/color-clip.json.
    #[arg(long)]
    pub classes: Option<PathBuf>,
    /// ONNX Runtime execution provider.
    #[arg(long, value_enum, default_value_t = EpArg::Cpu)]
    pub ep: EpArg,
    /// 2D held-out protocol: render the class scores into the views the encoder never saw
    /// (index ≡ N/2 mod N for `--every N` or `--hold-out-every N`) at full resolution and score them per pixel against the
    /// photos' colour classes, with the majority-class and pixel-lifting-oracle baselines.
    #[arg(long)]
    pub held_out: bool,
    /// The held-out step (held-out only): the encoder's `--hold-out-every`, else its `--every`;
    /// default: `inputs.hold_out_every`, else `inputs.every`, of the report.json beside the
    /// embeddings.
    #[arg(long = "hold-out-every", value_name = "N")]
    pub every: Option<usize>,
    /// The encoder's `--raster-scale`, at which the oracle lifts the encoded views (held-out
    /// only); default: `parameters.raster_scale` of the report.json beside the embeddings. The
    /// held-out views are always rendered at full resolution.
    #[arg(long)]
    pub raster_scale: Option<f64>,
    /// Weight rasterizer for the held-out renders and the oracle.
    #[arg(long, value_enum, default_value_t = RasterArg::Gpu)]
    pub rasterizer: RasterArg,
    /// More embeddings files of the same scene and --every to score in the same held-out pass
    /// (held-out only; listed under `variants` by path). Forms beside the main embeddings are
    /// scored too: `embeddings-level{0,1,2}.safetensors` (`encode --levels`) and
    /// `mixture.safetensors` (`encode --mixture-keep`).
    #[arg(long, value_name = "EMBEDDINGS")]
    pub compare: Vec<PathBuf>,
    /// Prediction filtering (SLAG PF): also score each segment's majority class (3D score), and
    /// measure the segments (purity against the colour classes, count and sizes); with
    /// --held-out the tables `argmax`, `pf-majority`, `pf-mean`, `pf-weighted`, `pf-confident`
    /// under `variants`.
    /// Needs the segments of `slag-encoder segment` (--segments).
    #[arg(long, alias = "pf")]
    pub prediction_filtering: bool,
    /// Segments for --prediction-filtering; default segments.safetensors beside --embeddings.
    #[arg(long, value_name = "FILE", requires = "prediction_filtering")]
    pub segments: Option<PathBuf>,
    /// More segments files of the same scene, measured (purity, sizes) and, with --held-out,
    /// filtered in the same pass (variants named `pf-…@<folder>/<stem>`).
    #[arg(long, value_name = "FILE", requires = "prediction_filtering")]
    pub more_segments: Vec<PathBuf>,
    /// The encode's masks' record, measured against the colour classes with --prediction-filtering
    /// (mask purity, and how its disagreement separates neighbours of different classes); default
    /// mask-record.safetensors beside --embeddings when it exists.
    #[arg(long, value_name = "FILE", requires = "prediction_filtering")]
    pub mask_record: Option<PathBuf>,
    /// With --held-out --prediction-filtering: write each Gaussian's lifted photo class (the
    /// oracle's class of most weight; one byte per Gaussian, 255 = none) to this file.
    #[arg(long, value_name = "FILE", requires = "prediction_filtering")]
    pub photo_classes_out: Option<PathBuf>,
    /// With --prediction-filtering (3D): also measure the segments' purity against the lifted
    /// photo classes of this file (written by --photo-classes-out on the same encode).
    #[arg(long, value_name = "FILE", requires = "prediction_filtering")]
    pub photo_classes: Option<PathBuf>,
}

impl From<&EvalArgs> for EvalColorsConfig {
    fn from(a: &EvalArgs) -> Self {
        EvalColorsConfig {
            scene: a.scene.clone(),
            ply: a.ply.clone(),
            embeddings: a.embeddings.clone(),
            color_clip: a.color_clip.clone(),
            clip_textual: a.clip_textual.clone(),
            tokenizer: a.tokenizer.clone(),
            classes: a.classes.clone(),
            ep: a.ep.into(),
            every: a.every,
            raster_scale: a.raster_scale,
            rasterizer: a.rasterizer.into(),
            compare: a.compare.clone(),
            prediction_filtering: a.prediction_filtering,
            segments: a.segments.clone(),
            more_segments: a.more_segments.clone(),
            mask_record: a.mask_record.clone(),
            photo_classes_out: a.photo_classes_out.clone(),
            photo_classes: a.photo_classes.clone(),
        }
    }
}
