//! A labelled-object room (`synth-scene --objects K --room`): boxes, cylinders and spheres of
//! known class on a floor and against walls, some touching each other, with **textured
//! surfaces**, written with the truth of every Gaussian, the truth that prediction filtering
//! assumes (each object is one class, whatever its texture shows).
//!
//! - **Room.** A square floor of side `extent` (gray) centred on the origin, z up, and four walls
//!   of height `extent / 4` (white) at `x, y = ±extent / 2`. The cameras are the ring of
//!   [`crate::synthetic`] (radius `0.35·extent`, height `0.6·extent`), inside the walls.
//! - **Objects** ([`room_layout`]): up to [`MAX_ROOM_OBJECTS`] boxes, vertical cylinders and
//!   spheres standing on the floor, in 9 classes (color-clip's colours other than gray and white;
//!   red twice), two against walls, three touching pairs, two far apart.
//! - **Texture** ([`Texture`]): each surface point takes its object's class colour, except
//!   *speckles* (cells of `speckle_size` whose hash falls below `speckles` take another class's
//!   colour), *stripes* (horizontal bands, a share `stripes` of each `stripe_period` of height,
//!   in a second class colour per object), and *shading* (a face turned to the light is lighter,
//!   one turned away darker: brightness `1 + shading·(2·max(0, n·L) − 1)`). The photos ray-cast
//!   the same texture at every hit point, so masks and crops see what the Gaussians carry.
//! - **Gaussians.** Flat discs lying in each surface (thin along its normal) on a jittered grid of
//!   step `√(area / N)`, coloured with the texture at their mean; surface points inside another
//!   object or behind a wall (never seen) are left out. Order: floor, walls, then each object's.
//! - **Truth.** `objects.json` (the list `eval-objects` reads: per object its `class` and `name`
//!   (the class colour), `shape`, `aabb`, `gaussians` `[start, end)`) and `truth.json`
//!   ([`GaussianTruth`]: the class and object of every Gaussian as runs over the vertex order;
//!   floor and walls are classes without an object).

use std::path::Path;

use glam::{DQuat, DVec3};
use slag_common::rng::SplitMix64;
use slag_common::scene::{Gaussians, ShCoeffs, write_ply};
use slag_common::{Error, Result};

use crate::synthetic::{
    COLOUR_NAMES, PALETTE, SceneFolders, SyntheticSceneParams, SyntheticSummary, check_params,
    ray_box, render_rays, write_file,
};

/// Largest `k` of [`room_layout`].
pub const MAX_ROOM_OBJECTS: usize = 10;
/// Class (palette index) of the floor: gray.
pub const FLOOR_CLASS: usize = 10;
/// Class (palette index) of the walls: white.
pub const WALL_CLASS: usize = 9;
/// The classes objects take (palette indices): every colour but gray and white.
const OBJECT_CLASSES: [usize; 10] = [0, 1, 2, 3, 4, 5, 6, 7, 8, 11];

/// Default [`Texture::speckles`].
pub const DEFAULT_SPECKLES: f64 = 0.08;
/// Default [`Texture::stripes`].
pub const DEFAULT_STRIPES: f64 = 0.15;
/// Default [`Texture::shading`].
pub const DEFAULT_SHADING: f64 = 0.3;

/// How surfaces are textured (module doc). Shares in `[0, 1]`, lengths in scene units.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Texture {
    /// Share of an object's surface cells in another class's colour.
    pub speckles: f64,
    /// Side of a speckle cell, scene units.
    pub speckle_size: f64,
    /// Share of each stripe period in the object's stripe colour.
    pub stripes: f64,
    /// Height of one stripe period, scene units.
    pub stripe_period: f64,
    /// Strength of the light's shading, 0 (none) to 1.
    pub shading: f64,
}

impl Texture {
    /// Defaults for a room of side `extent`: 8 % speckles of `extent / 60`, stripes 15 % of
    /// each `extent / 24`, shading 0.3: surfaces that are mostly one colour, with the flecks,
    /// bands and shaded faces of painted, printed and lit objects.
    pub fn for_extent(extent: f64) -> Self {
        Texture {
            speckles: DEFAULT_SPECKLES,
            speckle_size: extent / 60.0,
            stripes: DEFAULT_STRIPES,
            stripe_period: extent / 24.0,
            shading: DEFAULT_SHADING,
        }
    }

    /// Errors: [`Error::Param`] naming the field outside its domain.
    fn check(&self) -> Result<()> {
        for (name, v) in [
            ("speckles", self.speckles),
            ("stripes", self.stripes),
            ("shading", self.shading),
        ] {
            if !(0.0..=1.0).contains(&v) {
                return Err(Error::param(name, v, "a share in 0..=1"));
            }
        }
        for (name, v) in [
            ("speckle_size", self.speckle_size),
            ("stripe_period", self.stripe_period),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(Error::param(name, v, "a length > 0, scene units"));
            }
        }
        Ok(())
    }
}

/// Shape of a room object.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Shape {
    /// Axis-aligned box; `size` = full x, y, z lengths.
    Box,
    /// Vertical cylinder on the floor; `size` = [diameter, diameter, height].
    Cylinder,
    /// Sphere resting on the floor; `size` = [diameter; 3].
    Sphere,
}

/// One object of the room, standing on the floor (its base at z = 0).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct RoomObject {
    /// Class: index into [`PALETTE`] / [`COLOUR_NAMES`].
    pub class: usize,
    /// The class name (the prompt that should find it).
    pub name: &'static str,
    /// Shape.
    pub shape: Shape,
    /// Centre of the base, (x, y), scene units.
    pub center: [f64; 2],
    /// Full size along x, y, z, scene units.
    pub size: [f64; 3],
    /// Class of its stripes (palette index).
    pub stripe_class: usize,
}

impl RoomObject {
    /// The true box `[min xyz, max xyz]`, scene frame.
    pub fn aabb(&self) -> [[f64; 3]; 2] {
        let [sx, sy, sz] = self.size;
        [
            [self.center[0] - sx / 2.0, self.center[1] - sy / 2.0, 0.0],
            [self.center[0] + sx / 2.0, self.center[1] + sy / 2.0, sz],
        ]
    }

    /// Whether `p` lies inside the solid, grown by `tol`.
    fn contains(&self, p: DVec3, tol: f64) -> bool {
        let b = self.aabb();
        let in_box = (0..3).all(|a| p[a] >= b[0][a] - tol && p[a] <= b[1][a] + tol);
        match self.shape {
            Shape::Box => in_box,
            Shape::Cylinder => {
                let r = self.size[0] / 2.0 + tol;
                let (dx, dy) = (p.x - self.center[0], p.y - self.center[1]);
                in_box && dx * dx + dy * dy <= r * r
            }
            Shape::Sphere => {
                let r = self.size[0] / 2.0;
                p.distance(self.sphere_centre()) <= r + tol
            }
        }
    }

    fn sphere_centre(&self) -> DVec3 {
        DVec3::new(self.center[0], self.center[1], self.size[0] / 2.0)
    }
}

/// The first `k` (1..=[`MAX_ROOM_OBJECTS`]) objects of the room of side `extent`: a red box
/// against the wall x = −extent/2 with a blue cylinder touching it, a yellow sphere touching a
/// green box, a purple cylinder against the wall y = +extent/2 with a teal sphere touching it,
/// an orange box in the corner (+x, −y), a second red object (a cylinder), a pink box and a
/// brown box (tall) apart. Sizes 8–16 % of the extent.
///
/// Errors: [`Error::Param`] `objects` for `k` outside 1..=[`MAX_ROOM_OBJECTS`].
pub fn room_layout(k: usize, extent: f64) -> Result<Vec<RoomObject>> {
    if !(1..=MAX_ROOM_OBJECTS).contains(&k) {
        return Err(Error::param(
            "objects",
            k,
            format!("a number of room objects in 1..={MAX_ROOM_OBJECTS}"),
        ));
    }
    use Shape::*;
    // (class, shape, centre / extent, size / extent, stripe class)
    type Row = (usize, Shape, [f64; 2], [f64; 3], usize);
    let table: [Row; MAX_ROOM_OBJECTS] = [
        (0, Box, [-0.45, -0.10], [0.10, 0.16, 0.10], 2),
        (5, Cylinder, [-0.355, -0.10], [0.09, 0.09, 0.12], 9),
        (2, Sphere, [0.05, 0.0], [0.10, 0.10, 0.10], 1),
        (3, Box, [0.15, 0.0], [0.10, 0.10, 0.08], 11),
        (6, Cylinder, [-0.15, 0.45], [0.10, 0.10, 0.10], 7),
        (4, Sphere, [-0.06, 0.45], [0.08, 0.08, 0.08], 5),
        (1, Box, [0.43, -0.45], [0.14, 0.10, 0.12], 8),
        (0, Cylinder, [0.25, 0.25], [0.08, 0.08, 0.14], 11),
        (7, Box, [-0.25, 0.15], [0.12, 0.08, 0.06], 6),
        (8, Box, [0.30, -0.10], [0.08, 0.12, 0.16], 2),
    ];
    Ok(table[..k]
        .iter()
        .map(|&(class, shape, c, s, stripe_class)| RoomObject {
            class,
            name: COLOUR_NAMES[class],
            shape,
            center: c.map(|v| v * extent),
            size: s.map(|v| v * extent),
            stripe_class,
        })
        .collect())
}

/// What a surface point belongs to.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Surface {
    Floor,
    Wall,
    Object(usize),
}

/// The room: its side, wall height, objects and texture.
struct Room<'a> {
    extent: f64,
    wall: f64,
    objects: &'a [RoomObject],
    texture: Texture,
    seed: u64,
}

/// Unit vector towards the light (from above, a little from +x +y).
fn light() -> DVec3 {
    DVec3::new(0.4, 0.3, 1.0).normalize()
}

/// A hash of integer cell coordinates and a seed, uniform in [0, 1).
fn cell_hash(c: [i64; 3], seed: u64, salt: u64) -> f64 {
    let mut h = seed ^ salt.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    for v in c {
        h = (h ^ v as u64).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        h ^= h >> 31;
    }
    SplitMix64::new(h).next_f64()
}

impl Room<'_> {
    /// The colour (sRGB in [0, 1]) of surface `s` at point `p` with outward normal `n`.
    fn colour(&self, s: Surface, p: DVec3, n: DVec3) -> [f64; 3] {
        let t = &self.texture;
        let base = match s {
            Surface::Floor => FLOOR_CLASS,
            Surface::Wall => WALL_CLASS,
            Surface::Object(k) => {
                let o = &self.objects[k];
                let cell = [0, 1, 2].map(|a| (p[a] / t.speckle_size).floor() as i64);
                let phase = (p.z / t.stripe_period).rem_euclid(1.0);
                if cell_hash(cell, self.seed, 1) < t.speckles {
                    let others: Vec<usize> = OBJECT_CLASSES
                        .into_iter()
                        .filter(|&c| c != o.class)
                        .collect();
                    let pick = cell_hash(cell, self.seed, 2) * others.len() as f64;
                    others[(pick as usize).min(others.len() - 1)]
                } else if phase < t.stripes {
                    o.stripe_class
                } else {
                    o.class
                }
            }
        };
        let lit = 1.0 + t.shading * (2.0 * n.dot(light()).max(0.0) - 1.0);
        let k = if matches!(s, Surface::Object(_)) {
            lit
        } else {
            1.0
        };
        PALETTE[base].map(|v| (f64::from(v) * k).clamp(0.0, 1.0))
    }

    /// Whether a point of surface `s` is hidden: inside another object, or (an object's) on or
    /// behind a wall.
    fn hidden(&self, s: Surface, p: DVec3) -> bool {
        let tol = 1e-6 * self.extent;
        let own = match s {
            Surface::Object(k) => Some(k),
            _ => None,
        };
        if own.is_some() && (p.x.abs().max(p.y.abs()) >= self.extent / 2.0 - tol) {
            return true;
        }
        self.objects
            .iter()
            .enumerate()
            .any(|(j, o)| Some(j) != own && o.contains(p, tol))
    }
}

/// One surface sample: point, outward unit normal.
type Sample = (DVec3, DVec3);

/// Jittered grid samples of a rectangle `origin + u·a + v·b`, `u ∈ [0, la]`, `v ∈ [0, lb]`
/// (`a`, `b` unit), normal `n`, step `s`.
fn rect(
    origin: DVec3,
    (a, la): (DVec3, f64),
    (b, lb): (DVec3, f64),
    n: DVec3,
    s: f64,
    rng: &mut SplitMix64,
) -> Vec<Sample> {
    let (nu, nv) = (
        (la / s).ceil().max(1.0) as usize,
        (lb / s).ceil().max(1.0) as usize,
    );
    let mut out = Vec::with_capacity(nu * nv);
    for i in 0..nu {
        for j in 0..nv {
            let u = la * (i as f64 + rng.next_f64()) / nu as f64;
            let v = lb * (j as f64 + rng.next_f64()) / nv as f64;
            out.push((origin + a * u + b * v, n));
        }
    }
    out
}

/// The surface samples of one object at step `s` (boxes: top and four sides; cylinders: side
/// and top; spheres: a Fibonacci lattice).
fn object_samples(o: &RoomObject, s: f64, rng: &mut SplitMix64) -> Vec<Sample> {
    let b = o.aabb();
    let (lo, hi) = (DVec3::from(b[0]), DVec3::from(b[1]));
    let d = hi - lo;
    let (x, y, z) = (DVec3::X, DVec3::Y, DVec3::Z);
    match o.shape {
        Shape::Box => [
            rect(DVec3::new(lo.x, lo.y, hi.z), (x, d.x), (y, d.y), z, s, rng),
            rect(lo, (y, d.y), (z, d.z), -x, s, rng),
            rect(DVec3::new(hi.x, lo.y, lo.z), (y, d.y), (z, d.z), x, s, rng),
            rect(lo, (x, d.x), (z, d.z), -y, s, rng),
            rect(DVec3::new(lo.x, hi.y, lo.z), (x, d.x), (z, d.z), y, s, rng),
        ]
        .concat(),
        Shape::Cylinder => {
            let r = o.size[0] / 2.0;
            let c = DVec3::new(o.center[0], o.center[1], 0.0);
            let side = rect(
                DVec3::ZERO,
                (x, std::f64::consts::TAU * r),
                (z, d.z),
                z,
                s,
                rng,
            )
            .into_iter()
            .map(|(p, _)| {
                let a = p.x / r;
                let n = DVec3::new(a.cos(), a.sin(), 0.0);
                (c + n * r + z * p.z, n)
            });
            let top = rect(DVec3::new(lo.x, lo.y, hi.z), (x, d.x), (y, d.y), z, s, rng)
                .into_iter()
                .filter(|(p, _)| (p.x - c.x).powi(2) + (p.y - c.y).powi(2) <= r * r);
            side.chain(top).collect()
        }
        Shape::Sphere => {
            let r = o.size[0] / 2.0;
            let c = o.sphere_centre();
            let count = ((4.0 * std::f64::consts::PI * r * r) / (s * s))
                .ceil()
                .max(4.0) as usize;
            let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
            (0..count)
                .map(|i| {
                    let zc = 1.0 - 2.0 * (i as f64 + 0.5) / count as f64;
                    let rho = (1.0 - zc * zc).sqrt();
                    let a = golden * i as f64;
                    let n = DVec3::new(rho * a.cos(), rho * a.sin(), zc);
                    (c + n * r, n)
                })
                .collect()
        }
    }
}

/// Surface area of an object's sampled surfaces.
fn object_area(o: &RoomObject) -> f64 {
    let [sx, sy, sz] = o.size;
    match o.shape {
        Shape::Box => sx * sy + 2.0 * (sx + sy) * sz,
        Shape::Cylinder => {
            let r = sx / 2.0;
            std::f64::consts::PI * r * r + std::f64::consts::TAU * r * sz
        }
        Shape::Sphere => std::f64::consts::PI * sx * sx,
    }
}

/// Per-Gaussian truth: runs over the `.ply` vertex order.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct GaussianTruth {
    /// Class names, indexed by `class` (color-clip's order).
    pub classes: Vec<String>,
    /// Gaussians in the scene.
    pub gaussians: usize,
    /// Consecutive runs, covering `0..gaussians` in order.
    pub runs: Vec<TruthRun>,
}

/// One run of Gaussians of one class and object.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TruthRun {
    /// `[start, end)` in vertex order.
    pub gaussians: [usize; 2],
    /// Class (index into [`GaussianTruth::classes`]).
    pub class: usize,
    /// Object index (into `objects.json`); `None` for the floor and the walls.
    pub object: Option<usize>,
}

impl GaussianTruth {
    /// The file name beside `point_cloud.ply`.
    pub const FILE_NAME: &'static str = "truth.json";

    /// Reads `dir/truth.json`.
    ///
    /// Errors: I/O; a file that is not this list or whose runs do not cover the Gaussians in
    /// order ([`Error::Invalid`]: write the scene again with `synth-scene --room`).
    pub fn read(dir: &Path) -> Result<GaussianTruth> {
        let path = dir.join(Self::FILE_NAME);
        let bytes = std::fs::read(&path).map_err(|e| Error::io(&path, e))?;
        let bad = |why: String| {
            Error::Invalid(format!(
                "{} {why}; write the scene with `synth-scene --objects K --room`",
                path.display()
            ))
        };
        let t: GaussianTruth = serde_json::from_slice(&bytes)
            .map_err(|e| bad(format!("is not the per-Gaussian truth ({e})")))?;
        let mut next = 0;
        for r in &t.runs {
            if r.gaussians[0] != next || r.gaussians[1] < next || r.class >= t.classes.len() {
                return Err(bad(format!("has a run {:?} out of order", r.gaussians)));
            }
            next = r.gaussians[1];
        }
        if next != t.gaussians {
            return Err(bad(format!("covers {next} of {} Gaussians", t.gaussians)));
        }
        Ok(t)
    }

    /// Each Gaussian's class, vertex order.
    pub fn classes_per_gaussian(&self) -> Vec<u8> {
        let mut out = vec![0u8; self.gaussians];
        for r in &self.runs {
            out[r.gaussians[0]..r.gaussians[1]].fill(r.class as u8);
        }
        out
    }
}

/// The room's Gaussians and the runs of its truth (floor, walls, each object).
fn room_gaussians(room: &Room<'_>, p: &SyntheticSceneParams) -> (Gaussians, GaussianTruth) {
    let (e, h) = (room.extent, room.wall);
    let area = e * e + 4.0 * e * h + room.objects.iter().map(object_area).sum::<f64>();
    let s = (area / p.gaussians.max(1) as f64).sqrt();
    let mut rng = SplitMix64::new(p.seed ^ 0x005E_ED0F_F100_u64);
    let parts = surface_samples(room, s, &mut rng);
    let (g, runs) = splat_samples(room, parts, s, &mut rng);
    let truth = GaussianTruth {
        classes: COLOUR_NAMES.iter().map(|s| s.to_string()).collect(),
        gaussians: g.means.len(),
        runs,
    };
    (g, truth)
}

/// Points and outward normals on the room's floor, its four walls and each object, about `s`
/// metres apart, drawn from `rng` in that order.
fn surface_samples(room: &Room<'_>, s: f64, rng: &mut SplitMix64) -> Vec<(Surface, Vec<Sample>)> {
    let (e, h) = (room.extent, room.wall);
    let half = e / 2.0;
    let (x, y, z) = (DVec3::X, DVec3::Y, DVec3::Z);
    let floor = rect(DVec3::new(-half, -half, 0.0), (x, e), (y, e), z, s, rng);
    let walls = [
        rect(DVec3::new(-half, -half, 0.0), (y, e), (z, h), x, s, rng),
        rect(DVec3::new(half, -half, 0.0), (y, e), (z, h), -x, s, rng),
        rect(DVec3::new(-half, -half, 0.0), (x, e), (z, h), y, s, rng),
        rect(DVec3::new(-half, half, 0.0), (x, e), (z, h), -y, s, rng),
    ]
    .concat();
    let mut parts = vec![(Surface::Floor, floor), (Surface::Wall, walls)];
    for (k, o) in room.objects.iter().enumerate() {
        parts.push((Surface::Object(k), object_samples(o, s, rng)));
    }
    parts
}

/// One flat Gaussian per sample of `parts` that no object hides: a disc of about `s` metres
/// facing the sample's normal, its surface's colour as SH DC. Returns the Gaussians and one
/// truth run per surface, in order.
fn splat_samples(
    room: &Room<'_>,
    parts: Vec<(Surface, Vec<Sample>)>,
    s: f64,
    rng: &mut SplitMix64,
) -> (Gaussians, Vec<TruthRun>) {
    const SH_C0: f64 = 0.282_094_791_773_878_14;
    let mut g = Gaussians {
        means: Vec::new(),
        scales: Vec::new(),
        rotations: Vec::new(),
        opacities: Vec::new(),
        sh: None,
    };
    let mut dc = Vec::new();
    let mut runs = Vec::new();
    for (surface, samples) in parts {
        let start = g.means.len();
        for (m, n) in samples {
            if room.hidden(surface, m) {
                continue;
            }
            let size = s * (0.6 + 0.8 * rng.next_f64());
            let spin = DQuat::from_rotation_z(rng.next_f64() * std::f64::consts::PI);
            let q = (DQuat::from_rotation_arc(DVec3::Z, n) * spin).normalize();
            let jitter = 0.9 + 0.2 * rng.next_f64();
            let rgb = room.colour(surface, m, n);
            g.means.push(m.as_vec3().to_array());
            g.scales
                .push([size as f32, size as f32, (size * 0.1) as f32]);
            g.rotations
                .push([q.w as f32, q.x as f32, q.y as f32, q.z as f32]);
            g.opacities.push((0.6 + 0.35 * rng.next_f64()) as f32);
            dc.extend(rgb.map(|c| (((c * jitter).min(1.0) - 0.5) / SH_C0) as f32));
        }
        let (class, object) = match surface {
            Surface::Floor => (FLOOR_CLASS, None),
            Surface::Wall => (WALL_CLASS, None),
            Surface::Object(k) => (room.objects[k].class, Some(k)),
        };
        runs.push(TruthRun {
            gaussians: [start, g.means.len()],
            class,
            object,
        });
    }
    g.sh = Some(ShCoeffs {
        degree: 0,
        coeffs: dc,
    });
    (g, runs)
}

/// Nearest hit of the ray `c + t·d` (t > 0) with an object: distance, object, outward normal.
fn hit_object(room: &Room<'_>, c: DVec3, d: DVec3) -> Option<(f64, usize, DVec3)> {
    let mut best: Option<(f64, usize, DVec3)> = None;
    for (k, o) in room.objects.iter().enumerate() {
        let hit = match o.shape {
            Shape::Box => ray_box(c, d, &o.aabb()).map(|t| {
                let p = c + d * t;
                let b = o.aabb();
                let mut n = DVec3::ZERO;
                let mut best_gap = f64::INFINITY;
                for a in 0..3 {
                    for (side, sign) in [(0, -1.0), (1, 1.0)] {
                        let gap = (p[a] - b[side][a]).abs();
                        if gap < best_gap {
                            best_gap = gap;
                            n = DVec3::ZERO;
                            n[a] = sign;
                        }
                    }
                }
                (t, n)
            }),
            Shape::Sphere => {
                let (centre, r) = (o.sphere_centre(), o.size[0] / 2.0);
                let oc = c - centre;
                let (bq, cq) = (oc.dot(d), oc.length_squared() - r * r);
                let disc = bq * bq - d.length_squared() * cq;
                (disc >= 0.0).then(|| {
                    let t = (-bq - disc.sqrt()) / d.length_squared();
                    (t, ((c + d * t) - centre) / r)
                })
            }
            Shape::Cylinder => ray_cylinder(o, c, d),
        };
        if let Some((t, n)) = hit.filter(|h| h.0 > 0.0)
            && best.is_none_or(|b| t < b.0)
        {
            best = Some((t, k, n));
        }
    }
    best
}

/// The ray's first hit with a vertical cylinder's side or top (the base is on the floor).
fn ray_cylinder(o: &RoomObject, c: DVec3, d: DVec3) -> Option<(f64, DVec3)> {
    let (r, h) = (o.size[0] / 2.0, o.size[2]);
    let (ox, oy) = (c.x - o.center[0], c.y - o.center[1]);
    let mut best: Option<(f64, DVec3)> = None;
    let a = d.x * d.x + d.y * d.y;
    if a > 1e-15 {
        let b = ox * d.x + oy * d.y;
        let disc = b * b - a * (ox * ox + oy * oy - r * r);
        if disc >= 0.0 {
            let t = (-b - disc.sqrt()) / a;
            let z = c.z + d.z * t;
            if t > 0.0 && (0.0..=h).contains(&z) {
                let n = DVec3::new(ox + d.x * t, oy + d.y * t, 0.0) / r;
                best = Some((t, n));
            }
        }
    }
    if d.z.abs() > 1e-15 {
        let t = (h - c.z) / d.z;
        let (px, py) = (ox + d.x * t, oy + d.y * t);
        if t > 0.0 && px * px + py * py <= r * r && best.is_none_or(|b| t < b.0) {
            best = Some((t, DVec3::Z));
        }
    }
    best
}

/// The first hit of the ray with the floor or a wall, inside the room: distance, surface,
/// inward normal.
fn hit_room(room: &Room<'_>, c: DVec3, d: DVec3) -> Option<(f64, Surface, DVec3)> {
    let half = room.extent / 2.0;
    let mut best: Option<(f64, Surface, DVec3)> = None;
    let mut consider = |t: f64, s: Surface, n: DVec3| {
        let p = c + d * t;
        let inside = p.x.abs() <= half + 1e-9
            && p.y.abs() <= half + 1e-9
            && p.z >= -1e-9
            && p.z <= room.wall + 1e-9;
        if t > 0.0 && inside && best.is_none_or(|b| t < b.0) {
            best = Some((t, s, n));
        }
    };
    if d.z.abs() > 1e-15 {
        consider(-c.z / d.z, Surface::Floor, DVec3::Z);
    }
    for a in 0..2 {
        if d[a].abs() > 1e-15 {
            for sign in [-1.0, 1.0] {
                let mut n = DVec3::ZERO;
                n[a] = -sign;
                consider((sign * half - c[a]) / d[a], Surface::Wall, n);
            }
        }
    }
    best
}

/// The photo of view `i`: every pixel ray-cast against the objects, floor and walls, coloured
/// with the texture at the hit point; rays that leave the room over the walls see white.
fn render_room(i: usize, p: &SyntheticSceneParams, room: &Room<'_>) -> image::RgbImage {
    render_rays(i, p, |c, d| {
        let obj = hit_object(room, c, d);
        let wall = hit_room(room, c, d);
        match (obj, wall) {
            (Some((t, k, n)), w) if w.is_none_or(|w| t <= w.0) => {
                room.colour(Surface::Object(k), c + d * t, n)
            }
            (_, Some((t, s, n))) => room.colour(s, c + d * t, n),
            _ => [1.0; 3],
        }
    })
}

/// Writes the room scene (module doc) at `dir`: `point_cloud.ply`, `objects.json`,
/// `truth.json`, `images/view_XXXX.png` and `sparse/0/*.txt` (`images.txt` last: a folder
/// without it is incomplete). `p.extent` is the room's side, `p.gaussians` the number aimed at
/// (the hidden samples are left out, so a few fewer are written).
///
/// Errors: as [`crate::synthetic::write_synthetic_scene`]; [`Error::Param`] naming a texture
/// field outside its domain.
pub fn write_room_scene(
    dir: &Path,
    p: &SyntheticSceneParams,
    objects: &[RoomObject],
    texture: &Texture,
) -> Result<SyntheticSummary> {
    check_params(p)?;
    texture.check()?;
    let folders = SceneFolders::create(dir)?;
    let room = Room {
        extent: p.extent,
        wall: p.extent / 4.0,
        objects,
        texture: *texture,
        seed: p.seed,
    };
    let (g, truth) = room_gaussians(&room, p);
    let ply = dir.join("point_cloud.ply");
    write_ply(&ply, &g)?;
    let listed: Vec<serde_json::Value> = objects
        .iter()
        .enumerate()
        .map(|(k, o)| {
            let r = truth.runs.iter().find(|r| r.object == Some(k));
            let range = r.map_or([0, 0], |r| r.gaussians);
            serde_json::json!({
                "class": o.class, "colour": o.class, "name": o.name, "shape": o.shape,
                "center": o.center, "size": o.size, "aabb": o.aabb(), "gaussians": range,
                "stripe_class": o.stripe_class,
            })
        })
        .collect();
    write_file(&dir.join("objects.json"), &pretty(&listed)?)?;
    write_file(&dir.join(GaussianTruth::FILE_NAME), &pretty(&truth)?)?;
    folders.finish(p, &ply, g.len(), |i| render_room(i, p, &room))
}

/// Pretty JSON of the truth files the room writes.
fn pretty<T: serde::Serialize>(v: &T) -> Result<Vec<u8>> {
    serde_json::to_vec_pretty(v).map_err(|e| Error::internal(format!("scene truth JSON: {e}")))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn params(seed: u64) -> SyntheticSceneParams {
        SyntheticSceneParams {
            gaussians: 12_000,
            views: 2,
            width: 96,
            height: 72,
            extent: 6.0,
            seed,
            ..Default::default()
        }
    }

    #[test]
    #[allow(clippy::needless_range_loop)] // one index into the truth, the means and the colours
    fn the_room_is_written_with_its_truth_and_textured_objects() {
        let dir = tempfile::tempdir().unwrap();
        let p = params(3);
        let objects = room_layout(MAX_ROOM_OBJECTS, p.extent).unwrap();
        // Without shading (a face turned away from the light may take a neighbouring class's
        // shade, e.g. dark yellow is nearest orange): speckles and stripes only.
        let tex = Texture {
            shading: 0.0,
            ..Texture::for_extent(p.extent)
        };
        let s = write_room_scene(dir.path(), &p, &objects, &tex).unwrap();
        let truth = GaussianTruth::read(dir.path()).unwrap();
        assert_eq!(truth.gaussians, s.gaussians);
        assert!(
            s.gaussians > 10_000 && s.gaussians <= 13_000,
            "{}",
            s.gaussians
        );
        let g = slag_common::scene::load_ply(
            &dir.path().join("point_cloud.ply"),
            slag_common::scene::PlyLoadOptions { colours: true },
        )
        .unwrap();
        assert_eq!(g.len(), s.gaussians);
        let classes = truth.classes_per_gaussian();
        let sh = g.sh.as_ref().unwrap();
        // Every object has Gaussians within its box; mostly its class colour, some others.
        for (k, o) in objects.iter().enumerate() {
            let run = truth.runs.iter().find(|r| r.object == Some(k)).unwrap();
            let [a, b] = run.gaussians;
            assert!(b - a > 30, "object {k}: {} Gaussians", b - a);
            let bx = o.aabb();
            let (mut own, mut other) = (0, 0);
            for i in a..b {
                assert_eq!(classes[i] as usize, o.class);
                let m = g.means[i];
                for ax in 0..3 {
                    let v = f64::from(m[ax]);
                    assert!(v >= bx[0][ax] - 1e-3 && v <= bx[1][ax] + 1e-3, "{k} {m:?}");
                }
                let rgb = sh.dc(i).map(|c| 0.5 + 0.282_094_8 * c);
                let near = |c: usize| {
                    (0..3)
                        .map(|ch| (rgb[ch] - PALETTE[c][ch]).powi(2))
                        .sum::<f32>()
                };
                let best = (0..PALETTE.len())
                    .min_by(|&x, &y| near(x).total_cmp(&near(y)))
                    .unwrap();
                if best == o.class {
                    own += 1;
                } else {
                    other += 1;
                }
            }
            assert!(own > other, "object {k}: {own} own colour, {other} other");
            assert!(other > 0, "object {k} is untextured");
        }
        // Touching objects share no Gaussians inside each other.
        let cyl = truth.runs.iter().find(|r| r.object == Some(1)).unwrap();
        for i in cyl.gaussians[0]..cyl.gaussians[1] {
            let m = DVec3::from(g.means[i].map(f64::from));
            assert!(!objects[0].contains(m, 1e-6 * p.extent));
        }
        // objects.json is the list eval-objects reads; the same seed writes the same scene.
        let listed: serde_json::Value =
            serde_json::from_slice(&std::fs::read(dir.path().join("objects.json")).unwrap())
                .unwrap();
        assert_eq!(listed.as_array().unwrap().len(), MAX_ROOM_OBJECTS);
        assert_eq!(listed[1]["shape"], "cylinder");
        let again = tempfile::tempdir().unwrap();
        write_room_scene(again.path(), &p, &objects, &tex).unwrap();
        let read = |d: &Path| std::fs::read(d.join("point_cloud.ply")).unwrap();
        assert_eq!(read(dir.path()), read(again.path()));
        let img = image::open(dir.path().join("images/view_0000.png")).unwrap();
        assert_eq!((img.width(), img.height()), (96, 72));
    }

    #[test]
    fn bad_texture_and_counts_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let p = params(1);
        let objects = room_layout(2, p.extent).unwrap();
        let mut tex = Texture::for_extent(p.extent);
        tex.speckles = 1.5;
        assert!(matches!(
            write_room_scene(dir.path(), &p, &objects, &tex),
            Err(Error::Param {
                name: "speckles",
                ..
            })
        ));
        assert!(room_layout(0, 6.0).is_err());
        assert!(room_layout(MAX_ROOM_OBJECTS + 1, 6.0).is_err());
    }
}
