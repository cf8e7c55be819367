//! Showing an answer to a person: the loaded Gaussians as a 3DGS `.ply` with the matches painted,
//! and a small web page that renders it with a Gaussian-splat viewer.
//!
//! - [`DisplayAttrs`]: the display columns of every loaded Gaussian (log-scales, pre-sigmoid
//!   opacities, normalised rotations (w, x, y, z), SH DC), rows in the scan store's order (shards
//!   in manifest tile order, rows in shard order, as [`crate::engine::Engine::load`] pushes them);
//! - [`highlighted_ply`]: a binary little-endian INRIA-layout `.ply` of them, matches in a flat
//!   highlight colour, the rest optionally dimmed;
//! - the HTTP side (`GET /query.ply`, the page, its script and the viewer) is
//!   [`crate::serve::web`]; this module knows nothing of HTTP.
//!

use std::collections::HashSet;

use slag_common::scene::SH_C0;
use slag_common::shards::{DisplaySlices, MixtureShard, StoredShard};
use slag_common::{Error, Result};

/// Highlight colour of matches when none is given: magenta (linear display RGB in 0..1).
pub const DEFAULT_HIGHLIGHT: [f32; 3] = [1.0, 0.0, 1.0];
/// Pre-sigmoid opacity given to Gaussians whose shard has no opacities: `logit(0.95)`.
pub const FALLBACK_LOGIT_OPACITY: f32 = 2.944_439;
/// Isotropic standard deviation of Gaussians whose shard has no scales, as a fraction of the
/// diagonal of the loaded means' bounding box (0.01 scene units when that box is degenerate).
pub const FALLBACK_SCALE_FRACTION: f32 = 0.002;

const HAS_SCALES: u8 = 1;
const HAS_OPACITY: u8 = 2;
const HAS_ROTATION: u8 = 4;
const HAS_DC: u8 = 8;

/// Display columns of every loaded Gaussian, rows in the order of the scan store
/// ([`crate::scan::VectorStore`]); all values in the INRIA `.ply` storage convention.
///
/// Gaussians whose shard lacks a column get a fallback when written ([`highlighted_ply`]): a
/// small isotropic scale ([`FALLBACK_SCALE_FRACTION`] of the scene diagonal), the identity
/// rotation, opacity `sigmoid(`[`FALLBACK_LOGIT_OPACITY`]`)` = 0.95 and mid gray (`f_dc = 0`,
/// RGB 0.5).
#[derive(Debug, Clone, Default)]
pub struct DisplayAttrs {
    ids: Vec<u32>,
    means: Vec<[f32; 3]>,
    log_scales: Vec<[f32; 3]>,
    logit_opacities: Vec<f32>,
    rotations: Vec<[f32; 4]>,
    sh_dc: Vec<[f32; 3]>,
    present: Vec<u8>,
}

/// A decoded shard whose rows [`DisplayAttrs::push_shard`] reads: dense ([`StoredShard`]) and
/// mixture ([`MixtureShard`]) shards alike.
pub trait ShardDisplay {
    /// Ids `[N]`, means `[N]` (world frame) and the display sections.
    fn display_rows(&self) -> (&[u32], &[[f32; 3]], DisplaySlices<'_>);
}

impl ShardDisplay for StoredShard {
    fn display_rows(&self) -> (&[u32], &[[f32; 3]], DisplaySlices<'_>) {
        (&self.ids, &self.means, self.display())
    }
}

impl ShardDisplay for MixtureShard {
    fn display_rows(&self) -> (&[u32], &[[f32; 3]], DisplaySlices<'_>) {
        (&self.ids, &self.means, self.display())
    }
}

impl DisplayAttrs {
    /// No Gaussians.
    pub fn new() -> Self {
        Self::default()
    }

    /// Appends the rows of one shard, dense or mixture (call in the order the shards are pushed
    /// into the scan store). Columns of the wrong length (not produced by
    /// [`slag_common::shards::decode_shard`]) are treated as absent.
    pub fn push_shard(&mut self, s: &impl ShardDisplay) {
        let (ids, means, display) = s.display_rows();
        let DisplaySlices {
            scales,
            opacities,
            rotations,
            sh_dc,
        } = display;
        let n = ids.len().min(means.len());
        let ok = |len: usize| len == n;
        let scales = scales.filter(|v| ok(v.len()));
        let opac = opacities.filter(|v| ok(v.len()));
        let rot = rotations.filter(|v| ok(v.len()));
        let dc = sh_dc.filter(|v| ok(v.len()));
        let flags = scales.map_or(0, |_| HAS_SCALES)
            | opac.map_or(0, |_| HAS_OPACITY)
            | rot.map_or(0, |_| HAS_ROTATION)
            | dc.map_or(0, |_| HAS_DC);
        self.ids.extend_from_slice(&ids[..n]);
        self.means.extend_from_slice(&means[..n]);
        for i in 0..n {
            self.log_scales.push(scales.map_or([0.0; 3], |v| v[i]));
            self.logit_opacities
                .push(opac.map_or(FALLBACK_LOGIT_OPACITY, |v| v[i]));
            self.rotations
                .push(rot.map_or([1.0, 0.0, 0.0, 0.0], |v| v[i]));
            self.sh_dc.push(dc.map_or([0.0; 3], |v| v[i]));
            self.present.push(flags);
        }
    }

    /// Builds the columns of `shards` in order.
    pub fn from_shards<'a>(shards: impl IntoIterator<Item = &'a StoredShard>) -> Self {
        let mut d = Self::new();
        for s in shards {
            d.push_shard(s);
        }
        d
    }

    /// Number of Gaussians (rows).
    pub fn len(&self) -> usize {
        self.ids.len()
    }

    /// True without Gaussians.
    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }

    /// Source-`.ply` ids of the rows `[N]`.
    pub fn ids(&self) -> &[u32] {
        &self.ids
    }

    /// Opacity of row `row` in 0..1, the sigmoid of its stored pre-sigmoid opacity; `None` when
    /// its shard carried no opacities (or `row` is out of range).
    pub fn opacity(&self, row: usize) -> Option<f32> {
        let f = *self.present.get(row)?;
        (f & HAS_OPACITY != 0).then(|| 1.0 / (1.0 + (-self.logit_opacities[row]).exp()))
    }

    /// Rows whose shard carried all four display columns (scales, opacities, rotations, SH DC).
    pub fn complete(&self) -> usize {
        self.present.iter().filter(|&&f| f == 0b1111).count()
    }

    /// Bytes held (for `/stats`-style accounting).
    pub fn memory_bytes(&self) -> usize {
        self.len() * (4 + 12 + 12 + 4 + 16 + 12 + 1)
    }

    /// Log of the fallback isotropic scale: [`FALLBACK_SCALE_FRACTION`] of the means' diagonal.
    fn fallback_log_scale(&self) -> f32 {
        let b = slag_common::shards::Aabb::of_points(self.means.iter().copied());
        let diag = b
            .map(|b| {
                (0..3)
                    .map(|a| ((b.max[a] - b.min[a]) as f64).powi(2))
                    .sum::<f64>()
                    .sqrt()
            })
            .unwrap_or(0.0);
        let s = if diag.is_finite() && diag > 1e-9 {
            diag * FALLBACK_SCALE_FRACTION as f64
        } else {
            0.01
        };
        s.ln() as f32
    }
}

/// How matches and the rest are painted by [`highlighted_ply`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HighlightStyle {
    /// Flat colour of the matches, linear display RGB in 0..1 (written as
    /// `f_dc = (rgb - 0.5) / SH_C0`, the INRIA/gsplat DC convention).
    pub colour: [f32; 3],
    /// When `Some(f)` (0..=1), every other Gaussian's DC colour is scaled towards black:
    /// `rgb' = f * (0.5 + SH_C0 * f_dc)`.
    pub dim: Option<f32>,
}

impl Default for HighlightStyle {
    fn default() -> Self {
        HighlightStyle {
            colour: DEFAULT_HIGHLIGHT,
            dim: None,
        }
    }
}

/// `f_dc` of a display RGB colour: `(rgb - 0.5) / SH_C0`.
pub fn dc_of_rgb(rgb: [f32; 3]) -> [f32; 3] {
    rgb.map(|c| ((c as f64 - 0.5) / SH_C0) as f32)
}

/// The `.ply` property names written by [`highlighted_ply`], in order (all `float`).
pub const PLY_PROPERTIES: [&str; 14] = [
    "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
    "rot_0", "rot_1", "rot_2", "rot_3",
];

/// Every Gaussian of `attrs` as a binary little-endian INRIA-layout 3DGS `.ply`
/// (`float` properties [`PLY_PROPERTIES`]: means (world frame), SH DC, pre-sigmoid opacity,
/// log-scales, rotation (w, x, y, z); SH degree 0, no normals), which 3DGS viewers and
/// [`slag_common::scene::load_ply`] read. Rows whose id is in `highlighted` get
/// `style.colour`; the others keep their colour, dimmed by `style.dim`. Missing columns get the
/// fallbacks documented on [`DisplayAttrs`].
///
/// Errors ([`Error::Query`] `color` / `dim`): a non-finite or out-of-range colour or dim factor.
pub fn highlighted_ply(
    attrs: &DisplayAttrs,
    highlighted: &HashSet<u32>,
    style: &HighlightStyle,
) -> Result<Vec<u8>> {
    highlighted_ply_framed(attrs, highlighted, style, None)
}

/// Hamilton product `a ⊗ b` of quaternions `(w, x, y, z)`.
fn quat_mul(a: [f64; 4], b: [f64; 4]) -> [f64; 4] {
    [
        a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
        a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
        a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
        a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
    ]
}

/// [`highlighted_ply`] in the robot's map frame when `to_map` is given: each Gaussian is moved
/// by the scene-to-map similarity (mean `s·R·x + t`, log-scales `+ ln s`, rotation `q_R ⊗ q`), so
/// the `.ply` overlays the robot's map. `None`: the scene frame, as stored.
///
/// Errors: as [`highlighted_ply`].
pub fn highlighted_ply_framed(
    attrs: &DisplayAttrs,
    highlighted: &HashSet<u32>,
    style: &HighlightStyle,
    to_map: Option<&slag_common::shards::SceneToMap>,
) -> Result<Vec<u8>> {
    painted_ply_framed(
        attrs,
        &|id| highlighted.contains(&id).then_some(style.colour),
        style,
        to_map,
    )
}

/// Distinct colours of objects in [`object_colour`] (linear display RGB in 0..1; no magenta,
/// the colour of matches outside any object).
pub const OBJECT_PALETTE: [[f32; 3]; 10] = [
    [0.12, 0.47, 0.71],
    [1.0, 0.5, 0.05],
    [0.17, 0.63, 0.17],
    [0.84, 0.15, 0.16],
    [0.58, 0.4, 0.74],
    [0.55, 0.34, 0.29],
    [0.09, 0.75, 0.81],
    [0.74, 0.74, 0.13],
    [1.0, 1.0, 1.0],
    [0.0, 0.3, 1.0],
];

/// The colour of the `k`-th object of an answer: [`OBJECT_PALETTE`] in order, repeating after
/// ten objects (the web page labels its boxes with the same colours).
pub fn object_colour(k: usize) -> [f32; 3] {
    OBJECT_PALETTE[k % OBJECT_PALETTE.len()]
}

/// [`highlighted_ply_framed`] with a colour per Gaussian id: `paint(id)` = `Some(rgb)` paints
/// that Gaussian flat `rgb` (linear display RGB in 0..1), `None` keeps its colour, dimmed by
/// `style.dim` (`style.colour` is only validated here).
///
/// Errors: as [`highlighted_ply`]; [`Error::Query`] `color` for a painted colour outside 0..=1.
pub fn painted_ply_framed(
    attrs: &DisplayAttrs,
    paint: &dyn Fn(u32) -> Option<[f32; 3]>,
    style: &HighlightStyle,
    to_map: Option<&slag_common::shards::SceneToMap>,
) -> Result<Vec<u8>> {
    let frame = to_map.map(|t| (t, t.scale.ln() as f32, t.quaternion_wxyz()));
    check_style(style)?;
    let n = attrs.len();
    let mut bytes = slag_common::scene::float_vertex_header(
        n,
        &PLY_PROPERTIES,
        Some("slag-edge /query.ply: matches painted in a flat colour"),
    );
    bytes.reserve(n * PLY_PROPERTIES.len() * 4);
    let fallback_scale = attrs.fallback_log_scale();
    let mut put = |v: f32| bytes.extend_from_slice(&v.to_le_bytes());
    for i in 0..n {
        let f = attrs.present[i];
        let mean = match frame {
            Some((t, _, _)) => t.to_map_f32(attrs.means[i]),
            None => attrs.means[i],
        };
        mean.iter().for_each(|&v| put(v));
        painted_dc(paint(attrs.ids[i]), attrs.sh_dc[i], style.dim)?
            .iter()
            .for_each(|&v| put(v));
        put(attrs.logit_opacities[i]);
        let s = if f & HAS_SCALES != 0 {
            attrs.log_scales[i]
        } else {
            [fallback_scale; 3]
        };
        match frame {
            Some((_, ln_s, q_r)) => {
                s.iter().for_each(|&v| put(v + ln_s));
                quat_mul(q_r, attrs.rotations[i].map(f64::from))
                    .iter()
                    .for_each(|&v| put(v as f32));
            }
            None => {
                s.iter().for_each(|&v| put(v));
                attrs.rotations[i].iter().for_each(|&v| put(v));
            }
        }
    }
    Ok(bytes)
}

/// Refuses a highlight style whose colour is not RGB in 0..=1 ([`Error::Query`] `color`) or
/// whose dim factor is not in 0..=1 ([`Error::Query`] `dim`).
fn check_style(style: &HighlightStyle) -> Result<()> {
    if !unit_rgb(&style.colour) {
        return Err(Error::query(
            "color",
            format!(
                "highlight colour {:?}: use RGB components in 0..=1",
                style.colour
            ),
        ));
    }
    if let Some(f) = style.dim
        && !(f.is_finite() && (0.0..=1.0).contains(&f))
    {
        return Err(Error::query(
            "dim",
            format!("dim {f}: use a factor in 0..=1"),
        ));
    }
    Ok(())
}

/// Whether every component of `rgb` is a finite number in 0..=1.
fn unit_rgb(rgb: &[f32; 3]) -> bool {
    rgb.iter().all(|c| c.is_finite() && (0.0..=1.0).contains(c))
}

/// A Gaussian's SH DC in a painted PLY: `painted` (linear display RGB in 0..1) as DC, else its
/// own `dc`, its colour scaled by `dim` when given.
///
/// Errors: a painted colour outside 0..=1 ([`Error::Query`] `color`).
fn painted_dc(painted: Option<[f32; 3]>, dc: [f32; 3], dim: Option<f32>) -> Result<[f32; 3]> {
    if let Some(rgb) = painted {
        if !unit_rgb(&rgb) {
            return Err(Error::query(
                "color",
                format!("paint colour {rgb:?}: use RGB components in 0..=1"),
            ));
        }
        return Ok(dc_of_rgb(rgb));
    }
    Ok(match dim {
        Some(k) => dc.map(|c| {
            let rgb = 0.5 + SH_C0 * c as f64;
            ((k as f64 * rgb - 0.5) / SH_C0) as f32
        }),
        None => dc,
    })
}

/// Parses a colour `RRGGBB` or `#RRGGBB` (hex, sRGB bytes mapped to 0..1).
///
/// Errors: anything else ([`Error::Query`] `color`).
pub fn parse_colour(s: &str) -> Result<[f32; 3]> {
    let h = s.trim().trim_start_matches('#');
    let bad = || Error::query("color", format!("color {s:?}: use RRGGBB hex, e.g. ff00ff"));
    if h.len() != 6 || !h.is_ascii() {
        return Err(bad());
    }
    let mut rgb = [0f32; 3];
    for (k, c) in rgb.iter_mut().enumerate() {
        let v = u8::from_str_radix(&h[2 * k..2 * k + 2], 16).map_err(|_| bad())?;
        *c = v as f32 / 255.0;
    }
    Ok(rgb)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use slag_common::scene::{PlyLoadOptions, load_ply};
    use slag_common::shards::{Dtype, ShardHeader, StoredVectors};

    fn shard(ids: Vec<u32>, display: bool) -> StoredShard {
        let n = ids.len();
        let means: Vec<[f32; 3]> = ids
            .iter()
            .map(|&i| [i as f32, 2.0 * i as f32, -1.0])
            .collect();
        let q = |i: usize| {
            let v = [1.0 + i as f32, 0.2, -0.3, 0.1 * i as f32];
            let l = v.iter().map(|x| x * x).sum::<f32>().sqrt();
            v.map(|x| x / l)
        };
        StoredShard {
            header: ShardHeader {
                version: 1,
                scene_id: "s".into(),
                model: "m".into(),
                dim: 1,
                dtype: Dtype::F32,
                count: n as u32,
                aabb: Default::default(),
                tile_id: 0,
            },
            means,
            vectors: StoredVectors::F32(vec![1.0; n]),
            scales: display.then(|| {
                (0..n)
                    .map(|i| [-3.0, -2.5, -4.0 + i as f32 * 0.1])
                    .collect()
            }),
            opacities: display.then(|| (0..n).map(|i| -1.0 + i as f32 * 0.5).collect()),
            rotations: display.then(|| (0..n).map(q).collect()),
            sh_dc: display.then(|| (0..n).map(|i| [0.1 * i as f32, -0.4, 0.9]).collect()),
            segments: None,
            ids,
        }
    }

    #[test]
    fn ply_round_trips_through_load_ply_with_highlight_and_fallbacks() {
        let a = shard(vec![10, 11, 12], true);
        let b = shard(vec![40, 41], false);
        let attrs = DisplayAttrs::from_shards([&a, &b]);
        assert_eq!((attrs.len(), attrs.complete()), (5, 3));
        let hl: HashSet<u32> = [11, 41].into_iter().collect();
        let style = HighlightStyle {
            colour: [1.0, 0.0, 1.0],
            dim: Some(0.5),
        };
        let bytes = highlighted_ply(&attrs, &hl, &style).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("q.ply");
        std::fs::write(&p, &bytes).unwrap();
        let g = load_ply(&p, PlyLoadOptions { colours: true }).unwrap();
        assert_eq!(g.len(), 5);
        let sh = g.sh.as_ref().unwrap();
        assert_eq!(sh.degree, 0);
        let rows: Vec<(&StoredShard, usize)> = (0..3)
            .map(|k| (&a, k))
            .chain((0..2).map(|k| (&b, k)))
            .collect();
        let fallback = (0.002f64 * (31f64.powi(2) + 62f64.powi(2)).sqrt()) as f32;
        for (i, (s, k)) in rows.into_iter().enumerate() {
            assert_eq!(g.means[i], s.means[k]);
            let rgb: Vec<f64> = (0..3).map(|c| 0.5 + SH_C0 * sh.dc(i)[c] as f64).collect();
            if hl.contains(&s.ids[k]) {
                for (c, want) in rgb.iter().zip([1.0, 0.0, 1.0]) {
                    assert!((c - want).abs() < 1e-6, "{rgb:?}");
                }
            } else {
                let src = s.sh_dc.as_ref().map_or([0.0; 3], |d| d[k]);
                for c in 0..3 {
                    let want = 0.5 * (0.5 + SH_C0 * src[c] as f64);
                    assert!((rgb[c] - want).abs() < 1e-5, "{rgb:?} vs {want}");
                }
            }
            match (&s.scales, &s.opacities, &s.rotations) {
                (Some(sc), Some(op), Some(rot)) => {
                    for (got, log) in g.scales[i].iter().zip(sc[k]) {
                        let want = log.exp();
                        assert!((got - want).abs() < 1e-6 * want.max(1.0));
                    }
                    let want = 1.0 / (1.0 + (-op[k]).exp());
                    assert!((g.opacities[i] - want).abs() < 1e-6);
                    for (got, want) in g.rotations[i].iter().zip(rot[k]) {
                        assert!((got - want).abs() < 1e-6);
                    }
                }
                _ => {
                    for ax in 0..3 {
                        assert!((g.scales[i][ax] - fallback).abs() < 1e-5 * fallback);
                    }
                    assert!((g.opacities[i] - 0.95).abs() < 1e-5);
                    assert_eq!(g.rotations[i], [1.0, 0.0, 0.0, 0.0]);
                }
            }
        }
    }

    #[test]
    fn bad_style_is_a_typed_error() {
        let attrs = DisplayAttrs::from_shards([&shard(vec![1], true)]);
        let none = HashSet::new();
        for style in [
            HighlightStyle {
                colour: [2.0, 0.0, 0.0],
                dim: None,
            },
            HighlightStyle {
                colour: [f32::NAN, 0.0, 0.0],
                dim: None,
            },
            HighlightStyle {
                colour: [1.0, 0.0, 0.0],
                dim: Some(1.5),
            },
        ] {
            assert!(matches!(
                highlighted_ply(&attrs, &none, &style),
                Err(Error::Query { .. })
            ));
        }
        assert_eq!(parse_colour("#ff8000").unwrap(), [1.0, 128.0 / 255.0, 0.0]);
        for bad in ["ff00", "zz0000", "ff00ff00", "é0000"] {
            assert!(parse_colour(bad).is_err(), "{bad}");
        }
    }
}
