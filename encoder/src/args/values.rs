//! The values of the flags that pick a library setting (`--masks`, `--rasterizer`,
//! `--mask-weighting`, `--overlap`, `--smooth`, `--views`), each mapped to its library type with
//! `From`.

use crate::aggregate::{MaskOverlap, MaskWeighting};
use crate::config::{MaskSource, RasterBackend};
use crate::query::Smooth;

/// `--masks`: where the masks come from ([`MaskSource`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum MaskSourceArg {
    /// SAM automatic mask generation over [`SamConfig::encoder`] / [`SamConfig::decoder`]
    /// (the default, as in the paper).
    #[default]
    #[value(help = "SAM automatic mask generation over `--sam-encoder` / `--sam-decoder`")]
    Sam,
    /// Felzenszwalb-Huttenlocher graph segmentation (no model, fast, CPU).
    Graph,
}

#[cfg(doc)]
use crate::config::SamConfig;

impl From<MaskSourceArg> for MaskSource {
    fn from(a: MaskSourceArg) -> Self {
        match a {
            MaskSourceArg::Sam => MaskSource::Sam,
            MaskSourceArg::Graph => MaskSource::Graph,
        }
    }
}

/// `--rasterizer`: which weight rasterizer runs ([`RasterBackend`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum RasterArg {
    /// wgpu compute (Vulkan: a GPU, or Mesa lavapipe on CPU-only machines).
    #[default]
    Gpu,
    /// The slow f64 CPU reference (for checking).
    Cpu,
}

impl From<RasterArg> for RasterBackend {
    fn from(a: RasterArg) -> Self {
        match a {
            RasterArg::Gpu => RasterBackend::Gpu,
            RasterArg::Cpu => RasterBackend::Cpu,
        }
    }
}

/// `--mask-weighting`: specificity weighting of the image stage ([`MaskWeighting`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum MaskWeightingArg {
    /// `g_j = 1`: the paper's mean.
    #[default]
    None,
    /// `g_j = image pixels / mask area` (≥ 1): small, specific masks (parts) outweigh large
    /// ones (wholes, background) covering the same Gaussian.
    Area,
    /// `g_j = SAM predicted IoU × stability score` (both 1 for generators without scores, e.g.
    /// the graph segmenter): confident masks outweigh doubtful ones.
    SamScore,
}

impl From<MaskWeightingArg> for MaskWeighting {
    fn from(a: MaskWeightingArg) -> Self {
        match a {
            MaskWeightingArg::None => MaskWeighting::None,
            MaskWeightingArg::Area => MaskWeighting::Area,
            MaskWeightingArg::SamScore => MaskWeighting::SamScore,
        }
    }
}

/// `--crop-fill`: where a mask crop's white fill is applied ([`crate::clip::CropFill`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum CropFillArg {
    /// White outside the mask at the image's resolution, then the resize to CLIP's 224 × 224:
    /// the paper's crop (border pixels blend with the white).
    #[default]
    BeforeResize,
    /// The box of the image and of the mask resized alike, then white where the resized mask
    /// is below one half: the object's border pixels keep their colour.
    AfterResize,
}

impl From<CropFillArg> for crate::clip::CropFill {
    fn from(a: CropFillArg) -> Self {
        match a {
            CropFillArg::BeforeResize => crate::clip::CropFill::BeforeResize,
            CropFillArg::AfterResize => crate::clip::CropFill::AfterResize,
        }
    }
}

/// `--overlap`: how a pixel covered by several masks contributes ([`MaskOverlap`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum OverlapArg {
    /// To every mask that covers it (the paper's `a_kj = Σ_{p∈M_j} w_kp`).
    #[default]
    All,
    /// Only to the smallest covering mask (fewest pixels; ties: the lower mask index).
    Finest,
}

impl From<OverlapArg> for MaskOverlap {
    fn from(a: OverlapArg) -> Self {
        match a {
            OverlapArg::All => MaskOverlap::All,
            OverlapArg::Finest => MaskOverlap::Finest,
        }
    }
}

/// `--smooth`: whether a Gaussian's score is its own or smoothed within its segment
/// ([`Smooth`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum SmoothArg {
    /// Each Gaussian's own cosine (the paper's query).
    #[default]
    None,
    /// Each Gaussian scores the mean cosine of its geometric segment
    /// ([`slag_common::segments::segment_mean`]), so a segment matches or not as a whole.
    Segment,
}

impl From<SmoothArg> for Smooth {
    fn from(a: SmoothArg) -> Self {
        match a {
            SmoothArg::None => Smooth::None,
            SmoothArg::Segment => Smooth::Segment,
        }
    }
}

/// `--views`: which training views are encoded ([`crate::views::SelectionMode`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum ViewsArg {
    /// Every training view.
    All,
    /// `--view-count` training views, evenly spaced in name order.
    Uniform,
    /// The views a cheap weight-raster pass finds necessary: greedily, until every observed
    /// Gaussian is seen with `--view-coverage-weight` from `--view-coverage-min-views` viewpoints
    /// `--view-coverage-angle` apart; stops where a view adds less than
    /// `--view-coverage-min-gain` of the first view's gain (the default).
    #[default]
    Coverage,
}

impl From<ViewsArg> for crate::views::SelectionMode {
    fn from(a: ViewsArg) -> Self {
        match a {
            ViewsArg::All => crate::views::SelectionMode::All,
            ViewsArg::Uniform => crate::views::SelectionMode::Uniform,
            ViewsArg::Coverage => crate::views::SelectionMode::Coverage,
        }
    }
}
