//! Felzenszwalb-Huttenlocher graph segmentation: the weight-free, CPU-only, cheap end of slag's
//! mask speed/accuracy trade (SAM is the accurate end).
//!
//! Source convention: P. F. Felzenszwalb and D. P. Huttenlocher, "Efficient Graph-Based Image
//! Segmentation", IJCV 59(2), 2004 (Algorithm 1, §4), as in the authors' reference code
//! (`segment-image.h`), which is also what the ScanNet segmentator runs on meshes:
//!
//! 1. the RGB image (0..255 per channel, as f32) is smoothed with a separable Gaussian of standard
//!    deviation [`GraphParams::sigma`] pixels (kernel radius `ceil(4σ)`, border pixels replicated);
//! 2. the grid graph is **8-connected**: every pixel has edges to its right, lower, lower-right
//!    and upper-right neighbours (4 edges per pixel, each undirected pair once), with weight = the
//!    Euclidean distance of the two smoothed RGB colours (0..~441.7). (The reference code segments
//!    each channel separately and intersects; slag uses the common Euclidean-RGB variant, as
//!    scikit-image does.)
//! 3. weights are quantised to 1/128 of an RGB level and the edges sorted by weight with a stable
//!    LSD radix sort (ties keep their generation order, so the result is deterministic);
//! 4. a disjoint-set forest (union by rank, full path compression) merges the two components
//!    `C1, C2` of an edge of weight `w` when `w <= Int(C) + τ(C)` for both, `τ(C) = k / |C|`
//!    ([`GraphParams::k`]; `Int(C)` is the largest edge weight of `C`'s minimum spanning tree);
//! 5. a post-pass over the same sorted edges merges every pair of components one of which has
//!    fewer than [`GraphParams::min_size`] pixels, so every segment has at least
//!    `min(min_size, W·H)` pixels (at full resolution).
//!
//! Optional downscale ([`GraphParams::max_side`]): an image whose longer side exceeds it is
//! resized (triangle filter) so that its longer side equals `max_side`, segmented there with `k`
//! and `min_size` multiplied by the area ratio (so that `τ` and the minimum size describe the same
//! fraction of the image), and the labels are upsampled to full resolution by nearest neighbour
//! (pixel centres). The `min_size` guarantee then holds at the reduced resolution only.
//!
//! Defaults (chosen on the snowmiku 990×742 indoor photos, see [`GraphParams::default`]):
//! `sigma = 0.8`, `k = 500`, `min_size = 500` px (≈ 0.07 % of 990×742), no downscale: 45–70
//! segments per photo (`k = 300` gives 75–100; `max_side = 640` gives 85–110 in ~60 % of the
//! time).

use image::RgbImage;
use slag_common::{Error, Result};

use super::{Mask, MaskGenerator, MaskMeta};
use crate::check::require;
use crate::disjoint_sets::DisjointSets;

/// Parameters of [`segment_labels`] / [`GraphSegmenter`].
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct GraphParams {
    /// Standard deviation of the Gaussian pre-smoothing, pixels (of the segmented resolution).
    /// Values below 0.01 disable smoothing. Default 0.8 (scikit-image's default; the reference code's README
    /// suggests 0.5).
    pub sigma: f32,
    /// Scale `k` of the threshold `τ(C) = k / |C|`, in RGB-distance units (0..255 scale) times
    /// pixels. Larger `k` → larger, fewer segments. Default 500 (the reference code's typical
    /// value): with `min_size = 500` it yields 45–70 segments on a 990×742 snowmiku photo.
    pub k: f32,
    /// Minimum segment size, full-resolution pixels; smaller components are merged into a
    /// neighbour by the post-pass. Default 500 (≈ 0.07 % of a 990×742 image).
    pub min_size: u32,
    /// If set, segment at a reduced resolution whose longer side is `max_side` pixels (only when
    /// the image is larger) and upsample the labels by nearest neighbour. Default `None`.
    pub max_side: Option<u32>,
}

impl Default for GraphParams {
    fn default() -> Self {
        GraphParams {
            sigma: 0.8,
            k: 500.0,
            min_size: 500,
            max_side: None,
        }
    }
}

impl GraphParams {
    fn validate(&self) -> Result<()> {
        let (sigma, k) = (self.sigma, self.k);
        require(
            sigma.is_finite() && sigma >= 0.0,
            "graph_sigma",
            sigma,
            "a finite smoothing sigma >= 0 (default 0.8)",
        )?;
        require(
            k.is_finite() && k > 0.0,
            "graph_k",
            k,
            "a finite threshold scale k > 0 (default 500)",
        )?;
        require(
            self.max_side != Some(0),
            "graph_max_side",
            0,
            "a positive longer side in pixels, or none",
        )
    }
}

/// Segments `image` into connected regions (Felzenszwalb-Huttenlocher 2004, see the module docs).
///
/// Returns `(labels, count)`: `labels` has `W·H` entries, row-major, each in `0..count`; label 0 is
/// the largest segment and labels are ordered by area descending (ties: the segment whose first
/// pixel in raster order comes first). Deterministic.
///
/// Errors: a zero-sized image ([`Error::Invalid`]), 2^30 pixels or more to segment (after the
/// optional downscale) or invalid parameters ([`Error::Param`] `graph_sigma`, `graph_k`,
/// `graph_max_side`: non-finite or negative `sigma`, `k <= 0`, `max_side = 0`).
pub fn segment_labels(image: &RgbImage, params: &GraphParams) -> Result<(Vec<u32>, u32)> {
    params.validate()?;
    let (w, h) = image.dimensions();
    if w == 0 || h == 0 {
        return Err(Error::Invalid(format!(
            "graph segmenter got a {w}x{h} image; pass a non-empty RGB image"
        )));
    }
    let n = w as u64 * h as u64;
    let too_large = |sw: u32, sh: u32| -> Result<()> {
        if sw as u64 * sh as u64 >= 1 << 30 {
            return Err(Error::param(
                "graph_max_side",
                format!("{:?}", params.max_side),
                format!(
                    "a longer side that downscales the image below 2^30 pixels (it would segment \
                     {sw}x{sh})"
                ),
            ));
        }
        Ok(())
    };
    let labels = match params.max_side {
        Some(side) if w.max(h) > side => {
            let scale = side as f64 / w.max(h) as f64;
            let sw = ((w as f64 * scale).round() as u32).clamp(1, side);
            let sh = ((h as f64 * scale).round() as u32).clamp(1, side);
            too_large(sw, sh)?;
            let small =
                image::imageops::resize(image, sw, sh, image::imageops::FilterType::Triangle);
            let ratio = (sw as f64 * sh as f64) / n as f64;
            let small_params = GraphParams {
                sigma: params.sigma,
                k: (params.k as f64 * ratio) as f32,
                min_size: (params.min_size as f64 * ratio).ceil() as u32,
                max_side: None,
            };
            let small_labels = segment_raw(&small, &small_params);
            upsample_nearest(&small_labels, sw, sh, w, h)
        }
        _ => {
            too_large(w, h)?;
            segment_raw(image, params)
        }
    };
    Ok(order_by_area(labels))
}

/// Mask generator over [`segment_labels`]: one [`Mask`] per segment, full resolution, ordered by
/// area descending. The masks partition the image (every pixel is in exactly one mask);
/// `predicted_iou = stability_score = 1.0`, `point = None`.
#[derive(Debug, Clone, Default)]
pub struct GraphSegmenter {
    params: GraphParams,
}

impl GraphSegmenter {
    /// A segmenter with these parameters (validated on the first [`MaskGenerator::generate`]).
    pub fn new(params: GraphParams) -> Self {
        GraphSegmenter { params }
    }

    /// The parameters in use.
    pub fn params(&self) -> &GraphParams {
        &self.params
    }
}

impl MaskGenerator for GraphSegmenter {
    fn name(&self) -> &str {
        "graph"
    }

    /// Errors: as [`segment_labels`].
    fn generate(&mut self, image: &RgbImage) -> Result<Vec<Mask>> {
        let (labels, count) = segment_labels(image, &self.params)?;
        Ok(masks_from_labels(
            &labels,
            count,
            image.width(),
            image.height(),
        ))
    }
}

/// One [`Mask`] per label of a `width`×`height` label image with labels in `0..count`, in label
/// order, built in a single pass (bounding boxes and areas included). `labels` is row-major with
/// `width·height` entries (missing trailing rows count as unlabelled). Labels without pixels give
/// no mask; labels `>= count` are ignored.
pub fn masks_from_labels(labels: &[u32], count: u32, width: u32, height: u32) -> Vec<Mask> {
    let n = width as usize * height as usize;
    let c = count as usize;
    // `vec![0; n]` is a zeroed allocation (calloc), so untouched pages cost nothing up front.
    let mut pixels: Vec<Vec<u8>> = (0..c).map(|_| vec![0u8; n]).collect();
    let mut bbox = vec![[u32::MAX, u32::MAX, 0u32, 0u32]; c];
    let mut area = vec![0u32; c];
    if width > 0 {
        for (y, row) in labels
            .chunks_exact(width as usize)
            .take(height as usize)
            .enumerate()
        {
            let y = y as u32;
            let base = y as usize * width as usize;
            for (x, &l) in row.iter().enumerate() {
                let l = l as usize;
                if l >= c {
                    continue;
                }
                pixels[l][base + x] = 1;
                let x = x as u32;
                let b = &mut bbox[l];
                b[0] = b[0].min(x);
                b[1] = b[1].min(y);
                b[2] = b[2].max(x);
                b[3] = b[3].max(y);
                area[l] += 1;
            }
        }
    }
    pixels
        .into_iter()
        .zip(bbox)
        .zip(area)
        .filter(|&(_, a)| a > 0)
        .map(|((pixels, b), area)| Mask {
            pixels,
            meta: MaskMeta::unscored(width, height, [b[0], b[1], b[2] - b[0], b[3] - b[1]], area),
        })
        .collect()
}

/// Core segmentation on a validated, non-empty image: returns per-pixel component roots
/// (arbitrary ids `< W·H`).
fn segment_raw(image: &RgbImage, params: &GraphParams) -> Vec<u32> {
    let (w, h) = (image.width() as usize, image.height() as usize);
    let n = w * h;
    let smooth = smooth_rgb(image, params.sigma);
    let mut edges = build_edges(&smooth, w, h);
    radix_sort_by_weight(&mut edges);

    let mut forest = Forest::singletons(n);
    let mut thresh = vec![params.k; n];
    for &e in &edges {
        let weight = (e >> 32) as f32 * (1.0 / WEIGHT_SCALE);
        let (p, q) = endpoints(e as u32, w);
        let a = forest.find(p);
        let b = forest.find(q);
        if a != b && weight <= thresh[a as usize] && weight <= thresh[b as usize] {
            let r = forest.join(a, b);
            thresh[r as usize] = weight + params.k / forest.size(r) as f32;
        }
    }
    // Post-pass: only edges with an endpoint in a component below `min_size` can merge
    // (components only grow), so filter them first with one root lookup per pixel.
    let min_size = params.min_size;
    if min_size > 1 {
        let small: Vec<bool> = (0..n as u32)
            .map(|p| {
                let r = forest.find(p);
                forest.size(r) < min_size
            })
            .collect();
        for &e in &edges {
            let (p, q) = endpoints(e as u32, w);
            if !small[p as usize] && !small[q as usize] {
                continue;
            }
            let a = forest.find(p);
            let b = forest.find(q);
            if a != b && (forest.size(a) < min_size || forest.size(b) < min_size) {
                forest.join(a, b);
            }
        }
    }
    (0..n as u32).map(|p| forest.find(p)).collect()
}

/// Relabels arbitrary ids `< labels.len()` into `0..count`, ordered by area descending, ties by
/// first occurrence in raster order.
fn order_by_area(mut labels: Vec<u32>) -> (Vec<u32>, u32) {
    let n = labels.len();
    // Compact ids in order of first occurrence.
    let mut compact = vec![u32::MAX; n];
    let mut sizes: Vec<u32> = Vec::new();
    for l in labels.iter_mut() {
        let slot = &mut compact[*l as usize];
        if *slot == u32::MAX {
            *slot = sizes.len() as u32;
            sizes.push(0);
        }
        *l = *slot;
        sizes[*l as usize] += 1;
    }
    let mut order: Vec<u32> = (0..sizes.len() as u32).collect();
    // Stable sort: equal areas keep first-occurrence order.
    order.sort_by(|&a, &b| sizes[b as usize].cmp(&sizes[a as usize]));
    let mut rank = vec![0u32; sizes.len()];
    for (r, &c) in order.iter().enumerate() {
        rank[c as usize] = r as u32;
    }
    for l in labels.iter_mut() {
        *l = rank[*l as usize];
    }
    (labels, sizes.len() as u32)
}

/// Nearest-neighbour upsampling of a `sw`×`sh` label image to `w`×`h` (pixel centres).
fn upsample_nearest(small: &[u32], sw: u32, sh: u32, w: u32, h: u32) -> Vec<u32> {
    let map = |dst: u32, s: u32, d: u32| -> usize {
        (((dst as f64 + 0.5) * s as f64 / d as f64) as u32).min(s - 1) as usize
    };
    let xs: Vec<usize> = (0..w).map(|x| map(x, sw, w)).collect();
    let mut out = Vec::with_capacity(w as usize * h as usize);
    for y in 0..h {
        let row = &small[map(y, sh, h) * sw as usize..][..sw as usize];
        out.extend(xs.iter().map(|&sx| row[sx]));
    }
    out
}

/// Separable Gaussian smoothing of an RGB image, reference-code kernel
/// (`len = ceil(4σ) + 1` taps per side, normalised, replicated border). Interleaved RGB f32.
fn smooth_rgb(image: &RgbImage, sigma: f32) -> Vec<f32> {
    let (w, h) = (image.width() as usize, image.height() as usize);
    let src: Vec<f32> = image.as_raw().iter().map(|&v| v as f32).collect();
    if sigma < 0.01 {
        return src;
    }
    let len = (sigma * 4.0).ceil() as usize + 1;
    let mut mask: Vec<f32> = (0..len)
        .map(|i| (-0.5 * (i as f32 / sigma).powi(2)).exp())
        .collect();
    let sum = 2.0 * mask.iter().sum::<f32>() - mask[0];
    mask.iter_mut().for_each(|m| *m /= sum);

    // Horizontal pass over a row padded with `len - 1` replicated pixels on each side.
    let pad = len - 1;
    let mut tmp = vec![0f32; src.len()];
    let mut padded = vec![0f32; (w + 2 * pad) * 3];
    for y in 0..h {
        let row = &src[y * w * 3..(y + 1) * w * 3];
        for x in 0..w + 2 * pad {
            let sx = x.saturating_sub(pad).min(w - 1);
            padded[x * 3..x * 3 + 3].copy_from_slice(&row[sx * 3..sx * 3 + 3]);
        }
        let out = &mut tmp[y * w * 3..(y + 1) * w * 3];
        for (x, o) in out.chunks_exact_mut(3).enumerate() {
            let c = (x + pad) * 3;
            let mut acc = [
                mask[0] * padded[c],
                mask[0] * padded[c + 1],
                mask[0] * padded[c + 2],
            ];
            for (i, &m) in mask.iter().enumerate().skip(1) {
                let (l, r) = (c - i * 3, c + i * 3);
                for (ch, a) in acc.iter_mut().enumerate() {
                    *a += m * (padded[l + ch] + padded[r + ch]);
                }
            }
            o.copy_from_slice(&acc);
        }
    }
    // Vertical pass, row-wise so that memory is read contiguously.
    let stride = w * 3;
    let mut dst = vec![0f32; src.len()];
    for y in 0..h {
        let out = &mut dst[y * stride..(y + 1) * stride];
        let centre = &tmp[y * stride..(y + 1) * stride];
        out.iter_mut()
            .zip(centre)
            .for_each(|(o, &c)| *o = mask[0] * c);
        for (i, &m) in mask.iter().enumerate().skip(1) {
            let up = &tmp[y.saturating_sub(i) * stride..][..stride];
            let down = &tmp[(y + i).min(h - 1) * stride..][..stride];
            for ((o, &u), &d) in out.iter_mut().zip(up).zip(down) {
                *o += m * (u + d);
            }
        }
    }
    dst
}

/// Edge directions from pixel `(x, y)`: right, down, down-right, up-right (8-connectivity).
const DIRS: [(isize, isize); 4] = [(1, 0), (0, 1), (1, 1), (1, -1)];

/// Edge id `p * 4 + dir` → its two pixel indices.
#[inline]
fn endpoints(id: u32, w: usize) -> (u32, u32) {
    let p = (id >> 2) as usize;
    let (dx, dy) = DIRS[(id & 3) as usize];
    let q = (p as isize + dy * w as isize + dx) as usize;
    (p as u32, q as u32)
}

/// Weights are stored quantised to `1 / WEIGHT_SCALE` RGB levels (the largest distance,
/// `255·√3 ≈ 441.7`, maps to 56,537 < 2^16).
const WEIGHT_SCALE: f32 = 128.0;

/// All grid edges packed as `(quantised weight << 32) | (p * 4 + dir)`, the quantised weight
/// being `round(distance · WEIGHT_SCALE)` (16 bits).
fn build_edges(smooth: &[f32], w: usize, h: usize) -> Vec<u64> {
    let mut edges = Vec::with_capacity(w * h * 4);
    let key = |a: &[f32], b: &[f32]| -> u64 {
        let d = [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
        let dist = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        // Non-negative, so `+ 0.5` then truncation rounds half up.
        ((dist * WEIGHT_SCALE + 0.5) as u64).min(0xffff) << 32
    };
    let stride = w * 3;
    for y in 0..h {
        let row = &smooth[y * stride..(y + 1) * stride];
        let below = (y + 1 < h).then(|| &smooth[(y + 1) * stride..(y + 2) * stride]);
        let above = (y > 0).then(|| &smooth[(y - 1) * stride..y * stride]);
        for x in 0..w {
            let id = ((y * w + x) * 4) as u64;
            let c = &row[x * 3..x * 3 + 3];
            let right = (x + 1 < w).then(|| x * 3 + 3..x * 3 + 6);
            if let Some(r) = right.clone() {
                edges.push(key(c, &row[r]) | id);
            }
            if let Some(b) = below {
                edges.push(key(c, &b[x * 3..x * 3 + 3]) | (id + 1));
                if let Some(r) = right.clone() {
                    edges.push(key(c, &b[r]) | (id + 2));
                }
            }
            if let (Some(a), Some(r)) = (above, right) {
                edges.push(key(c, &a[r]) | (id + 3));
            }
        }
    }
    edges
}

/// Stable LSD radix sort of `v` by bits 32..48 (the quantised weight; two 8-bit digits, a digit
/// whose values are all equal is skipped).
fn radix_sort_by_weight(v: &mut Vec<u64>) {
    let mut buf = vec![0u64; v.len()];
    for shift in [32u32, 40] {
        let mut count = [0usize; 256];
        for &e in v.iter() {
            count[((e >> shift) & 0xff) as usize] += 1;
        }
        if count.contains(&v.len()) {
            continue;
        }
        let mut sum = 0;
        for c in count.iter_mut() {
            let here = *c;
            *c = sum;
            sum += here;
        }
        for &e in v.iter() {
            let d = ((e >> shift) & 0xff) as usize;
            buf[count[d]] = e;
            count[d] += 1;
        }
        std::mem::swap(v, &mut buf);
    }
}

/// A component of the pixel graph: its union-by-rank rank and its pixel count.
#[derive(Clone, Copy)]
struct Component {
    rank: u8,
    size: u32,
}

/// Disjoint-set forest with union by rank and path compression, tracking component sizes.
type Forest = DisjointSets<Component>;

impl Forest {
    /// Every pixel of `n` its own component.
    fn singletons(n: usize) -> Self {
        DisjointSets::new(n, Component { rank: 0, size: 1 })
    }

    /// Pixels in the component of root `root`.
    fn size(&self, root: u32) -> u32 {
        self.component(root).size
    }

    /// Joins two distinct roots; returns the new root.
    fn join(&mut self, a: u32, b: u32) -> u32 {
        let (ca, cb) = (self.component(a), self.component(b));
        let (a, b, ra, rb) = if ca.rank < cb.rank {
            (b, a, cb.rank, ca.rank)
        } else {
            (a, b, ca.rank, cb.rank)
        };
        let merged = Component {
            rank: if ra == rb { ra + 1 } else { ra },
            size: ca.size + cb.size,
        };
        self.attach(b, a, merged);
        a
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)] // tests fail loudly on purpose
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Deterministic xorshift noise in `-amp..=amp`.
    struct Noise(u64);
    impl Noise {
        fn next(&mut self, amp: i32) -> i32 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            (self.0 % (2 * amp as u64 + 1)) as i32 - amp
        }
    }

    /// A `w`×`h` image of solid rectangles (`(x0, y0, x1, y1, rgb)`, later ones painted over
    /// earlier ones, end-exclusive) on a background, with uniform noise of ±`amp`; returns the
    /// image and the ground-truth region index per pixel (0 = background).
    fn rectangles(
        w: u32,
        h: u32,
        background: [u8; 3],
        rects: &[(u32, u32, u32, u32, [u8; 3])],
        amp: i32,
    ) -> (RgbImage, Vec<u32>) {
        let mut gt = vec![0u32; (w * h) as usize];
        let mut img = RgbImage::from_pixel(w, h, image::Rgb(background));
        for (i, &(x0, y0, x1, y1, c)) in rects.iter().enumerate() {
            for y in y0..y1 {
                for x in x0..x1 {
                    img.put_pixel(x, y, image::Rgb(c));
                    gt[(y * w + x) as usize] = i as u32 + 1;
                }
            }
        }
        let mut noise = Noise(0x9E37_79B9_7F4A_7C15);
        if amp > 0 {
            for p in img.pixels_mut() {
                for v in p.0.iter_mut() {
                    *v = (*v as i32 + noise.next(amp)).clamp(0, 255) as u8;
                }
            }
        }
        (img, gt)
    }

    /// For every ground-truth region, the best IoU of any predicted segment.
    fn best_ious(gt: &[u32], labels: &[u32], count: u32) -> Vec<f64> {
        let regions = *gt.iter().max().unwrap() as usize + 1;
        let c = count as usize;
        let mut inter = vec![0u64; regions * c];
        let mut gt_area = vec![0u64; regions];
        let mut seg_area = vec![0u64; c];
        for (&g, &l) in gt.iter().zip(labels) {
            inter[g as usize * c + l as usize] += 1;
            gt_area[g as usize] += 1;
            seg_area[l as usize] += 1;
        }
        (0..regions)
            .map(|g| {
                (0..c)
                    .map(|l| {
                        let i = inter[g * c + l] as f64;
                        i / (gt_area[g] as f64 + seg_area[l] as f64 - i)
                    })
                    .fold(0.0, f64::max)
            })
            .collect()
    }

    /// The default `sigma` with `k = 1500` and a `min_size` below the smallest rectangle (900 px)
    /// for the 160x120 synthetic scenes. (With `k = 500`, the one-pixel rings of blurred ramp
    /// pixels along each outline stay separate in the main pass and can join the wrong side
    /// through a corner in the post-pass: IoU ~0.9; noise-free edges this sharp are rare in
    /// photos.)
    const RECT_PARAMS: GraphParams = GraphParams {
        sigma: 0.8,
        k: 1500.0,
        min_size: 400,
        max_side: None,
    };

    fn scene() -> Vec<(u32, u32, u32, u32, [u8; 3])> {
        vec![
            (5, 5, 55, 40, [200, 40, 40]),
            (70, 10, 140, 70, [40, 180, 60]),
            (10, 50, 60, 110, [30, 60, 200]),
            (80, 80, 150, 112, [230, 220, 60]),
            (100, 25, 130, 55, [20, 20, 20]),
        ]
    }

    /// Segments [`scene`]'s rectangles (noise ±`noise`) with `params` and asserts that it finds
    /// the background and the 5 rectangles, each with a best IoU of at least `min_iou`.
    fn assert_rectangles_recovered(noise: i32, params: &GraphParams, min_iou: f64) {
        let (img, gt) = rectangles(160, 120, [128, 128, 128], &scene(), noise);
        let (labels, count) = segment_labels(&img, params).unwrap();
        assert_eq!(count, 6, "background + 5 rectangles with {params:?}");
        let ious = best_ious(&gt, &labels, count);
        assert!(
            ious.iter().all(|&i| i >= min_iou),
            "IoUs {ious:?} with {params:?}"
        );
    }

    #[test]
    fn clean_rectangles_are_recovered_exactly() {
        assert_rectangles_recovered(0, &RECT_PARAMS, 1.0);
    }

    #[test]
    fn unsmoothed_rectangles_are_recovered_exactly_for_any_k() {
        for k in [50.0, 500.0, 5000.0] {
            let params = GraphParams {
                sigma: 0.0,
                k,
                min_size: 1,
                max_side: None,
            };
            assert_rectangles_recovered(0, &params, 1.0);
        }
    }

    #[test]
    fn noisy_rectangles_are_recovered() {
        assert_rectangles_recovered(12, &RECT_PARAMS, 0.99);
    }

    #[test]
    fn downscaled_segmentation_recovers_rectangles() {
        // 320x240 segmented at 160x120; rectangle edges fall on even pixels, so the nearest
        // upsampling is exact up to the resize filter's blur at edges.
        let rects: Vec<_> = scene()
            .into_iter()
            .map(|(a, b, c, d, col)| (a * 2, b * 2, c * 2, d * 2, col))
            .collect();
        let (img, gt) = rectangles(320, 240, [128, 128, 128], &rects, 0);
        // k and min_size are scaled by the area ratio (1/4): segmented with RECT_PARAMS.
        let params = GraphParams {
            k: 6000.0,
            min_size: 1600,
            max_side: Some(160),
            sigma: 0.8,
        };
        let (labels, count) = segment_labels(&img, &params).unwrap();
        assert_eq!(labels.len(), 320 * 240);
        assert_eq!(count, 6);
        let ious = best_ious(&gt, &labels, count);
        assert!(ious.iter().all(|&i| i >= 0.97), "IoUs {ious:?}");
    }

    #[test]
    fn masks_partition_the_image_in_area_order() {
        let (img, _) = rectangles(160, 120, [128, 128, 128], &scene(), 12);
        let mut seg = GraphSegmenter::new(RECT_PARAMS);
        assert_eq!(seg.name(), "graph");
        let masks = seg.generate(&img).unwrap();
        let mut cover = vec![0u32; 160 * 120];
        for m in &masks {
            assert_eq!((m.width, m.height), (160, 120));
            // Independent recomputation of area and bbox.
            let reference = Mask::from_pixels(160, 120, m.pixels.clone()).unwrap();
            assert_eq!(reference.area, m.area);
            assert_eq!(reference.bbox_xywh, m.bbox_xywh);
            for (c, &v) in cover.iter_mut().zip(&m.pixels) {
                *c += v as u32;
            }
        }
        assert!(
            cover.iter().all(|&c| c == 1),
            "every pixel in exactly one mask"
        );
        assert!(
            masks.windows(2).all(|p| p[0].area >= p[1].area),
            "area descending"
        );
    }

    #[test]
    fn min_size_is_respected() {
        // Many tiny 3x3 specks that differ strongly from the background.
        let rects: Vec<_> = (0..20)
            .map(|i| {
                (
                    5 + (i % 5) * 20,
                    5 + (i / 5) * 20,
                    8 + (i % 5) * 20,
                    8 + (i / 5) * 20,
                    [250, 0, 0],
                )
            })
            .collect();
        let (img, _) = rectangles(100, 80, [0, 0, 250], &rects, 3);
        let loose = GraphParams {
            sigma: 0.0,
            min_size: 1,
            ..GraphParams::default()
        };
        let (_, many) = segment_labels(&img, &loose).unwrap();
        assert!(
            many >= 21,
            "specks are separate segments without min_size, got {many}"
        );
        for min_size in [10u32, 50, 500] {
            let params = GraphParams {
                sigma: 0.0,
                min_size,
                ..GraphParams::default()
            };
            let (labels, count) = segment_labels(&img, &params).unwrap();
            let mut sizes = vec![0u32; count as usize];
            labels.iter().for_each(|&l| sizes[l as usize] += 1);
            assert!(
                sizes.iter().all(|&s| s >= min_size),
                "min_size {min_size}: {sizes:?}"
            );
        }
        // Larger than the image: one segment.
        let params = GraphParams {
            min_size: 100 * 80 + 1,
            ..GraphParams::default()
        };
        assert_eq!(segment_labels(&img, &params).unwrap().1, 1);
    }

    #[test]
    fn deterministic() {
        let (img, _) = rectangles(160, 120, [100, 120, 140], &scene()[..3], 40);
        let params = GraphParams {
            min_size: 5,
            ..GraphParams::default()
        };
        let a = segment_labels(&img, &params).unwrap();
        let b = segment_labels(&img, &params).unwrap();
        assert_eq!(a, b);
        assert!(a.1 > 1);
    }

    #[test]
    fn trivial_images_give_one_segment() {
        let one = RgbImage::from_pixel(1, 1, image::Rgb([10, 20, 30]));
        assert_eq!(
            segment_labels(&one, &GraphParams::default()).unwrap(),
            (vec![0], 1)
        );
        let flat = RgbImage::from_pixel(64, 48, image::Rgb([90, 90, 90]));
        let params = GraphParams {
            min_size: 1,
            ..GraphParams::default()
        };
        let (labels, count) = segment_labels(&flat, &params).unwrap();
        assert_eq!(count, 1);
        assert!(labels.iter().all(|&l| l == 0));
        let masks = GraphSegmenter::new(params).generate(&flat).unwrap();
        assert_eq!(masks.len(), 1);
        assert_eq!(masks[0].area, 64 * 48);
        assert_eq!(masks[0].bbox_xywh, [0, 0, 63, 47]);
    }

    #[test]
    fn bad_input_is_a_typed_error() {
        let empty = RgbImage::new(0, 5);
        assert!(matches!(
            segment_labels(&empty, &GraphParams::default()),
            Err(Error::Invalid(_))
        ));
        assert!(matches!(
            GraphSegmenter::new(GraphParams::default()).generate(&RgbImage::new(4, 0)),
            Err(Error::Invalid(_))
        ));
        let img = RgbImage::new(4, 4);
        for bad in [
            GraphParams {
                k: 0.0,
                ..GraphParams::default()
            },
            GraphParams {
                k: f32::NAN,
                ..GraphParams::default()
            },
            GraphParams {
                sigma: -1.0,
                ..GraphParams::default()
            },
            GraphParams {
                max_side: Some(0),
                ..GraphParams::default()
            },
        ] {
            assert!(
                matches!(segment_labels(&img, &bad), Err(Error::Param { .. })),
                "{bad:?}"
            );
        }
    }

    #[test]
    fn radix_sort_matches_std_sort() {
        let mut noise = Noise(7);
        let mut v: Vec<u64> = (0..5000u64)
            .map(|i| (((noise.next(30000) + 30000) as u64) << 32) | i)
            .collect();
        let mut reference = v.clone();
        reference.sort_by_key(|e| e >> 32); // stable
        radix_sort_by_weight(&mut v);
        assert_eq!(v, reference);
    }

    /// Brute-force check that segments are 8-connected regions: flood fill each label.
    fn connected_components_agree(labels: &[u32], w: usize, h: usize) -> bool {
        let mut seen = vec![false; labels.len()];
        let mut regions = 0usize;
        for start in 0..labels.len() {
            if seen[start] {
                continue;
            }
            regions += 1;
            let mut stack = vec![start];
            seen[start] = true;
            while let Some(p) = stack.pop() {
                let (x, y) = ((p % w) as isize, (p / w) as isize);
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        let (nx, ny) = (x + dx, y + dy);
                        if nx < 0 || ny < 0 || nx >= w as isize || ny >= h as isize {
                            continue;
                        }
                        let q = ny as usize * w + nx as usize;
                        if !seen[q] && labels[q] == labels[p] {
                            seen[q] = true;
                            stack.push(q);
                        }
                    }
                }
            }
        }
        let count = labels.iter().copied().max().map_or(0, |m| m as usize + 1);
        regions == count
    }

    proptest! {
        #[test]
        fn random_images_are_partitioned(
            w in 1u32..24,
            h in 1u32..24,
            seed in any::<u64>(),
            k in 1.0f32..3000.0,
            min_size in 0u32..40,
            sigma in 0.0f32..2.0,
        ) {
            let mut noise = Noise(seed | 1);
            let mut img = RgbImage::new(w, h);
            for p in img.pixels_mut() {
                for v in p.0.iter_mut() {
                    *v = (noise.next(127) + 128) as u8;
                }
            }
            let params = GraphParams { sigma, k, min_size, max_side: None };
            let (labels, count) = segment_labels(&img, &params).unwrap();
            prop_assert_eq!(labels.len(), (w * h) as usize);
            prop_assert!(labels.iter().all(|&l| l < count));
            prop_assert!(connected_components_agree(&labels, w as usize, h as usize));
            let masks = masks_from_labels(&labels, count, w, h);
            prop_assert_eq!(masks.len(), count as usize);
            let total: u64 = masks.iter().map(|m| m.area as u64).sum();
            prop_assert_eq!(total, (w * h) as u64);
            let mut cover = vec![0u8; (w * h) as usize];
            for m in &masks {
                prop_assert!(m.area >= min_size.min(w * h));
                for (c, &v) in cover.iter_mut().zip(&m.pixels) { *c += v; }
            }
            prop_assert!(cover.iter().all(|&c| c == 1));
        }
    }
}
