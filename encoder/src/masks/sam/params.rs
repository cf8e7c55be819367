//! What a SAM automatic mask generation run is asked for: its parameters (segment_anything
//! 1.0's names), their checks, the decoder's batch size per device and the prompt grid.

use slag_common::Result;

use crate::check::require;
use crate::preprocess::SAM_IMAGE_SIZE;

/// `SamAutomaticMaskGenerator` parameters (segment_anything 1.0 names and semantics).
///
/// The defaults are those of slag's reference run (`shared/fixtures/sam-amg/reference.json`), not
/// segment_anything's ViT-H defaults (32 points per side, 0.88 / 0.95 thresholds).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SamParams {
    /// Grid points along each image side (`points_per_side`² prompts per image).
    pub points_per_side: u32,
    /// Prompts per decoder call. Results do not depend on it; memory and speed do (one call
    /// holds `points_per_batch * 4` low-resolution, or full-resolution, f32 logit maps). `None`:
    /// [`GPU_POINTS_PER_BATCH`] when the decoder runs on a GPU, [`CPU_POINTS_PER_BATCH`] on the
    /// CPU. See [`SamParams::batch_for`].
    #[serde(default)]
    pub points_per_batch: Option<usize>,
    /// Keep masks whose predicted IoU is `>` this.
    pub pred_iou_thresh: f32,
    /// Keep masks whose stability score is `>=` this.
    pub stability_score_thresh: f32,
    /// Logit offset for the stability score.
    pub stability_score_offset: f32,
    /// Box IoU above which NMS drops the lower-scored mask.
    pub box_nms_thresh: f32,
    /// Logit threshold that binarises masks (`Sam.mask_threshold`).
    pub mask_threshold: f32,
    /// Where the full-resolution logits come from.
    #[serde(default)]
    pub postprocess: MaskPostprocess,
    /// Host memory one decoder call may take, bytes: the prompts per call are then at most
    /// `decoder_batch_bytes / `[`decoder_bytes_per_prompt`] (at least 1), fewer than
    /// `points_per_batch` on large images. Results do not depend on it. `None`: no cap (GPU
    /// sessions, whose tensors are on the device). The encoder sets it for CPU front workers,
    /// which each hold their own sessions: one budget shared by all of them.
    #[serde(default)]
    pub decoder_batch_bytes: Option<usize>,
}

/// Host bytes one prompt costs in a CPU decoder call on an image of `h × w` pixels: its 4
/// multimask channels as f32 at the image size and at SAM's 1024 × 1024 upsampling step, each
/// held twice (the resize's input and output, kept in ONNX Runtime's arena). Measured with
/// color-sam at 990 × 742: 61 MB per prompt; this gives 57 MB.
pub fn decoder_bytes_per_prompt(h: u32, w: u32) -> usize {
    let full = h as usize * w as usize;
    let up = SAM_IMAGE_SIZE as usize * SAM_IMAGE_SIZE as usize;
    2 * 4 * std::mem::size_of::<f32>() * (full + up)
}

impl SamParams {
    /// Prompts per decoder call on an image of `h × w` pixels with the decoder on a GPU
    /// (`on_gpu`) or not: `points_per_batch`, or when it is `None` [`GPU_POINTS_PER_BATCH`] on
    /// a GPU (at most the grid) and [`CPU_POINTS_PER_BATCH`] on the CPU; capped by
    /// [`SamParams::decoder_batch_bytes`] (at least 1).
    pub fn batch_for(&self, h: u32, w: u32, on_gpu: bool) -> usize {
        let cap = self
            .decoder_batch_bytes
            .map_or(usize::MAX, |b| b / decoder_bytes_per_prompt(h, w));
        let grid = (self.points_per_side as usize).pow(2);
        let wanted = match self.points_per_batch {
            Some(n) => n,
            None if on_gpu => grid.min(GPU_POINTS_PER_BATCH),
            None => CPU_POINTS_PER_BATCH,
        };
        wanted.min(cap).max(1)
    }
}

/// Prompts per decoder call on the CPU when none is asked for (segment_anything's default).
pub const CPU_POINTS_PER_BATCH: usize = 64;

/// Prompts per decoder call on a GPU when none is asked for. Fewer, larger calls keep the GPU
/// busier, and a decoder that does the image's work once per call (scripts/export-models.py)
/// does it for more prompts at a time; larger calls also hold larger outputs on the host. On an
/// H100 (2M Gaussians, 250 views, ViT-H fp16 timing model, 4 fronts, one run each) 128 gave an
/// encode of 45.9 s at 6.82 GiB peak RSS, 256 gave 46.1 s at 8.47 GiB.
pub const GPU_POINTS_PER_BATCH: usize = 128;

/// Where AMG's full-resolution mask logits come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MaskPostprocess {
    /// `low_res_masks` (P × 4 × 256 × 256) from the decoder, upsampled on the host for the
    /// candidates that pass the predicted-IoU filter only (the graph's full-resolution `masks`
    /// output is not requested, so it is neither copied back nor, on the GPU, kept).
    #[default]
    LowRes,
    /// The graph's own `masks` output (P × 4 × H × W), as segment_anything reads it.
    Graph,
}

impl Default for SamParams {
    fn default() -> Self {
        SamParams {
            points_per_side: 16,
            points_per_batch: None,
            pred_iou_thresh: 0.8,
            stability_score_thresh: 0.5,
            stability_score_offset: 1.0,
            box_nms_thresh: 0.7,
            mask_threshold: 0.0,
            postprocess: MaskPostprocess::LowRes,
            decoder_batch_bytes: None,
        }
    }
}

impl SamParams {
    /// Checks ranges.
    ///
    /// # Errors
    /// [`Error::Param`] (named by the field) for zero counts or non-finite / out-of-range
    /// thresholds.
    pub fn validate(&self) -> Result<()> {
        let side = self.points_per_side;
        require(
            (1..=1024).contains(&side),
            "points_per_side",
            side,
            "SAM points per side in 1..=1024",
        )?;
        let batch = self.points_per_batch.unwrap_or(1);
        require(
            batch > 0,
            "points_per_batch",
            batch,
            "at least 1 SAM point prompt per batch",
        )?;
        for (name, v) in [
            ("pred_iou_thresh", self.pred_iou_thresh),
            ("stability_score_thresh", self.stability_score_thresh),
            ("box_nms_thresh", self.box_nms_thresh),
        ] {
            let in_unit_interval = (0.0..=1.0).contains(&v);
            require(in_unit_interval, name, v, "a SAM threshold in [0, 1]")?;
        }
        for (name, v) in [
            ("stability_score_offset", self.stability_score_offset),
            ("mask_threshold", self.mask_threshold),
        ] {
            require(v.is_finite(), name, v, "a finite SAM logit offset")?;
        }
        Ok(())
    }
}

/// segment_anything's `build_point_grid(n)`: `n`² points in `[0, 1]²`, row-major (x fastest),
/// at `linspace(1/(2n), 1 - 1/(2n), n)`, as `(x, y)`.
pub fn build_point_grid(n: u32) -> Vec<[f64; 2]> {
    let n = n as usize;
    let offset = 1.0 / (2.0 * n as f64);
    // numpy.linspace: start + i * step, the last value set to stop exactly.
    let side: Vec<f64> = if n == 1 {
        vec![offset]
    } else {
        let step = (1.0 - 2.0 * offset) / (n - 1) as f64;
        (0..n)
            .map(|i| {
                if i == n - 1 {
                    1.0 - offset
                } else {
                    offset + i as f64 * step
                }
            })
            .collect()
    };
    let mut pts = Vec::with_capacity(n * n);
    for &y in &side {
        for &x in &side {
            pts.push([x, y]);
        }
    }
    pts
}
