//! CLIP image embeddings of mask crops (SLAG: `E_j` = CLIP embedding of mask `M_j`'s crop).
//!
//! The crop is the paper's: the mask's bounding box (inclusive, SAM/COCO `xywh`), pixels outside
//! the mask set to white (255). Each crop gets open_clip's preprocessing: shortest side 224 with
//! PIL bicubic and centre crop, as bytes ([`crate::preprocess::clip_pixels`]). Where the white
//! fill is applied is [`CropFill`]: before that resize (the paper's order and the default, which
//! blends the mask's border pixels with white) or after it (the box of the image and the mask
//! resized alike, white set at CLIP's resolution). Then CLIP's
//! mean/std ([`crate::preprocess::clip_normalize`]), on the host for a tower whose input is
//! `pixel_values f32[B,3,224,224]`, in the graph for one whose input is `pixels
//! u8[B,3,224,224]` (`scripts/clip-u8-pixels.py`; a quarter of the bytes to copy to a GPU).
//! Crops run through the visual tower in batches, and every output is L2-normalised. On a GPU
//! one [`ClipService`] per GPU owns the tower and batches the crops of every front worker's
//! images together.

use std::path::Path;
use std::sync::{Arc, Mutex, mpsc};
use std::time::Instant;

use image::RgbImage;
use ort::value::TensorRef;
use rayon::prelude::*;
use slag_common::onnx::{self, ElemType, ExecutionProvider, OnnxModel, Placement, TensorSpec};
use slag_common::text::l2_normalize;
use slag_common::{Error, Result};

use crate::masks::Mask;
use crate::preprocess::{CLIP_IMAGE_SIZE, CLIP_PIXELS, clip_normalize, clip_pixels};

const VISUAL_INPUTS: &[TensorSpec] = &[TensorSpec::named(
    "pixel_values",
    ElemType::F32,
    &[-1, 3, 224, 224],
)];
const VISUAL_INPUTS_U8: &[TensorSpec] = &[TensorSpec::named(
    "pixels",
    ElemType::U8,
    &[-1, 3, 224, 224],
)];
const VISUAL_OUTPUTS: &[TensorSpec] = &[TensorSpec::any_name(ElemType::F32, &[-1, -1])];

/// What a CLIP image tower takes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum VisualInput {
    /// `pixel_values f32[B,3,224,224]`: normalised with CLIP's mean/std on the host (every
    /// export of `scripts/export-models.py clip` without `--u8-pixels`, the fixtures).
    F32PixelValues,
    /// `pixels u8[B,3,224,224]`: the crop's RGB bytes; the graph scales and normalises
    /// (`scripts/clip-u8-pixels.py`, `export-models.py clip --u8-pixels`).
    U8Pixels,
}

/// Where a crop's white fill is applied relative to CLIP's resize to 224 × 224 (`encode
/// --crop-fill`).
///
/// The resize (bicubic, as open_clip's) mixes each output pixel from a few input pixels; filled
/// before it, a mask's border pixels are blended with the white outside, which pulls a small or
/// light object's colour towards white. Filled after it, the bounding box of the raw image is
/// resized and the mask with it (the same filter), and every pixel where the resized mask is
/// below one half is set white at CLIP's resolution; before that resize, the mask's colours are
/// extended a few pixels past its border, so a kept pixel mixes only the object's own colours
/// (neither white nor the background next to the object).
/// The two are the same crop when the mask fills its box, or when the box needs no resize.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CropFill {
    /// White outside the mask at the image's resolution, then the resize: the paper's crop
    /// (`np.where(mask, image, 255)` then open_clip's preprocessing), as in
    /// `fixtures/clip/reference.json`. The default: the other order helped the labelled-object
    /// room with heavy texture but cost snowmiku's held-out mIoU
    /// (`docs/results/prediction-filtering.md`).
    #[default]
    BeforeResize,
    /// The box of the image (the mask's colours extended past its border) and of the mask
    /// resized alike, then white where the resized mask is below one half.
    AfterResize,
}

/// The white-background bounding-box crop of `mask` in `image` (the paper's CLIP input):
/// `np.where(mask, image, 255)[y:y+h+1, x:x+w+1]` with `[x, y, w, h] = mask.bbox_xywh`, the box
/// clipped to the image.
///
/// # Errors
/// [`Error::Mismatch`] when the mask and image sizes differ, [`Error::Internal`] for a malformed
/// mask or a box outside the image.
pub fn crop(image: &RgbImage, mask: &Mask) -> Result<RgbImage> {
    let b = crop_box(image, mask)?;
    let src = image.as_raw();
    let mut out = vec![255u8; b.w * b.h * 3];
    for (yy, orow) in out.chunks_exact_mut(b.w * 3).enumerate() {
        let start = (b.y + yy) * b.iw + b.x;
        let inside = &mask.pixels[start..start + b.w];
        let irow = &src[start * 3..(start + b.w) * 3];
        for ((o, i), &m) in orow
            .chunks_exact_mut(3)
            .zip(irow.chunks_exact(3))
            .zip(inside)
        {
            if m != 0 {
                o.copy_from_slice(i);
            }
        }
    }
    b.image(out)
}

/// A mask's bounding box clipped to its image, in pixels (`x`, `y`: top left; `w`, `h`: size;
/// `iw`: the image's width).
struct CropBox {
    x: usize,
    y: usize,
    w: usize,
    h: usize,
    iw: usize,
}

impl CropBox {
    /// `rgb` (`w × h × 3` bytes) as an image of the box's size.
    fn image(&self, rgb: Vec<u8>) -> Result<RgbImage> {
        RgbImage::from_raw(self.w as u32, self.h as u32, rgb)
            .ok_or_else(|| Error::internal("crop buffer size mismatch"))
    }
}

/// The box of `mask` in `image` ([`crop`]), after checking that they fit each other.
///
/// # Errors
/// As [`crop`].
fn crop_box(image: &RgbImage, mask: &Mask) -> Result<CropBox> {
    if (mask.width, mask.height) != image.dimensions() {
        return Err(Error::mismatch(
            slag_common::Mismatched::ImageSize,
            format!(
                "mask is {}x{} but the image is {}x{}: masks must be at full image resolution",
                mask.width,
                mask.height,
                image.width(),
                image.height()
            ),
        ));
    }
    if mask.pixels.len() != mask.width as usize * mask.height as usize {
        return Err(Error::internal(format!(
            "mask has {} pixels, expected {}x{}",
            mask.pixels.len(),
            mask.width,
            mask.height
        )));
    }
    let [x, y, w, h] = mask.bbox_xywh;
    let (iw, ih) = image.dimensions();
    if x >= iw || y >= ih {
        return Err(Error::internal(format!(
            "mask bbox [{x}, {y}, {w}, {h}] starts outside the {iw}x{ih} image"
        )));
    }
    let x1 = x.saturating_add(w).min(iw - 1);
    let y1 = y.saturating_add(h).min(ih - 1);
    Ok(CropBox {
        x: x as usize,
        y: y as usize,
        w: (x1 - x + 1) as usize,
        h: (y1 - y + 1) as usize,
        iw: iw as usize,
    })
}

/// One mask's CLIP input `u8[3, 224, 224]` into `out`, its white fill applied as `fill` says:
/// [`CropFill::BeforeResize`] is [`crop`] then [`clip_pixels`]. [`CropFill::AfterResize`] runs
/// [`clip_pixels`] on the box of the image with the mask's colours extended past its border
/// ([`extend_colours`], as deep as the resize's filter reaches, so no mask pixel is mixed with
/// a pixel outside the mask) and on the box of the mask (0 or 255 in every channel), then sets
/// white every pixel whose resized mask value is below 128.
///
/// # Errors
/// As [`crop`] and [`clip_pixels`].
pub fn mask_crop_pixels(
    image: &RgbImage,
    mask: &Mask,
    fill: CropFill,
    out: &mut [u8],
) -> Result<()> {
    if fill == CropFill::BeforeResize {
        return clip_pixels(&crop(image, mask)?, out);
    }
    let b = crop_box(image, mask)?;
    let src = image.as_raw();
    let mut raw = Vec::with_capacity(b.w * b.h * 3);
    let mut inside = Vec::with_capacity(b.w * b.h);
    for yy in 0..b.h {
        let start = (b.y + yy) * b.iw + b.x;
        raw.extend_from_slice(&src[start * 3..(start + b.w) * 3]);
        inside.extend(mask.pixels[start..start + b.w].iter().map(|&m| m != 0));
    }
    let mask_rgb = inside
        .iter()
        .flat_map(|&m| [if m { 255 } else { 0 }; 3])
        .collect();
    // Bicubic reaches 2 input pixels, or 2 × the shrink factor when the box shrinks to 224.
    let shrink = b.w.min(b.h) as f64 / f64::from(CLIP_IMAGE_SIZE);
    let depth = (2.0 * shrink.max(1.0)).ceil() as usize + 1;
    extend_colours(&mut raw, inside, b.w, depth);
    clip_pixels(&b.image(raw)?, out)?;
    let mut resized = vec![0u8; CLIP_PIXELS];
    clip_pixels(&b.image(mask_rgb)?, &mut resized)?;
    let plane = CLIP_PIXELS / 3;
    for (i, _) in resized[..plane]
        .iter()
        .enumerate()
        .filter(|(_, m)| **m < 128)
    {
        for c in 0..3 {
            out[c * plane + i] = 255;
        }
    }
    Ok(())
}

/// Extends the colours of the pixels marked `inside` of `rgb` (a `width`-pixel wide RGB image)
/// outward by `depth` rings: in each ring, every pixel outside with an 8-neighbour inside (or
/// reached by an earlier ring) takes those neighbours' mean colour.
fn extend_colours(rgb: &mut [u8], mut inside: Vec<bool>, width: usize, depth: usize) {
    let height = inside.len() / width.max(1);
    let mut ring = Vec::new();
    for _ in 0..depth {
        ring.clear();
        for y in 0..height {
            for x in (0..width).filter(|&x| !inside[y * width + x]) {
                let (mut sum, mut n) = ([0u32; 3], 0u32);
                for ny in y.saturating_sub(1)..(y + 2).min(height) {
                    for nx in x.saturating_sub(1)..(x + 2).min(width) {
                        let q = ny * width + nx;
                        if inside[q] {
                            for (s, &v) in sum.iter_mut().zip(&rgb[q * 3..q * 3 + 3]) {
                                *s += u32::from(v);
                            }
                            n += 1;
                        }
                    }
                }
                if n > 0 {
                    ring.push((y * width + x, sum.map(|s| ((s + n / 2) / n) as u8)));
                }
            }
        }
        if ring.is_empty() {
            break;
        }
        for &(p, colour) in &ring {
            rgb[p * 3..p * 3 + 3].copy_from_slice(&colour);
            inside[p] = true;
        }
    }
}

/// The CLIP image tower over ONNX (`pixel_values f32[B,3,224,224]` or `pixels u8[B,3,224,224]`
/// ([`VisualInput`]) → one f32[B,D] output, e.g. open_clip's `encode_image` without
/// normalisation).
pub struct ClipVisual {
    model: OnnxModel,
    batch_size: usize,
    input_name: String,
    input: VisualInput,
    model_id: String,
    dim: usize,
    /// Whether every run is padded to `batch_size` rows (GPU providers; see `run_batch`).
    fixed_batch: bool,
    /// Where the crops' white fill is applied.
    crop_fill: CropFill,
}

impl ClipVisual {
    /// Loads and checks the visual tower on `ep` (GPU 0); crops are embedded `batch_size` at a
    /// time.
    ///
    /// # Errors
    /// [`Error::Param`] `clip_batch` for `batch_size == 0`; [`Error::Model`] for a missing/unloadable model or
    /// the wrong signature (e.g. a SAM encoder or a text tower); [`Error::Inference`] when the
    /// provider fails.
    pub fn new(model: &Path, ep: ExecutionProvider, batch_size: usize) -> Result<Self> {
        Self::with_threads(model, ep, batch_size, 0)
    }

    /// [`ClipVisual::new`] with an explicit ONNX Runtime intra-op thread count (0 = default).
    ///
    /// # Errors
    /// As [`ClipVisual::new`].
    pub fn with_threads(
        model: &Path,
        ep: ExecutionProvider,
        batch_size: usize,
        intra_threads: usize,
    ) -> Result<Self> {
        Self::with_placement(model, &Placement::new(ep, 0, intra_threads), batch_size)
    }

    /// [`ClipVisual::new`] where `placement` says (provider, GPU, threads, arena cap).
    ///
    /// # Errors
    /// As [`ClipVisual::new`].
    pub fn with_placement(model: &Path, placement: &Placement, batch_size: usize) -> Result<Self> {
        if batch_size == 0 {
            return Err(Error::param(
                "clip_batch",
                0,
                "a CLIP batch of at least 1 crop",
            ));
        }
        let loaded = OnnxModel::load(model, placement)?;
        let takes_bytes = onnx::check_signature(
            loaded.session(),
            model,
            "CLIP image tower",
            VISUAL_INPUTS_U8,
            VISUAL_OUTPUTS,
            "",
        )
        .is_ok();
        if !takes_bytes {
            onnx::check_signature(
                loaded.session(),
                model,
                "CLIP image tower",
                VISUAL_INPUTS,
                VISUAL_OUTPUTS,
                "pass a CLIP visual model exported with input pixel_values f32[B,3,224,224] (or \
                 pixels u8[B,3,224,224], scripts/clip-u8-pixels.py) and one output image_embeds \
                 f32[B,D] (e.g. open_clip encode_image; scripts/export-models.py clip)",
            )?;
        }
        let input_name = loaded.session().inputs()[0].name().to_string();
        let declared = match loaded.session().outputs()[0].dtype() {
            ort::value::ValueType::Tensor { shape, .. } => shape.last().copied().filter(|&d| d > 0),
            _ => None,
        };
        let model_id = onnx::clip_pair_id(loaded.session(), model);
        let fixed_batch = loaded.provider() != ExecutionProvider::Cpu;
        let mut clip = ClipVisual {
            model: loaded,
            batch_size,
            input_name,
            input: if takes_bytes {
                VisualInput::U8Pixels
            } else {
                VisualInput::F32PixelValues
            },
            model_id,
            dim: 0,
            fixed_batch,
            crop_fill: CropFill::default(),
        };
        clip.dim = match declared {
            Some(d) => d as usize,
            // Dynamic width: one probe run on a mid-grey image.
            None => clip.embed_pixels(&vec![128u8; CLIP_PIXELS])?[0].len(),
        };
        Ok(clip)
    }

    /// Embedding width D (the model's output width).
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Model id recorded in outputs: the CLIP pair id ([`onnx::clip_pair_id`]: ONNX metadata
    /// `slag.clip_pair_id`, else the file stem without `-visual`, e.g. `color-clip`).
    pub fn model_id(&self) -> &str {
        &self.model_id
    }

    /// The provider that runs the tower and where (`cpu`, `cuda:0`).
    pub fn device_label(&self) -> String {
        self.model.device_label()
    }

    /// The provider that runs the tower.
    pub fn provider(&self) -> ExecutionProvider {
        self.model.provider()
    }

    /// What the tower takes (bytes, or values normalised on the host).
    pub fn input(&self) -> VisualInput {
        self.input
    }

    /// Crops per run.
    pub fn batch_size(&self) -> usize {
        self.batch_size
    }

    /// Whether short runs are padded to the batch size (on by default on GPU providers, off on
    /// the CPU). Results do not depend on it beyond the provider's rounding; turning it on on
    /// the CPU is for tests.
    pub fn set_fixed_batch(&mut self, on: bool) {
        self.fixed_batch = on;
    }

    /// Where the crops of [`ClipVisual::embed_masks`] get their white fill (default
    /// [`CropFill::BeforeResize`]); a [`ClipService`] started from this tower keeps it.
    pub fn set_crop_fill(&mut self, fill: CropFill) {
        self.crop_fill = fill;
    }

    /// Where the crops of [`ClipVisual::embed_masks`] get their white fill.
    pub fn crop_fill(&self) -> CropFill {
        self.crop_fill
    }

    /// Embeds crops `u8[n,3,224,224]` made by [`crate::preprocess::clip_pixels`] (or
    /// [`crop_pixels`]): `n` L2-normalised rows of the model's width, in runs of at most the
    /// batch size. An f32 tower's values are normalised here, one batch at a time.
    ///
    /// # Errors
    /// [`Error::Internal`] for a buffer that is not a whole number of images, [`Error::Inference`]
    /// when the run fails, [`Error::Model`] for a wrong output or an embedding of zero norm.
    pub fn embed_pixels(&mut self, pixels: &[u8]) -> Result<Vec<Vec<f32>>> {
        let per = whole_crops(pixels.len())?;
        let mut out = Vec::with_capacity(pixels.len() / per);
        for chunk in pixels.chunks(self.batch_size * per) {
            let rows = match self.input {
                VisualInput::U8Pixels => self.run_batch(Batch::Bytes(chunk))?,
                VisualInput::F32PixelValues => {
                    let values = normalized(chunk)?;
                    self.run_batch(Batch::Values(&values))?
                }
            };
            out.extend(rows);
        }
        Ok(out)
    }

    /// Embeds crops already in the tower's input form ([`Crops::for_tower`]), in runs of at
    /// most the batch size.
    ///
    /// # Errors
    /// As [`ClipVisual::embed_pixels`]; [`Error::Internal`] for crops of the other form.
    fn embed_crops(&mut self, crops: &Crops) -> Result<Vec<Vec<f32>>> {
        let all = crops.batch();
        if all.input() != self.input {
            return Err(Error::internal(format!(
                "crops prepared for another CLIP tower input than {:?}",
                self.input
            )));
        }
        let n = all.count();
        let mut out = Vec::with_capacity(n);
        for start in (0..n).step_by(self.batch_size) {
            out.extend(self.run_batch(all.crops(start..n.min(start + self.batch_size)))?);
        }
        Ok(out)
    }

    /// Runs one batch of at most `batch_size` crops.
    ///
    /// On a GPU provider every run has exactly `batch_size` rows: a short batch is padded with
    /// zero images whose rows are dropped. The tower then sees one input shape for the whole
    /// encode, and its convolution plans are built once, in the first run. Building a cuDNN
    /// plan for a new batch size in the middle of an encode, while SAM's sessions run on other
    /// threads of the same GPU, failed with CUDA error 901 ("operation failed due to a previous
    /// error during capture") under ONNX Runtime 1.31.
    fn run_batch(&mut self, batch: Batch<'_>) -> Result<Vec<Vec<f32>>> {
        let s = CLIP_IMAGE_SIZE as usize;
        let n = batch.count();
        let rows = if self.fixed_batch {
            n.max(self.batch_size)
        } else {
            n
        };
        let errs = self.model.errors();
        let path = self.model.path().to_path_buf();
        let name = self.input_name.as_str();
        let session = self.model.session_mut();
        let run = match batch {
            Batch::Bytes(b) => {
                let b = padded(b, rows);
                let input = TensorRef::from_array_view(([rows, 3, s, s], b.as_ref()))
                    .map_err(|e| errs.error("cannot build the CLIP input", &e))?;
                session.run(ort::inputs![name => input])
            }
            Batch::Values(v) => {
                let v = padded(v, rows);
                let input = TensorRef::from_array_view(([rows, 3, s, s], v.as_ref()))
                    .map_err(|e| errs.error("cannot build the CLIP input", &e))?;
                session.run(ort::inputs![name => input])
            }
        };
        let outputs = run.map_err(|e| errs.error("CLIP visual run", &e))?;
        let (shape, data) = outputs[0]
            .try_extract_tensor::<f32>()
            .map_err(|e| errs.unexpected(format!("CLIP output is not f32: {e}")))?;
        if shape.len() != 2 || shape[0] != rows as i64 || shape[1] <= 0 {
            return Err(errs.unexpected(format!(
                "CLIP visual returned shape {shape:?} for {rows} images, expected [{rows}, D]"
            )));
        }
        let d = shape[1] as usize;
        let mut out: Vec<Vec<f32>> = data.chunks_exact(d).take(n).map(<[f32]>::to_vec).collect();
        for v in &mut out {
            l2_normalize(v, &path)?;
        }
        Ok(out)
    }

    /// CLIP embeddings (L2-normalised, model width `D`) of the white-background crops of `masks`
    /// in `image` (white fill as [`ClipVisual::set_crop_fill`] says), in mask order. Crops are
    /// cut and preprocessed in parallel (rayon), then run in batches of the configured size.
    ///
    /// # Errors
    /// As [`crop`] and [`ClipVisual::embed_pixels`].
    pub fn embed_masks(&mut self, image: &RgbImage, masks: &[Mask]) -> Result<Vec<Vec<f32>>> {
        let pixels = crop_pixels(image, masks, self.crop_fill)?;
        self.embed_pixels(&pixels)
    }

    /// Moves the tower onto its own thread, which runs the crops of every [`ClipHandle`] in shared
    /// batches (see [`ClipService`]).
    ///
    /// On a GPU provider one full batch of mid-grey images runs first, on the calling thread, so
    /// the tower's plans exist before the front workers start (see `run_batch`).
    ///
    /// # Errors
    /// [`Error::Inference`] when that first run fails.
    pub fn into_service(mut self) -> Result<ClipService> {
        if self.fixed_batch {
            self.embed_pixels(&vec![128u8; self.batch_size * CLIP_PIXELS])?;
        }
        Ok(ClipService::start(self))
    }
}

/// `u8[masks.len(), 3, 224, 224]`: the white-background crops of `masks`, resized and
/// centre-cropped for CLIP, white filled as `fill` says ([`mask_crop_pixels`]), cut in parallel
/// (rayon).
///
/// # Errors
/// As [`crop`] and [`clip_pixels`].
pub fn crop_pixels(image: &RgbImage, masks: &[Mask], fill: CropFill) -> Result<Vec<u8>> {
    let per = CLIP_PIXELS;
    let mut pixels = vec![0u8; masks.len() * per];
    pixels
        .par_chunks_mut(per)
        .zip(masks.par_iter())
        .try_for_each(|(buf, m)| mask_crop_pixels(image, m, fill, buf))?;
    Ok(pixels)
}

/// The crop size in values, after checking that `len` values are whole crops.
///
/// # Errors
/// [`Error::Internal`] otherwise.
fn whole_crops(len: usize) -> Result<usize> {
    if len.is_multiple_of(CLIP_PIXELS) {
        Ok(CLIP_PIXELS)
    } else {
        Err(Error::internal(format!(
            "CLIP pixel buffer of {len} values is not a multiple of 3*224*224"
        )))
    }
}

/// `bytes` (whole crops of [`clip_pixels`]) scaled and normalised for an f32 tower, crops in
/// parallel (rayon).
///
/// # Errors
/// As [`clip_normalize`].
fn normalized(bytes: &[u8]) -> Result<Vec<f32>> {
    let per = whole_crops(bytes.len())?;
    let mut values = vec![0f32; bytes.len()];
    values
        .par_chunks_mut(per)
        .zip(bytes.par_chunks(per))
        .try_for_each(|(o, b)| clip_normalize(b, o))?;
    Ok(values)
}

/// `buf` with zero crops appended up to `rows` crops (borrowed when it has them already).
fn padded<T: Copy + Default>(buf: &[T], rows: usize) -> std::borrow::Cow<'_, [T]> {
    let want = rows * CLIP_PIXELS;
    if buf.len() >= want {
        return std::borrow::Cow::Borrowed(buf);
    }
    let mut v = Vec::with_capacity(want);
    v.extend_from_slice(buf);
    v.resize(want, T::default());
    std::borrow::Cow::Owned(v)
}

/// One run's crops, borrowed, in a tower's input form.
#[derive(Clone, Copy)]
enum Batch<'a> {
    Bytes(&'a [u8]),
    Values(&'a [f32]),
}

impl<'a> Batch<'a> {
    fn count(&self) -> usize {
        match self {
            Batch::Bytes(b) => b.len() / CLIP_PIXELS,
            Batch::Values(v) => v.len() / CLIP_PIXELS,
        }
    }

    /// The tower input this form is for.
    fn input(&self) -> VisualInput {
        match self {
            Batch::Bytes(_) => VisualInput::U8Pixels,
            Batch::Values(_) => VisualInput::F32PixelValues,
        }
    }

    /// Crops `range` (crop indices) of these.
    fn crops(self, range: std::ops::Range<usize>) -> Batch<'a> {
        let values = range.start * CLIP_PIXELS..range.end * CLIP_PIXELS;
        match self {
            Batch::Bytes(b) => Batch::Bytes(&b[values]),
            Batch::Values(v) => Batch::Values(&v[values]),
        }
    }
}

/// Crops in the form their tower takes: bytes for a byte tower, CLIP-normalised values for an
/// f32 tower. Front workers make them, so the service thread only concatenates and runs.
enum Crops {
    Bytes(Vec<u8>),
    Values(Vec<f32>),
}

impl Crops {
    /// `pixels` (whole crops of [`clip_pixels`]) for a tower taking `input`; an f32 tower's are
    /// normalised here, on the calling thread's rayon pool.
    ///
    /// # Errors
    /// As [`clip_normalize`].
    fn for_tower(input: VisualInput, pixels: Vec<u8>) -> Result<Crops> {
        Ok(match input {
            VisualInput::U8Pixels => Crops::Bytes(pixels),
            VisualInput::F32PixelValues => Crops::Values(normalized(&pixels)?),
        })
    }

    /// The crops, borrowed.
    fn batch(&self) -> Batch<'_> {
        match self {
            Crops::Bytes(b) => Batch::Bytes(b),
            Crops::Values(v) => Batch::Values(v),
        }
    }

    /// The crops of `reqs` in order, as one buffer (moved, not copied, for one request).
    ///
    /// # Errors
    /// [`Error::Internal`] for requests of different forms.
    fn concat(reqs: &mut [Request]) -> Result<Crops> {
        if let [one] = reqs {
            return Ok(std::mem::replace(&mut one.crops, Crops::Bytes(Vec::new())));
        }
        let mut bytes = Vec::new();
        let mut values = Vec::new();
        for r in reqs.iter() {
            match &r.crops {
                Crops::Bytes(b) => bytes.extend_from_slice(b),
                Crops::Values(v) => values.extend_from_slice(v),
            }
        }
        match (bytes.is_empty(), values.is_empty()) {
            (_, true) => Ok(Crops::Bytes(bytes)),
            (true, false) => Ok(Crops::Values(values)),
            (false, false) => Err(Error::internal(
                "CLIP requests of one tower in both byte and value form",
            )),
        }
    }
}

/// One front worker's crops waiting for the tower.
struct Request {
    crops: Crops,
    /// Crops in this request (`crops` is moved out when it runs alone).
    count: usize,
    reply: mpsc::SyncSender<Result<Vec<Vec<f32>>>>,
}

/// What a [`ClipService`] has done: runs, crops, and seconds inside the tower.
#[derive(Debug, Clone, Copy, Default, serde::Serialize)]
pub struct ClipServiceStats {
    /// Tower runs.
    pub runs: u64,
    /// Crops embedded.
    pub crops: u64,
    /// Seconds inside the tower's runs.
    pub run_s: f64,
}

/// The CLIP image tower of one GPU on its own thread, shared by every front worker of that GPU
/// through [`ClipHandle`]s: each worker cuts and preprocesses its crops on its own thread, sends
/// them, and waits; the service takes every request that is waiting, concatenates their crops,
/// and runs them in batches of the tower's batch size, so crops of several images share a run
/// (one image's ~50 crops alone would leave a large batch half empty). The thread ends when the
/// service and every handle are dropped.
pub struct ClipService {
    tx: mpsc::Sender<Request>,
    model_id: String,
    dim: usize,
    device: String,
    provider: ExecutionProvider,
    stats: Arc<Mutex<ClipServiceStats>>,
    input: VisualInput,
    crop_fill: CropFill,
}

impl ClipService {
    fn start(mut clip: ClipVisual) -> Self {
        let (tx, rx) = mpsc::channel::<Request>();
        let stats = Arc::new(Mutex::new(ClipServiceStats::default()));
        let (model_id, dim, device, provider, input, crop_fill) = (
            clip.model_id.clone(),
            clip.dim,
            clip.device_label(),
            clip.provider(),
            clip.input,
            clip.crop_fill,
        );
        let st = Arc::clone(&stats);
        let spawned = std::thread::Builder::new()
            .name(format!("clip-{device}"))
            .spawn(move || {
                while let Ok(first) = rx.recv() {
                    let mut n = first.count;
                    let mut reqs = vec![first];
                    while n < clip.batch_size {
                        match rx.try_recv() {
                            Ok(r) => {
                                n += r.count;
                                reqs.push(r);
                            }
                            Err(_) => break,
                        }
                    }
                    let t = Instant::now();
                    let result = Crops::concat(&mut reqs).and_then(|c| clip.embed_crops(&c));
                    if let Ok(mut s) = st.lock() {
                        s.runs += n.div_ceil(clip.batch_size) as u64;
                        s.crops += n as u64;
                        s.run_s += t.elapsed().as_secs_f64();
                    }
                    match result {
                        Ok(mut rows) => {
                            // Hand each request its rows, in order.
                            for r in reqs.into_iter().rev() {
                                let mine = rows.split_off(rows.len() - r.count);
                                let _ = r.reply.send(Ok(mine));
                            }
                        }
                        Err(e) => {
                            // Every image of the failed run gets the error (typed as it was).
                            for r in reqs {
                                let _ = r.reply.send(Err(copy_error(&e)));
                            }
                        }
                    }
                }
            });
        if let Err(e) = spawned {
            tracing::error!("cannot start the CLIP service thread: {e}");
        }
        ClipService {
            tx,
            model_id,
            dim,
            device,
            provider,
            stats,
            input,
            crop_fill,
        }
    }

    /// A handle for one front worker.
    pub fn handle(&self) -> ClipHandle {
        ClipHandle {
            tx: self.tx.clone(),
            model_id: self.model_id.clone(),
            dim: self.dim,
            device: self.device.clone(),
            input: self.input,
            crop_fill: self.crop_fill,
        }
    }

    /// Where the tower runs (`cpu`, `cuda:0`).
    pub fn device_label(&self) -> &str {
        &self.device
    }

    /// The provider that runs the tower.
    pub fn provider(&self) -> ExecutionProvider {
        self.provider
    }

    /// Runs, crops and seconds so far.
    pub fn stats(&self) -> ClipServiceStats {
        self.stats.lock().map(|s| *s).unwrap_or_default()
    }
}

/// The same error for another waiting request: the same variant (so the same kind) where it
/// can be copied; an I/O error keeps its kind and text.
fn copy_error(e: &Error) -> Error {
    match e {
        Error::Inference {
            model,
            provider,
            device,
            message,
            remedy,
        } => Error::Inference {
            model: model.clone(),
            provider: provider.clone(),
            device: device.clone(),
            message: message.clone(),
            remedy: remedy.clone(),
        },
        Error::Model { path, message } => Error::model(path, message.clone()),
        Error::Io { path, source } => {
            Error::io(path, std::io::Error::new(source.kind(), source.to_string()))
        }
        Error::Format { path, message } => Error::format(path, message.clone()),
        Error::Param {
            name,
            value,
            expected,
        } => Error::param(name, value, expected.clone()),
        Error::Query { field, message } => Error::query(field, message.clone()),
        Error::Mismatch { what, message } => Error::mismatch(*what, message.clone()),
        Error::Limit {
            resource,
            needed,
            limit,
        } => Error::limit(*resource, needed, limit),
        Error::Shard(s) => Error::Shard(s.clone()),
        Error::Gpu(m) => Error::Gpu(m.clone()),
        Error::Invalid(m) => Error::Invalid(m.clone()),
        other => Error::internal(other.to_string()),
    }
}

/// A front worker's way to a [`ClipService`]; implements the pipeline's crop embedder.
#[derive(Clone)]
pub struct ClipHandle {
    tx: mpsc::Sender<Request>,
    model_id: String,
    dim: usize,
    device: String,
    input: VisualInput,
    crop_fill: CropFill,
}

impl ClipHandle {
    /// Model id (the visual tower's file stem).
    pub fn model_id(&self) -> &str {
        &self.model_id
    }
    /// Embedding width D.
    pub fn dim(&self) -> usize {
        self.dim
    }
    /// Where the tower runs.
    pub fn device_label(&self) -> &str {
        &self.device
    }

    /// As [`ClipVisual::embed_masks`], through the service. The crops are cut and, for an f32
    /// tower, normalised on the calling thread, so the service's thread only runs the tower.
    ///
    /// # Errors
    /// As [`ClipVisual::embed_masks`]; [`Error::Invalid`] if the service thread is gone.
    pub fn embed_masks(&self, image: &RgbImage, masks: &[Mask]) -> Result<Vec<Vec<f32>>> {
        if masks.is_empty() {
            return Ok(Vec::new());
        }
        let crops = Crops::for_tower(self.input, crop_pixels(image, masks, self.crop_fill)?)?;
        let count = crops.batch().count();
        let (reply, answer) = mpsc::sync_channel(1);
        let gone = || {
            Error::Invalid(format!(
                "the CLIP service on {} stopped (an earlier error ended it)",
                self.device
            ))
        };
        self.tx
            .send(Request {
                crops,
                count,
                reply,
            })
            .map_err(|_| gone())?;
        answer.recv().map_err(|_| gone())?
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn crop_is_inclusive_bbox_with_white_outside() {
        let img = RgbImage::from_fn(6, 5, |x, y| image::Rgb([x as u8, y as u8, 7]));
        let mut px = vec![0u8; 30];
        px[6 + 2] = 1; // (2,1)
        px[3 * 6 + 4] = 1; // (4,3)
        let m = Mask::from_pixels(6, 5, px).unwrap();
        assert_eq!(m.bbox_xywh, [2, 1, 2, 2]);
        let c = crop(&img, &m).unwrap();
        assert_eq!(c.dimensions(), (3, 3));
        assert_eq!(c.get_pixel(0, 0).0, [2, 1, 7]);
        assert_eq!(c.get_pixel(2, 2).0, [4, 3, 7]);
        assert_eq!(c.get_pixel(1, 1).0, [255, 255, 255]);
        assert_eq!(c.get_pixel(2, 0).0, [255, 255, 255]);
    }

    #[test]
    fn crop_clips_box_and_rejects_size_mismatch() {
        let img = RgbImage::new(4, 4);
        let mut m = Mask::from_pixels(4, 4, vec![1; 16]).unwrap();
        m.bbox_xywh = [2, 2, 10, 10];
        assert_eq!(crop(&img, &m).unwrap().dimensions(), (2, 2));
        let small = RgbImage::new(3, 4);
        assert!(matches!(
            crop(&small, &m),
            Err(Error::Mismatch {
                what: slag_common::Mismatched::ImageSize,
                ..
            })
        ));
    }

    /// The `[r, g, b]` pixels of one CLIP input `u8[3, 224, 224]`.
    fn rgb_pixels(buf: &[u8]) -> Vec<[u8; 3]> {
        let plane = CLIP_PIXELS / 3;
        (0..plane)
            .map(|i| [buf[i], buf[plane + i], buf[2 * plane + i]])
            .collect()
    }

    #[test]
    fn fill_after_resize_keeps_the_border_colour() {
        // A light object (pink) on a gray floor; the mask is a triangle, so its box holds
        // pixels outside it, and the 30 x 20 box is enlarged to CLIP's 224.
        const PINK: [u8; 3] = [250, 160, 200];
        let (w, h) = (48u32, 32u32);
        let inside =
            |x: u32, y: u32| (4..34).contains(&x) && (6..26).contains(&y) && x - 4 >= y - 6;
        let img = RgbImage::from_fn(w, h, |x, y| {
            image::Rgb(if inside(x, y) { PINK } else { [128, 128, 128] })
        });
        let px = (0..w * h).map(|i| u8::from(inside(i % w, i / w))).collect();
        let m = Mask::from_pixels(w, h, px).unwrap();
        let mut after = vec![0u8; CLIP_PIXELS];
        mask_crop_pixels(&img, &m, CropFill::AfterResize, &mut after).unwrap();
        let mut before = vec![0u8; CLIP_PIXELS];
        mask_crop_pixels(&img, &m, CropFill::BeforeResize, &mut before).unwrap();
        let after = rgb_pixels(&after);
        let white = [255u8; 3];
        // Filled after the resize, every pixel is the object's own colour or the fill: the
        // border is not blended with white (nor with the floor outside the mask).
        let pink = after.iter().filter(|&&p| p == PINK).count();
        assert!(after.iter().all(|&p| p == PINK || p == white));
        assert!(
            pink > after.len() / 4 && pink < after.len() * 3 / 4,
            "{pink} pink pixels"
        );
        // Filled before it, the border pixels are pink blended with white.
        let blended = rgb_pixels(&before)
            .into_iter()
            .filter(|&p| p != PINK && p != white)
            .count();
        assert!(blended > 100, "only {blended} blended pixels");
    }

    #[test]
    fn fills_agree_where_the_mask_covers_its_box() {
        let img = RgbImage::from_fn(40, 30, |x, y| {
            image::Rgb([(x * 6) as u8, (y * 8) as u8, ((x * y) % 251) as u8])
        });
        let px = (0..40 * 30)
            .map(|i| u8::from((3..34).contains(&(i % 40)) && (5..22).contains(&(i / 40))))
            .collect();
        let m = Mask::from_pixels(40, 30, px).unwrap();
        let mut crops = [vec![0u8; CLIP_PIXELS], vec![0u8; CLIP_PIXELS]];
        for (fill, out) in [CropFill::BeforeResize, CropFill::AfterResize]
            .into_iter()
            .zip(&mut crops)
        {
            mask_crop_pixels(&img, &m, fill, out).unwrap();
        }
        assert!(
            crops[0] == crops[1],
            "the two fills differ on a full-box mask"
        );
        assert!(crops[0].iter().any(|&v| v != 255));
        let small = RgbImage::new(39, 30);
        assert!(matches!(
            mask_crop_pixels(&small, &m, CropFill::AfterResize, &mut crops[0]),
            Err(Error::Mismatch { .. })
        ));
    }
}
