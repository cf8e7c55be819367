//! The CPU reference rasterizer: slow, simple, f64 throughout, written directly from the spec in
//! [`super::project`]; the GPU path is tested against it.

use rayon::prelude::*;
use slag_common::Result;
use slag_common::camera::{Intrinsics, WorldToCamera};
use slag_common::scene::Gaussians;

use super::project::{
    ALPHA_MIN, Splat2d, T_MIN, TILE_SIZE, project_gaussian, splat_alpha, tile_grid, tile_rect,
};
use super::{PixelWeights, WeightRasterizer, validate_raster};

/// Reference implementation of the weight rasterizer in f64: project every Gaussian
/// ([`project_gaussian`]), bin it into every 16×16 tile its radius box touches, sort each tile's
/// list by `(depth rounded to f32, id)` (the GPU's sort key), then blend front to back per pixel. Tiles run in parallel (rayon); each
/// tile is a plain per-pixel loop.
#[derive(Debug, Clone)]
pub struct CpuRasterizer {
    gaussians: Gaussians,
}

impl CpuRasterizer {
    /// Keeps a copy of the Gaussians' geometry (means, scales, rotations, opacities; SH dropped).
    pub fn new(gaussians: &Gaussians) -> Self {
        let gaussians = Gaussians {
            means: gaussians.means.clone(),
            scales: gaussians.scales.clone(),
            rotations: gaussians.rotations.clone(),
            opacities: gaussians.opacities.clone(),
            sh: None,
        };
        CpuRasterizer { gaussians }
    }

    /// Projects every Gaussian; `None` for culled ones. Index = Gaussian id.
    pub fn project_all(&self, k: &Intrinsics, w2c: &WorldToCamera) -> Vec<Option<Splat2d>> {
        let g = &self.gaussians;
        (0..g.len())
            .into_par_iter()
            .map(|i| {
                let f = |v: [f32; 3]| v.map(f64::from);
                let q = g.rotations[i].map(f64::from);
                project_gaussian(
                    f(g.means[i]),
                    f(g.scales[i]),
                    q,
                    g.opacities[i] as f64,
                    k,
                    w2c,
                )
            })
            .collect()
    }
}

impl WeightRasterizer for CpuRasterizer {
    fn rasterize(&mut self, k: &Intrinsics, w2c: &WorldToCamera) -> Result<PixelWeights> {
        validate_raster(k)?;
        let splats = self.project_all(k, w2c);
        let (tx, ty) = tile_grid(k.width, k.height);
        let bins = bin_into_tiles(&splats, tx, ty);
        // Per tile: sort front to back, ties by id; then blend each pixel.
        let tiles: Vec<TilePixels> = bins
            .into_par_iter()
            .enumerate()
            .map(|(t, list)| blend_tile(k, &splats, tx, t as u32, list))
            .collect();
        gather_csr(k, tx, &tiles)
    }

    fn name(&self) -> &str {
        "cpu-reference-f64"
    }
}

/// One tile's blended pixels, row-major within the tile: each pixel's `(Gaussian id, weight)`
/// list, front to back.
type TilePixels = Vec<Vec<(u32, f32)>>;

/// Binning step: every visible splat's `(depth as f32, id)` goes into each tile its radius box
/// touches; one list per tile of the `tx × ty` grid, in id order.
fn bin_into_tiles(splats: &[Option<Splat2d>], tx: u32, ty: u32) -> Vec<Vec<(f32, u32)>> {
    let mut bins: Vec<Vec<(f32, u32)>> = vec![Vec::new(); (tx * ty) as usize];
    for (id, s) in splats.iter().enumerate() {
        let Some(s) = s else { continue };
        let [x0, y0, x1, y1] = tile_rect(s.mean2d, s.radius, tx, ty);
        for y in y0..y1 {
            for x in x0..x1 {
                bins[(y * tx + x) as usize].push((s.depth as f32, id as u32));
            }
        }
    }
    bins
}

/// Tile step: sorts tile `t`'s list by `(depth, id)` and blends each of its pixels; pixels
/// outside the image get an empty list.
fn blend_tile(
    k: &Intrinsics,
    splats: &[Option<Splat2d>],
    tx: u32,
    t: u32,
    mut list: Vec<(f32, u32)>,
) -> TilePixels {
    list.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    let (tile_x, tile_y) = (t % tx, t / tx);
    let mut out = Vec::with_capacity((TILE_SIZE * TILE_SIZE) as usize);
    for ly in 0..TILE_SIZE {
        for lx in 0..TILE_SIZE {
            let (x, y) = (tile_x * TILE_SIZE + lx, tile_y * TILE_SIZE + ly);
            if x >= k.width || y >= k.height {
                out.push(Vec::new());
                continue;
            }
            out.push(blend_pixel(splats, &list, x as f64 + 0.5, y as f64 + 0.5));
        }
    }
    out
}

/// Pixel step: front-to-back alpha blending at pixel centre `(px, py)` over the tile's sorted
/// list; weight = alpha × transmittance, skipping splats below [`ALPHA_MIN`] and stopping before
/// transmittance would fall under [`T_MIN`].
fn blend_pixel(
    splats: &[Option<Splat2d>],
    list: &[(f32, u32)],
    px: f64,
    py: f64,
) -> Vec<(u32, f32)> {
    let mut t_acc = 1.0f64;
    let mut pixel = Vec::new();
    for &(_, id) in list {
        let Some(s) = &splats[id as usize] else {
            continue;
        };
        let (sigma, alpha) = splat_alpha(s, px, py);
        if sigma < 0.0 || alpha < ALPHA_MIN {
            continue;
        }
        let next_t = t_acc * (1.0 - alpha);
        if next_t < T_MIN {
            break;
        }
        pixel.push((id, (alpha * t_acc) as f32));
        t_acc = next_t;
    }
    pixel
}

/// Gather step: the tiles' pixel lists into CSR, pixel order `y * width + x`.
fn gather_csr(k: &Intrinsics, tx: u32, tiles: &[TilePixels]) -> Result<PixelWeights> {
    let n_pix = k.width as usize * k.height as usize;
    let mut offsets = Vec::with_capacity(n_pix + 1);
    let mut ids = Vec::new();
    let mut weights = Vec::new();
    offsets.push(0u32);
    for y in 0..k.height {
        for x in 0..k.width {
            let t = (y / TILE_SIZE) * tx + x / TILE_SIZE;
            let l = (y % TILE_SIZE) * TILE_SIZE + x % TILE_SIZE;
            for &(id, w) in &tiles[t as usize][l as usize] {
                ids.push(id);
                weights.push(w);
            }
            let n = u32::try_from(ids.len()).map_err(|_| {
                slag_common::Error::limit(
                    slag_common::Resource::RasterEntries,
                    "more than 2^32 pixel weights in one view",
                    "2^32",
                )
            })?;
            offsets.push(n);
        }
    }
    Ok(PixelWeights {
        width: k.width,
        height: k.height,
        offsets,
        ids,
        weights,
    })
}
