//! `slag-encoder render`: colour render of a training view through the weight rasterizer
//! (`colour_p = Σ_k w_kp c_k` on black), written as PNG, with its PSNR against the photo. This is
//! how the rasterizer's weights are validated on real data.

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;
use slag_common::camera;
use slag_common::scene::{self, PlyLoadOptions};

use slag_encoder::args::RasterArg;
use slag_encoder::pipeline::scene_ply;
use slag_encoder::raster::WeightRasterizer;

/// Arguments of `render`.
#[derive(Debug, Clone, Args)]
pub struct RenderArgs {
    /// Scene folder (point_cloud.ply, images/, sparse/0 or transforms.json).
    #[arg(long = "scene-dir", value_name = "DIR")]
    pub scene: PathBuf,
    /// The .ply; default <scene>/point_cloud.ply.
    #[arg(long)]
    pub ply: Option<PathBuf>,
    /// View to render: image file name, or index in the name-sorted list.
    #[arg(long, default_value = "0")]
    pub view: String,
    /// Render resolution relative to the photo (PSNR is reported at scale 1 only).
    #[arg(long, default_value_t = 1.0)]
    pub raster_scale: f64,
    /// Weight rasterizer.
    #[arg(long, value_enum, default_value_t = RasterArg::Gpu)]
    pub rasterizer: RasterArg,
    /// Output PNG.
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
}

/// What `render` reports.
#[derive(Debug, serde::Serialize)]
pub struct RenderOutput {
    /// Rendered view.
    pub view: String,
    /// Rasterizer used.
    pub rasterizer: String,
    /// Output size.
    pub width: u32,
    /// Output size.
    pub height: u32,
    /// PSNR against the photo, dB (scale 1 only).
    pub psnr_db: Option<f64>,
    /// The PNG written.
    pub out: PathBuf,
}

/// Runs `render`.
pub fn run(a: &RenderArgs) -> anyhow::Result<RenderOutput> {
    let ply = scene_ply(&a.scene, a.ply.as_deref());
    let gaussians = scene::load_ply(&ply, PlyLoadOptions { colours: true })?;
    let views = camera::load_views(&a.scene)?;
    let view = match a.view.parse::<usize>() {
        Ok(i) => views
            .get(i)
            .with_context(|| format!("view index {i} out of range (0..{})", views.len()))?,
        Err(_) => views
            .iter()
            .find(|v| v.name == a.view)
            .with_context(|| format!("no view named {:?} in {}", a.view, a.scene.display()))?,
    };
    let mut r: Box<dyn WeightRasterizer> =
        slag_encoder::pipeline::build::make_rasterizer(a.rasterizer.into(), &gaussians)?;
    let intr = slag_encoder::raster::raster_intrinsics(&view.intrinsics, a.raster_scale)?;
    let weights = r.rasterize(&intr, &view.world_to_camera)?;
    let img = slag_encoder::raster::colour::render_colour(
        &gaussians,
        &intr,
        &view.world_to_camera,
        &weights,
    )?;
    let psnr_db = if (a.raster_scale - 1.0).abs() < 1e-12 {
        let photo = slag_encoder::pipeline::read_image(view)?;
        Some(slag_encoder::raster::colour::psnr(&img, &photo)?)
    } else {
        None
    };
    img.save(&a.out)
        .with_context(|| format!("writing {}", a.out.display()))?;
    Ok(RenderOutput {
        view: view.name.clone(),
        rasterizer: r.name().to_string(),
        width: img.width(),
        height: img.height(),
        psnr_db,
        out: a.out.clone(),
    })
}
