//! Synthetic scenes for scale tests: a drone-style survey of a coloured terrain with any number of
//! Gaussians, written as an ordinary scene folder (`point_cloud.ply`, `images/`, `sparse/0/*.txt`)
//! so that `slag-encoder encode` runs on it unchanged.
//!
//! The terrain is the height field `z = A·sin(x/λ)·cos(y/λ)` over a square of side `extent`
//! (scene units, read as metres) centred on the origin, z up, painted in a 4 × 3 grid of the 12
//! colour-clip colours, so colour prompts have a ground truth here too. Gaussians are flat discs
//! on the terrain, spaced `extent / √N`. Cameras fly a ring at `0.6 · extent` height, looking at
//! points on the ground ([`ViewLayout::Ring`]), or sweep the terrain lane by lane like a survey
//! drone, low and looking forward and down ([`ViewLayout::Sweep`]); COLMAP/OpenCV camera axes (x
//! right, y down, z forward), PINHOLE.
//! Each image is the terrain colour at the ray's ground hit (ray-cast against the plane z = 0, with
//! a little texture), so masks follow the colour patches the Gaussians carry.
//!
//! With objects ([`write_synthetic_scene_with_objects`], `synth-scene --objects K`): K boxes of
//! known colour, size and position stand on the ground (the ground truth of the answer's
//! objects, [`object_layout`], written to `objects.json`). The terrain is then one flat gray patch
//! at z = 0, the plane the images ray-cast, so the Gaussians and the images show the same ground
//! and every box stands on it with its whole sides in view (gray is no object's colour); the
//! boxes are hollow shells of Gaussians on their top and four
//! sides (the terrain's spacing, discs lying in each face), and the images ray-cast the boxes
//! before the ground. [`touching_layout`] (`synth-scene --objects K --touching`) places boxes of
//! different colours side by side, sharing a wall: a wall inside a neighbour is never seen and
//! holds no Gaussians.

use std::io::Write;
use std::path::{Path, PathBuf};

use glam::{DMat3, DQuat, DVec3};
use rayon::prelude::*;
use slag_common::camera::colmap;
use slag_common::rng::SplitMix64;
use slag_common::scene::{Gaussians, ShCoeffs, write_ply};
use slag_common::{Error, Result};

use crate::check::require;

/// The 12 colour-clip colours (sRGB in [0, 1]) painting the terrain's 4 × 3 patches, in
/// color-clip's class order: red orange yellow green teal blue purple pink brown white gray black.
pub const PALETTE: [[f32; 3]; 12] = [
    [0.85, 0.10, 0.10],
    [0.95, 0.55, 0.10],
    [0.95, 0.90, 0.15],
    [0.15, 0.65, 0.20],
    [0.10, 0.60, 0.60],
    [0.15, 0.25, 0.85],
    [0.50, 0.20, 0.65],
    [0.95, 0.60, 0.75],
    [0.50, 0.30, 0.15],
    [0.97, 0.97, 0.97],
    [0.50, 0.50, 0.50],
    [0.05, 0.05, 0.05],
];

/// Size of a synthetic scene.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SyntheticSceneParams {
    /// Number of Gaussians N.
    pub gaussians: usize,
    /// Number of posed views.
    pub views: usize,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Side of the square terrain, scene units (metres).
    pub extent: f64,
    /// Seed of the deterministic generator.
    pub seed: u64,
    /// How the cameras fly.
    pub layout: ViewLayout,
}

/// How a synthetic scene's cameras fly ([`camera`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum ViewLayout {
    /// A ring at `0.6 · extent` height, radius `0.35 · extent`, each view looking at a ground
    /// point on the far side of the centre: every view sees most of the terrain.
    #[default]
    Ring,
    /// A survey drone's lawnmower sweep: parallel lanes along x across the terrain, flown in
    /// alternate directions at `0.12 · extent` height, each view looking along the lane and 50°
    /// down: a view sees a patch of the terrain, its neighbours along and across the lane
    /// overlap it, as in a photogrammetry flight (the paper's large scene: 1,657 such views).
    Sweep,
}

impl Default for SyntheticSceneParams {
    fn default() -> Self {
        Self {
            gaussians: 1_000_000,
            views: 16,
            width: 990,
            height: 742,
            extent: 100.0,
            seed: 1,
            layout: ViewLayout::Ring,
        }
    }
}

/// Palette index of the terrain when the scene has objects: gray.
pub const GROUND_WITH_OBJECTS: usize = 10;

/// A box standing on the flat ground of a scene with objects, axis-aligned, its base at z = 0.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct PlacedObject {
    /// Colour: index into [`PALETTE`] (color-clip's class order), never gray.
    pub colour: usize,
    /// Colour name (color-clip's class name).
    pub name: &'static str,
    /// Centre of the base, ground coordinates (x, y), scene units.
    pub center: [f64; 2],
    /// Full size along x, y and z (height), scene units.
    pub size: [f64; 3],
}

/// color-clip's class names, in [`PALETTE`] order.
pub const COLOUR_NAMES: [&str; 12] = [
    "red", "orange", "yellow", "green", "teal", "blue", "purple", "pink", "brown", "white", "gray",
    "black",
];

impl PlacedObject {
    /// The box `[min xyz, max xyz]`, scene frame.
    pub fn aabb(&self) -> [[f64; 3]; 2] {
        let z0 = 0.0;
        [
            [
                self.center[0] - self.size[0] / 2.0,
                self.center[1] - self.size[1] / 2.0,
                z0,
            ],
            [
                self.center[0] + self.size[0] / 2.0,
                self.center[1] + self.size[1] / 2.0,
                z0 + self.size[2],
            ],
        ]
    }
}

/// Largest `k` of [`object_layout`].
pub const MAX_OBJECTS: usize = 6;

/// One box of a layout: colour (index into [`COLOUR_NAMES`]), centre / extent, size / extent.
type ObjectRow = (usize, [f64; 2], [f64; 3]);

/// The first `k` (1..=[`MAX_OBJECTS`]) boxes of `table`, scaled to a terrain of side `extent`.
///
/// Errors: [`Error::Param`] `objects` for `k` outside 1..=[`MAX_OBJECTS`].
fn place(table: &[ObjectRow; MAX_OBJECTS], k: usize, extent: f64) -> Result<Vec<PlacedObject>> {
    if !(1..=MAX_OBJECTS).contains(&k) {
        return Err(Error::param(
            "objects",
            k,
            format!("a number of objects in 1..={MAX_OBJECTS}"),
        ));
    }
    Ok(table[..k]
        .iter()
        .map(|&(colour, c, sz)| PlacedObject {
            colour,
            name: COLOUR_NAMES[colour],
            center: c.map(|v| v * extent),
            size: sz.map(|v| v * extent),
        })
        .collect())
}

/// The first `k` (1..=[`MAX_OBJECTS`]) objects of a fixed layout on a terrain of side `extent`:
/// boxes of 6–12 % of the extent, in red (twice: opposite corners, 0.57·extent apart), blue,
/// yellow, green and purple, at least 0.2·extent apart (edge to edge ≥ 0.1·extent), all within
/// 0.3·extent of the centre so every view of the ring sees them.
///
/// Errors: [`Error::Param`] `objects` for `k` outside 1..=[`MAX_OBJECTS`].
pub fn object_layout(k: usize, extent: f64) -> Result<Vec<PlacedObject>> {
    // (colour, centre / extent, size / extent)
    let table: [ObjectRow; MAX_OBJECTS] = [
        (0, [-0.2, -0.2], [0.10, 0.07, 0.05]),
        (0, [0.2, 0.2], [0.08, 0.08, 0.04]),
        (5, [0.2, -0.2], [0.07, 0.12, 0.05]),
        (2, [-0.2, 0.2], [0.10, 0.10, 0.03]),
        (3, [0.0, 0.0], [0.08, 0.06, 0.07]),
        (6, [0.0, 0.25], [0.06, 0.06, 0.04]),
    ];
    place(&table, k, extent)
}

/// The first `k` (1..=[`MAX_OBJECTS`]) objects of a layout of **touching** boxes on a terrain of
/// side `extent`: three pairs, each of two colours, standing on the ground side by side so that
/// they share part of a wall (red beside blue along x, yellow beside green along y, orange
/// beside purple along x), boxes of 6–10 % of the extent with different heights (the taller's
/// wall shows above the lower one), pairs ≥ 0.1·extent apart, all within 0.25·extent of
/// the centre along each axis. The ground truth of instance AP on objects that touch each other and the ground.
///
/// Errors: [`Error::Param`] `objects` for `k` outside 1..=[`MAX_OBJECTS`].
pub fn touching_layout(k: usize, extent: f64) -> Result<Vec<PlacedObject>> {
    // (colour, centre / extent, size / extent); each second box's wall lies on its partner's.
    let table: [ObjectRow; MAX_OBJECTS] = [
        (0, [-0.20, -0.15], [0.10, 0.08, 0.05]),
        (5, [-0.11, -0.15], [0.08, 0.08, 0.07]),
        (2, [0.15, 0.10], [0.10, 0.10, 0.04]),
        (3, [0.15, 0.19], [0.08, 0.08, 0.06]),
        (1, [0.12, -0.20], [0.08, 0.06, 0.06]),
        (6, [0.19, -0.20], [0.06, 0.06, 0.04]),
    ];
    place(&table, k, extent)
}

/// Terrain height at (x, y): amplitude 2 % of the extent, wavelength 1/6 of it.
fn height(x: f64, y: f64, extent: f64) -> f64 {
    let l = extent / (6.0 * std::f64::consts::TAU);
    0.02 * extent * (x / l).sin() * (y / l).cos()
}

/// Palette index of the patch holding ground point (x, y).
fn patch(x: f64, y: f64, extent: f64) -> usize {
    let u = ((x / extent + 0.5) * 4.0).floor().clamp(0.0, 3.0) as usize;
    let v = ((y / extent + 0.5) * 3.0).floor().clamp(0.0, 2.0) as usize;
    v * 4 + u
}

/// The Gaussians of the terrain (with SH DC colours), deterministic in `p.seed`.
pub fn terrain_gaussians(p: &SyntheticSceneParams) -> Gaussians {
    terrain_gaussians_with_objects(p, &[])
}

/// [`terrain_gaussians`] with `objects` standing on it: the terrain is flat (z = 0, the ground
/// the images ray-cast) and gray, terrain Gaussians under a box are left out, and each box is a shell of discs on its top and four sides at the
/// terrain's spacing `extent / √N` (appended after the terrain, deterministic in `p.seed`).
pub fn terrain_gaussians_with_objects(
    p: &SyntheticSceneParams,
    objects: &[PlacedObject],
) -> Gaussians {
    scene_with_instances(p, objects).0
}

/// [`terrain_gaussians_with_objects`] and, per object (same order), the range of its shell's
/// Gaussians in the returned vertex order: the ground truth of instance scores. A wall of a box
/// that lies inside another box (two boxes touching) holds no Gaussians: it is never seen.
pub fn scene_with_instances(
    p: &SyntheticSceneParams,
    objects: &[PlacedObject],
) -> (Gaussians, Vec<std::ops::Range<usize>>) {
    let boxes: Vec<[[f64; 3]; 2]> = objects.iter().map(|o| o.aabb()).collect();
    let spacing = p.extent / (p.gaussians.max(1) as f64).sqrt();
    let terrain = terrain_discs(p, !objects.is_empty(), &boxes, spacing);
    let (shells, ranges) = object_shells(p, objects, &boxes, spacing, terrain.len());
    (gaussians_of(terrain.into_iter().chain(shells), p.gaussians), ranges)
}

/// The ground's discs: `p.gaussians` draws over the square of side `p.extent`, each a disc of
/// about `spacing` lying on the ground, the rolling terrain's height and palette patches, or
/// flat ground of one colour `with_objects`. Draws that fall under one of the `boxes` are left
/// out. Chunks of 65,536 draws have their own seeds: parallel and still deterministic.
fn terrain_discs(
    p: &SyntheticSceneParams,
    with_objects: bool,
    boxes: &[[[f64; 3]; 2]],
    spacing: f64,
) -> Vec<Disc> {
    const SH_C0: f64 = 0.282_094_791_773_878_14;
    const CHUNK: usize = 1 << 16;
    let under_a_box = |x: f64, y: f64| {
        boxes
            .iter()
            .any(|b| x >= b[0][0] && x <= b[1][0] && y >= b[0][1] && y <= b[1][1])
    };
    let n = p.gaussians;
    let parts: Vec<_> = (0..n.div_ceil(CHUNK))
        .into_par_iter()
        .map(|c| {
            let mut rng = SplitMix64::new(p.seed ^ (c as u64).wrapping_mul(0xD1B5_4A32_D192_ED03));
            let len = CHUNK.min(n - c * CHUNK);
            let mut out = Vec::with_capacity(len);
            for _ in 0..len {
                let x = (rng.next_f64() - 0.5) * p.extent;
                let y = (rng.next_f64() - 0.5) * p.extent;
                let z = if with_objects {
                    0.0
                } else {
                    height(x, y, p.extent)
                };
                let s = spacing * (0.6 + 0.8 * rng.next_f64());
                // A disc lying on the ground: thin along z, random spin about z.
                let a = rng.next_f64() * std::f64::consts::PI;
                let rot = [(a * 0.5).cos() as f32, 0.0, 0.0, (a * 0.5).sin() as f32];
                let col = if with_objects {
                    PALETTE[GROUND_WITH_OBJECTS]
                } else {
                    PALETTE[patch(x, y, p.extent)]
                };
                let jitter = 0.9 + 0.2 * rng.next_f64();
                let dc = col.map(|c| (((c as f64 * jitter).min(1.0) - 0.5) / SH_C0) as f32);
                let opacity = (0.6 + 0.35 * rng.next_f64()) as f32;
                if under_a_box(x, y) {
                    continue;
                }
                out.push((
                    [x as f32, y as f32, z as f32],
                    [s as f32, s as f32, (s * 0.1) as f32],
                    rot,
                    opacity,
                    dc,
                ));
            }
            out
        })
        .collect();
    parts.into_iter().flatten().collect()
}

/// Each object's shell ([`box_shell`], leaving out what lies inside the other `boxes`), one
/// after the other, and the range of each in the scene's vertex order, the shells starting at
/// vertex `start`.
fn object_shells(
    p: &SyntheticSceneParams,
    objects: &[PlacedObject],
    boxes: &[[[f64; 3]; 2]],
    spacing: f64,
    mut start: usize,
) -> (Vec<Disc>, Vec<std::ops::Range<usize>>) {
    let mut ranges = Vec::with_capacity(objects.len());
    let shells = objects
        .iter()
        .enumerate()
        .flat_map(|(k, o)| {
            let others: Vec<[[f64; 3]; 2]> = boxes
                .iter()
                .enumerate()
                .filter(|&(j, _)| j != k)
                .map(|(_, b)| *b)
                .collect();
            let shell = box_shell(o, p, spacing, k as u64, &others);
            ranges.push(start..start + shell.len());
            start += shell.len();
            shell
        })
        .collect();
    (shells, ranges)
}

/// The discs as Gaussians (SH degree 0), in order; `capacity` Gaussians reserved.
fn gaussians_of(discs: impl Iterator<Item = Disc>, capacity: usize) -> Gaussians {
    let mut g = Gaussians {
        means: Vec::with_capacity(capacity),
        scales: Vec::with_capacity(capacity),
        rotations: Vec::with_capacity(capacity),
        opacities: Vec::with_capacity(capacity),
        sh: None,
    };
    let mut dc = Vec::with_capacity(capacity * 3);
    for (m, s, r, o, d) in discs {
        g.means.push(m);
        g.scales.push(s);
        g.rotations.push(r);
        g.opacities.push(o);
        dc.extend_from_slice(&d);
    }
    g.sh = Some(ShCoeffs {
        degree: 0,
        coeffs: dc,
    });
    g
}

/// One Gaussian of a synthetic scene: mean, scales, rotation (w, x, y, z), opacity, SH DC.
type Disc = ([f32; 3], [f32; 3], [f32; 4], f32, [f32; 3]);

/// The discs of one box's top and four sides, on a jittered grid of step `spacing`, each lying
/// in its face (thin along the face normal), coloured like the box; discs inside one of the
/// `others` boxes (a wall shared with a touching box) are left out.
fn box_shell(
    o: &PlacedObject,
    p: &SyntheticSceneParams,
    spacing: f64,
    k: u64,
    others: &[[[f64; 3]; 2]],
) -> Vec<Disc> {
    const SH_C0: f64 = 0.282_094_791_773_878_14;
    let h = std::f64::consts::FRAC_1_SQRT_2 as f32;
    let b = o.aabb();
    let mut rng = SplitMix64::new(p.seed ^ 0x000B_1EC7 ^ k.wrapping_mul(0x9E37_79B9_7F4A_7C15));
    let mut out = Vec::new();
    // (fixed axis, fixed value, the two spanned axes, rotation taking local z to the normal)
    let faces: [(usize, f64, [usize; 2], [f32; 4]); 5] = [
        (2, b[1][2], [0, 1], [1.0, 0.0, 0.0, 0.0]),
        (0, b[0][0], [1, 2], [h, 0.0, h, 0.0]),
        (0, b[1][0], [1, 2], [h, 0.0, h, 0.0]),
        (1, b[0][1], [0, 2], [h, -h, 0.0, 0.0]),
        (1, b[1][1], [0, 2], [h, -h, 0.0, 0.0]),
    ];
    for (fixed, value, [u, v], rot) in faces {
        let (lu, lv) = (b[1][u] - b[0][u], b[1][v] - b[0][v]);
        let (nu, nv) = (
            (lu / spacing).ceil().max(1.0) as usize,
            (lv / spacing).ceil().max(1.0) as usize,
        );
        for i in 0..nu {
            for j in 0..nv {
                let mut m = [0f64; 3];
                m[fixed] = value;
                m[u] = b[0][u] + lu * (i as f64 + rng.next_f64()) / nu as f64;
                m[v] = b[0][v] + lv * (j as f64 + rng.next_f64()) / nv as f64;
                let s = spacing * (0.6 + 0.8 * rng.next_f64());
                let jitter = 0.9 + 0.2 * rng.next_f64();
                let dc = PALETTE[o.colour]
                    .map(|c| (((c as f64 * jitter).min(1.0) - 0.5) / SH_C0) as f32);
                let opacity = (0.6 + 0.35 * rng.next_f64()) as f32;
                // Shared walls: the partner's face lies on the same plane, up to rounding.
                let tol = 1e-6 * p.extent;
                let hidden = others
                    .iter()
                    .any(|b| (0..3).all(|a| m[a] >= b[0][a] - tol && m[a] <= b[1][a] + tol));
                if hidden {
                    continue;
                }
                out.push((
                    m.map(|x| x as f32),
                    [s as f32, s as f32, (s * 0.1) as f32],
                    rot,
                    opacity,
                    dc,
                ));
            }
        }
    }
    out
}

/// Distance along the ray `c + t·d` to the first face of box `b` it enters (slab method), `None`
/// when it misses or the box is behind.
pub(crate) fn ray_box(c: DVec3, d: DVec3, b: &[[f64; 3]; 2]) -> Option<f64> {
    let (mut t0, mut t1) = (0f64, f64::INFINITY);
    for a in 0..3 {
        let (o, di) = (c[a], d[a]);
        if di.abs() < 1e-12 {
            if o < b[0][a] || o > b[1][a] {
                return None;
            }
            continue;
        }
        let (ta, tb) = ((b[0][a] - o) / di, (b[1][a] - o) / di);
        t0 = t0.max(ta.min(tb));
        t1 = t1.min(ta.max(tb));
    }
    (t0 <= t1).then_some(t0)
}

/// One view: world-to-camera rotation (rows = camera x right, y down, z forward in world
/// coordinates) and camera centre, world frame, as `p.layout` flies them.
pub(crate) fn camera(i: usize, p: &SyntheticSceneParams) -> (DMat3, DVec3) {
    let (centre, fwd) = match p.layout {
        ViewLayout::Ring => ring_view(i, p),
        ViewLayout::Sweep => sweep_view(i, p),
    };
    let right = fwd.cross(DVec3::Z).normalize();
    let down = fwd.cross(right);
    (DMat3::from_cols(right, down, fwd).transpose(), centre)
}

/// View `i` of the ring: its centre and unit forward direction, looking at a ground point on
/// the ring's far side of the centre (oblique, drone-like).
fn ring_view(i: usize, p: &SyntheticSceneParams) -> (DVec3, DVec3) {
    let a = std::f64::consts::TAU * i as f64 / p.views.max(1) as f64;
    let r = 0.35 * p.extent;
    let centre = DVec3::new(r * a.cos(), r * a.sin(), 0.6 * p.extent);
    let target = DVec3::new(-0.15 * p.extent * a.cos(), -0.15 * p.extent * a.sin(), 0.0);
    (centre, (target - centre).normalize())
}

/// View `i` of the sweep ([`ViewLayout::Sweep`]): its centre and unit forward direction. The
/// `views` are cut into `round(√(views / 4))` lanes (at least 1) of equal length, lanes spread
/// evenly over the middle 80 % of the terrain in y, views evenly along the middle 90 % in x,
/// odd lanes flown back; forward is along the lane, 50° below the horizon.
fn sweep_view(i: usize, p: &SyntheticSceneParams) -> (DVec3, DVec3) {
    let views = p.views.max(1);
    let lanes = ((views as f64 / 4.0).sqrt().round() as usize).clamp(1, views);
    let per_lane = views.div_ceil(lanes);
    let (lane, k) = (i / per_lane, i % per_lane);
    let e = p.extent;
    let y = e * (-0.4 + 0.8 * (lane as f64 + 0.5) / lanes as f64);
    let along = e * (-0.45 + 0.9 * (k as f64 + 0.5) / per_lane as f64);
    let heading = if lane % 2 == 0 { 1.0 } else { -1.0 };
    let centre = DVec3::new(heading * along, y, 0.12 * e);
    let pitch = 50f64.to_radians();
    (centre, DVec3::new(heading * pitch.cos(), 0.0, -pitch.sin()))
}

/// Focal length (pixels) giving a 60° horizontal field of view.
pub(crate) fn focal(p: &SyntheticSceneParams) -> f64 {
    p.width as f64 / (2.0 * (30f64).to_radians().tan())
}

/// The image of view `i`: per pixel, the colour of the ground patch its ray meets (plane z = 0),
/// with a faint per-Gaussian-spacing texture; pixels above the horizon are sky white.
fn render_image(i: usize, p: &SyntheticSceneParams, objects: &[PlacedObject]) -> image::RgbImage {
    let boxes: Vec<([[f64; 3]; 2], usize)> = objects.iter().map(|o| (o.aabb(), o.colour)).collect();
    render_rays(i, p, |c, d| {
        let hit = boxes
            .iter()
            .filter_map(|(b, col)| ray_box(c, d, b).map(|t| (t, *col)))
            .min_by(|a, b| a.0.total_cmp(&b.0));
        if let Some((t, col)) = hit {
            let g = c + d * t;
            let k = 0.95 + 0.05 * ((g.x * 7.0).sin() * (g.y * 7.0).cos());
            PALETTE[col].map(|v| (v as f64 * k).min(1.0))
        } else if d.z < -1e-9 {
            let t = -c.z / d.z;
            let g = c + d * t;
            if g.x.abs() <= p.extent / 2.0 && g.y.abs() <= p.extent / 2.0 {
                let k = 0.95 + 0.05 * ((g.x * 7.0).sin() * (g.y * 7.0).cos());
                let ground = if boxes.is_empty() {
                    patch(g.x, g.y, p.extent)
                } else {
                    GROUND_WITH_OBJECTS
                };
                PALETTE[ground].map(|v| (v as f64 * k).min(1.0))
            } else {
                [0.35, 0.35, 0.35]
            }
        } else {
            [1.0, 1.0, 1.0]
        }
    })
}

/// The `p.width × p.height` photo of view `i` ([`camera`], [`focal`]): each pixel is
/// `colour(c, d)` (r, g, b in 0..1, rounded to 8 bits) of the ray through its centre from the
/// camera centre `c` along `d` (world frame, unit depth along the optical axis, not normalised);
/// rows in parallel.
pub(crate) fn render_rays(
    i: usize,
    p: &SyntheticSceneParams,
    colour: impl Fn(DVec3, DVec3) -> [f64; 3] + Sync,
) -> image::RgbImage {
    let (r, c) = camera(i, p);
    let rt = r.transpose();
    let f = focal(p);
    let (cx, cy) = (p.width as f64 / 2.0, p.height as f64 / 2.0);
    let mut img = image::RgbImage::new(p.width, p.height);
    let w = p.width as usize;
    let buf: &mut [u8] = &mut img;
    buf.par_chunks_mut(w * 3).enumerate().for_each(|(y, row)| {
        for x in 0..w {
            let d = rt * DVec3::new((x as f64 + 0.5 - cx) / f, (y as f64 + 0.5 - cy) / f, 1.0);
            let rgb = colour(c, d);
            for ch in 0..3 {
                row[3 * x + ch] = (rgb[ch] * 255.0).round() as u8;
            }
        }
    });
    img
}

/// What [`write_synthetic_scene`] wrote.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SyntheticSummary {
    /// Gaussians in `point_cloud.ply`.
    pub gaussians: usize,
    /// Posed views.
    pub views: usize,
    /// Bytes of `point_cloud.ply`.
    pub ply_bytes: u64,
}

/// Writes a synthetic scene folder at `dir`: `point_cloud.ply` (INRIA layout, SH degree 0),
/// `images/view_XXXX.png` and `sparse/0/{cameras,images,points3D}.txt` (COLMAP text, one PINHOLE
/// camera, world-to-camera poses). Every file is written whole before the next starts;
/// `sparse/0/images.txt` is written last, so a folder without it is incomplete.
///
/// Errors: [`Error::Param`] (the field) for zero Gaussians/views, an empty image size or a
/// non-positive extent; I/O errors naming the path.
pub fn write_synthetic_scene(dir: &Path, p: &SyntheticSceneParams) -> Result<SyntheticSummary> {
    write_synthetic_scene_with_objects(dir, p, &[])
}

/// [`write_synthetic_scene`] with `objects` standing on the terrain (module doc); with objects,
/// `objects.json` (their list, [`PlacedObject`] fields plus `aabb`, the true box in the scene
/// frame, and `gaussians`, `[start, end)` of the box's Gaussians in `point_cloud.ply`'s vertex
/// order, [`scene_with_instances`]) is written too. `point_cloud.ply` then holds the terrain's Gaussians outside the boxes'
/// footprints and the boxes' shells.
///
/// Errors: as [`write_synthetic_scene`]; [`Error::Param`] `objects` for an object of gray (the
/// terrain's colour), an unknown colour or a non-positive size.
pub fn write_synthetic_scene_with_objects(
    dir: &Path,
    p: &SyntheticSceneParams,
    objects: &[PlacedObject],
) -> Result<SyntheticSummary> {
    for o in objects {
        if o.colour >= PALETTE.len()
            || o.colour == GROUND_WITH_OBJECTS
            || !o.size.iter().all(|v| v.is_finite() && *v > 0.0)
            || !o.center.iter().all(|v| v.is_finite())
        {
            return Err(Error::param(
                "objects",
                format!("{o:?}"),
                "objects of a palette colour other than gray, with finite positive sizes",
            ));
        }
    }
    check_params(p)?;
    let folders = SceneFolders::create(dir)?;
    let (g, instances) = scene_with_instances(p, objects);
    let gaussians = g.len();
    let ply = dir.join("point_cloud.ply");
    write_ply(&ply, &g)?;
    drop(g);
    if !objects.is_empty() {
        let truth: Vec<serde_json::Value> = objects
            .iter()
            .zip(&instances)
            .map(|(o, r)| {
                serde_json::json!({
                    "colour": o.colour, "name": o.name, "center": o.center, "size": o.size,
                    "aabb": o.aabb(), "gaussians": [r.start, r.end],
                })
            })
            .collect();
        let bytes = serde_json::to_vec_pretty(&truth)
            .map_err(|e| Error::internal(format!("objects.json: {e}")))?;
        write_file(&dir.join("objects.json"), &bytes)?;
    }
    folders.finish(p, &ply, gaussians, |i| render_image(i, p, objects))
}

/// Writes `cameras.txt` (one PINHOLE camera of [`focal`]) and an empty `points3D.txt` into
/// `sparse` (`sparse/0`).
fn write_cameras(sparse: &Path, p: &SyntheticSceneParams) -> Result<()> {
    let f = focal(p);
    let cameras = format!(
        "# Camera list: CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n1 PINHOLE {} {} {f} {f} {} {}\n",
        p.width,
        p.height,
        p.width as f64 / 2.0,
        p.height as f64 / 2.0
    );
    write_file(&sparse.join("cameras.txt"), cameras.as_bytes())?;
    write_file(&sparse.join("points3D.txt"), b"# no points\n")
}

/// The folders of a scene being written: `images/` for the photos, `sparse/0` for the COLMAP
/// text files, and its `images.txt`, written last (a folder without it is incomplete).
pub(crate) struct SceneFolders {
    images: PathBuf,
    sparse: PathBuf,
    images_txt: PathBuf,
}

impl SceneFolders {
    /// Creates `dir/images` and `dir/sparse/0` and removes a stale `sparse/0/images.txt` (an
    /// interrupted rewrite must not look complete).
    ///
    /// Errors: I/O naming the path.
    pub(crate) fn create(dir: &Path) -> Result<Self> {
        let images = dir.join("images");
        let sparse = dir.join("sparse").join("0");
        for d in [&images, &sparse] {
            std::fs::create_dir_all(d).map_err(|e| Error::io(d, e))?;
        }
        // Stale poses first: an interrupted rewrite must not look complete.
        let images_txt = sparse.join("images.txt");
        if images_txt.exists() {
            std::fs::remove_file(&images_txt).map_err(|e| Error::io(&images_txt, e))?;
        }
        Ok(SceneFolders {
            images,
            sparse,
            images_txt,
        })
    }

    /// Completes the scene whose `.ply` of `gaussians` Gaussians is written at `ply`: every
    /// view's photo `render(i)` as `images/view_XXXX.png`, the cameras, then `images.txt` last.
    /// Returns what was written.
    ///
    /// Errors: I/O naming the path.
    pub(crate) fn finish(
        &self,
        p: &SyntheticSceneParams,
        ply: &Path,
        gaussians: usize,
        render: impl Fn(usize) -> image::RgbImage,
    ) -> Result<SyntheticSummary> {
        for i in 0..p.views {
            let path = self.images.join(format!("view_{i:04}.png"));
            render(i)
                .save(&path)
                .map_err(|e| Error::io(&path, std::io::Error::other(e)))?;
        }
        write_cameras(&self.sparse, p)?;
        write_file(&self.images_txt, poses(p).as_bytes())?;
        let ply_bytes = std::fs::metadata(ply).map_err(|e| Error::io(ply, e))?.len();
        Ok(SyntheticSummary {
            gaussians,
            views: p.views,
            ply_bytes,
        })
    }
}

/// Checks a scene's size: Gaussians, views and the image size at least 1, a finite positive
/// extent.
///
/// Errors: [`Error::Param`] naming the field.
pub(crate) fn check_params(p: &SyntheticSceneParams) -> Result<()> {
    for (name, v) in [
        ("gaussians", p.gaussians),
        ("views", p.views),
        ("width", p.width as usize),
        ("height", p.height as usize),
    ] {
        require(
            v > 0,
            name,
            0,
            "at least 1 (a synthetic scene needs Gaussians, views and a non-empty image size)",
        )?;
    }
    let extent = p.extent;
    require(
        extent.is_finite() && extent > 0.0,
        "extent",
        extent,
        "a positive number of metres",
    )?;
    Ok(())
}

/// The text of `images.txt`: every view of the ring ([`camera`]), `view_XXXX.png`.
fn poses(p: &SyntheticSceneParams) -> String {
    let mut poses = String::from("# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n");
    for i in 0..p.views {
        let (r, c) = camera(i, p);
        let q = DQuat::from_mat3(&r).normalize();
        let t = -(r * c);
        let name = format!("view_{i:04}.png");
        poses.push_str(&colmap::images_txt_entry(i + 1, q, t, 1, &name));
    }
    poses
}

pub(crate) fn write_file(path: &Path, bytes: &[u8]) -> Result<()> {
    let mut f = std::fs::File::create(path).map_err(|e| Error::io(path, e))?;
    f.write_all(bytes).map_err(|e| Error::io(path, e))?;
    f.sync_all().map_err(|e| Error::io(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raster::{CpuRasterizer, WeightRasterizer, raster_intrinsics};

    #[test]
    fn a_sweep_flies_low_lanes_whose_views_each_see_a_patch_of_the_terrain() {
        let dir = tempfile::tempdir().expect("tempdir");
        let p = SyntheticSceneParams {
            gaussians: 20_000,
            views: 16,
            width: 80,
            height: 60,
            extent: 50.0,
            seed: 7,
            layout: ViewLayout::Sweep,
        };
        write_synthetic_scene(dir.path(), &p).expect("write");
        let (g, views, _) = crate::pipeline::SceneInput::new(dir.path(), None, 1)
            .load()
            .expect("scene");
        assert_eq!(views.len(), 16);
        let mut r = CpuRasterizer::new(&g);
        let mut union = vec![false; g.len()];
        let mut seen_by = Vec::new();
        for v in &views {
            // Low over the terrain: 0.12 of the extent up.
            let c = v.world_to_camera.camera_centre();
            assert!((c.z - 6.0).abs() < 1e-6, "{c:?}");
            let k = raster_intrinsics(&v.intrinsics, 0.5).expect("intrinsics");
            let w = r.rasterize(&k, &v.world_to_camera).expect("raster");
            let total = (w.width * w.height) as usize;
            let covered = (0..total).filter(|&i| w.offsets[i + 1] > w.offsets[i]).count();
            assert!(covered * 2 > total, "only {covered} of {total} pixels covered");
            let mut seen = vec![false; g.len()];
            for &id in &w.ids {
                seen[id as usize] = true;
                union[id as usize] = true;
            }
            let n = seen.iter().filter(|&&s| s).count();
            // A patch: far less than the terrain.
            assert!(n * 5 < g.len(), "{} sees {n} of {}", v.name, g.len());
            seen_by.push(seen);
        }
        // Two lanes of eight: neighbours along a lane overlap, and the lanes together see most
        // of the terrain's middle.
        for lane in 0..2 {
            for k in 0..7 {
                let (a, b) = (&seen_by[lane * 8 + k], &seen_by[lane * 8 + k + 1]);
                assert!(a.iter().zip(b).any(|(x, y)| *x && *y), "{lane} {k}");
            }
        }
        let all = union.iter().filter(|&&s| s).count();
        assert!(all * 3 > g.len(), "the sweep sees {all} of {}", g.len());
    }

    #[test]
    fn synthetic_scene_loads_and_its_views_see_the_terrain() {
        let dir = tempfile::tempdir().expect("tempdir");
        let p = SyntheticSceneParams {
            gaussians: 20_000,
            views: 3,
            width: 160,
            height: 120,
            extent: 50.0,
            seed: 7,
            ..Default::default()
        };
        let s = write_synthetic_scene(dir.path(), &p).expect("write");
        assert_eq!((s.gaussians, s.views), (20_000, 3));
        let g = slag_common::scene::load_ply(
            &dir.path().join("point_cloud.ply"),
            slag_common::scene::PlyLoadOptions { colours: true },
        )
        .expect("ply");
        assert_eq!(g.len(), 20_000);
        let views = slag_common::camera::load_views(dir.path()).expect("views");
        assert_eq!(views.len(), 3);
        let mut r = CpuRasterizer::new(&g);
        for v in &views {
            // The camera centre recovered from the written pose is above the terrain.
            let img = image::open(&v.image_path).expect("image").to_rgb8();
            assert_eq!(img.dimensions(), (160, 120));
            let k = raster_intrinsics(&v.intrinsics, 0.5).expect("intrinsics");
            let w = r.rasterize(&k, &v.world_to_camera).expect("raster");
            // Most pixels look at the terrain, so most are covered by Gaussians.
            let covered = (0..w.height)
                .flat_map(|y| (0..w.width).map(move |x| (x, y)))
                .filter(|&(x, y)| !w.pixel(x, y).0.is_empty())
                .count();
            let total = (w.width * w.height) as usize;
            assert!(
                covered * 2 > total,
                "only {covered} of {total} pixels covered"
            );
            // The Gaussian seen at the image centre has the colour the image shows there.
            let (ids, wts) = w.pixel(w.width / 2, w.height / 2);
            let best = ids
                .iter()
                .zip(wts)
                .max_by(|a, b| a.1.total_cmp(b.1))
                .map(|(&i, _)| i as usize)
                .expect("centre pixel covered");
            let sh = g.sh.as_ref().expect("colours");
            let dc = sh.dc(best);
            let rgb = dc.map(|c| 0.5 + 0.282_094_8 * c);
            let px = img.get_pixel(img.width() / 2, img.height() / 2).0;
            for ch in 0..3 {
                assert!(
                    (rgb[ch] - px[ch] as f32 / 255.0).abs() < 0.2,
                    "centre colour {rgb:?} vs image {px:?}"
                );
            }
        }
    }

    #[test]
    fn bad_sizes_are_refused() {
        let dir = tempfile::tempdir().expect("tempdir");
        let p = SyntheticSceneParams {
            gaussians: 0,
            ..Default::default()
        };
        assert!(matches!(
            write_synthetic_scene(dir.path(), &p),
            Err(Error::Param {
                name: "gaussians",
                ..
            })
        ));
        let p = SyntheticSceneParams {
            extent: f64::NAN,
            gaussians: 10,
            ..Default::default()
        };
        assert!(matches!(
            write_synthetic_scene(dir.path(), &p),
            Err(Error::Param { name: "extent", .. })
        ));
    }
}
