//! `slag-encoder synth-scene`: write a synthetic terrain scene of any size (scale tests).

use std::path::PathBuf;

use clap::Args;

use slag_encoder::object_scene::{self, Texture, room_layout, write_room_scene};
use slag_encoder::synthetic::{
    SyntheticSceneParams, SyntheticSummary, ViewLayout, object_layout, touching_layout,
    write_synthetic_scene_with_objects,
};

/// Arguments of `synth-scene`.
#[derive(Debug, Clone, Args)]
pub struct SynthArgs {
    /// Number of Gaussians (suffixes K and M allowed, e.g. 30M).
    #[arg(long, value_parser = parse_count)]
    pub gaussians: usize,
    /// Number of posed views.
    #[arg(long = "view-count", value_name = "N", default_value_t = 16)]
    pub views: usize,
    /// Image width, pixels.
    #[arg(long, default_value_t = 990)]
    pub width: u32,
    /// Image height, pixels.
    #[arg(long, default_value_t = 742)]
    pub height: u32,
    /// Side of the square terrain, metres.
    #[arg(long, default_value_t = 100.0)]
    pub extent: f64,
    /// Generator seed.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// How the cameras fly: a ring high above the terrain, each view seeing most of it, or a
    /// survey drone's lawnmower sweep, low and looking forward and down, each view a patch (the
    /// paper's large scene: --gaussians 38M --view-count 1657 --layout sweep).
    #[arg(long, value_enum, default_value_t = ViewLayout::Ring)]
    pub layout: ViewLayout,
    /// Output scene folder.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Place K (1..=6) boxes of known colour, size and position on a gray terrain (two red ones
    /// far apart first), the ground truth of query answers' objects; written to objects.json.
    #[arg(long)]
    pub objects: Option<usize>,
    /// With --objects: boxes of different colours in touching pairs (sharing a wall, all on the
    /// ground) instead of far apart; the ground truth of instance AP (`eval-objects`).
    #[arg(long, requires = "objects", conflicts_with = "room")]
    pub touching: bool,
    /// With --objects K (1..=10): a room instead of a terrain: boxes, cylinders and spheres of
    /// known class on a gray floor and against white walls, some touching, with textured
    /// surfaces; --extent is the room's side; writes truth.json (every Gaussian's class and
    /// object) beside objects.json.
    #[arg(long, requires = "objects")]
    pub room: bool,
    /// With --room: share of an object's surface cells (speckles) in another class's colour.
    #[arg(long, requires = "room", default_value_t = object_scene::DEFAULT_SPECKLES)]
    pub speckles: f64,
    /// With --room: side of a speckle cell, scene units; default extent / 60.
    #[arg(long, requires = "room")]
    pub speckle_size: Option<f64>,
    /// With --room: share of each stripe period in the object's stripe colour.
    #[arg(long, requires = "room", default_value_t = object_scene::DEFAULT_STRIPES)]
    pub stripes: f64,
    /// With --room: height of one stripe period, scene units; default extent / 24.
    #[arg(long, requires = "room")]
    pub stripe_period: Option<f64>,
    /// With --room: shading strength (faces towards the light lighter, away darker), 0..=1.
    #[arg(long, requires = "room", default_value_t = object_scene::DEFAULT_SHADING)]
    pub shading: f64,
}

/// Parses `30M`, `500K` or a plain count.
pub fn parse_count(s: &str) -> Result<usize, String> {
    let t = s.trim();
    let (num, mult) = match t.chars().last() {
        Some('M' | 'm') => (&t[..t.len() - 1], 1_000_000),
        Some('K' | 'k') => (&t[..t.len() - 1], 1_000),
        _ => (t, 1),
    };
    num.parse::<usize>()
        .ok()
        .and_then(|n| n.checked_mul(mult))
        .filter(|&n| n > 0)
        .ok_or_else(|| format!("{s:?} is not a positive count (e.g. 1000000, 500K, 30M)"))
}

/// Writes the scene and returns what was written.
pub fn run(a: &SynthArgs) -> anyhow::Result<SyntheticSummary> {
    let p = SyntheticSceneParams {
        gaussians: a.gaussians,
        views: a.views,
        width: a.width,
        height: a.height,
        extent: a.extent,
        seed: a.seed,
        layout: a.layout,
    };
    if let (true, Some(k)) = (a.room, a.objects) {
        let defaults = Texture::for_extent(a.extent);
        let texture = Texture {
            speckles: a.speckles,
            speckle_size: a.speckle_size.unwrap_or(defaults.speckle_size),
            stripes: a.stripes,
            stripe_period: a.stripe_period.unwrap_or(defaults.stripe_period),
            shading: a.shading,
        };
        let objects = room_layout(k, a.extent)?;
        return Ok(write_room_scene(&a.out, &p, &objects, &texture)?);
    }
    let objects = match a.objects {
        Some(k) if a.touching => touching_layout(k, a.extent)?,
        Some(k) => object_layout(k, a.extent)?,
        None => Vec::new(),
    };
    Ok(write_synthetic_scene_with_objects(&a.out, &p, &objects)?)
}
