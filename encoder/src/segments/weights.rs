//! The edge weights (module doc, "Graph and weights"): each Gaussian's normal, flatness and
//! size, and the weight of an edge from them and, with a masks' record, the mask term.

use rayon::prelude::*;
use slag_common::mask_record::MaskRecord;
use slag_common::scene::Gaussians;

use super::SegmentParams;

/// Per-Gaussian geometry the weights need.
pub(super) struct Geometry {
    normals: Vec<[f32; 3]>,
    flatness: Vec<f32>,
    pub(super) size: Vec<f32>,
}

pub(super) fn geometry(g: &Gaussians) -> Geometry {
    let per: Vec<([f32; 3], f32, f32)> = g
        .scales
        .par_iter()
        .zip(&g.rotations)
        .map(|(s, q)| {
            let mut order = [0usize, 1, 2];
            order.sort_by(|&a, &b| s[a].total_cmp(&s[b]).then(a.cmp(&b)));
            let (lo, mid, hi) = (s[order[0]], s[order[1]], s[order[2]]);
            let flat = if mid > 0.0 && lo.is_finite() && mid.is_finite() {
                (1.0 - lo / mid).clamp(0.0, 1.0)
            } else {
                0.0
            };
            (axis(q, order[0]), flat, hi.max(0.0))
        })
        .collect();
    Geometry {
        normals: per.iter().map(|p| p.0).collect(),
        flatness: per.iter().map(|p| p.1).collect(),
        size: per.iter().map(|p| p.2).collect(),
    }
}

impl Geometry {
    /// The same geometry with entry `r` that of Gaussian `perm[r]` (in parallel).
    pub(super) fn permuted(&self, perm: &[u32]) -> Geometry {
        let at = |v: &[f32]| perm.par_iter().map(|&i| v[i as usize]).collect();
        Geometry {
            normals: perm.par_iter().map(|&i| self.normals[i as usize]).collect(),
            flatness: at(&self.flatness),
            size: at(&self.size),
        }
    }
}

/// Column `a` of the rotation matrix of the quaternion `q` = (w, x, y, z), normalised first.
fn axis(q: &[f32; 4], a: usize) -> [f32; 3] {
    let n = q.iter().map(|v| v * v).sum::<f32>().sqrt();
    if !(n.is_finite() && n > 0.0) {
        let mut e = [0.0; 3];
        e[a] = 1.0;
        return e;
    }
    let (w, x, y, z) = (q[0] / n, q[1] / n, q[2] / n, q[3] / n);
    match a {
        0 => [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y + w * z),
            2.0 * (x * z - w * y),
        ],
        1 => [
            2.0 * (x * y - w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z + w * x),
        ],
        _ => [
            2.0 * (x * z + w * y),
            2.0 * (y * z - w * x),
            1.0 - 2.0 * (x * x + y * y),
        ],
    }
}

/// An undirected edge `(i, j)`, `i < j`, with its weight; ordered by `(w, i, j)` (weights are
/// ≥ 0, so their bit patterns order like the values).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, bytemuck::Zeroable)]
pub(super) struct Edge {
    pub(super) w: u32,
    pub(super) i: u32,
    pub(super) j: u32,
}

impl Edge {
    pub(super) fn weight(&self) -> f32 {
        f32::from_bits(self.w)
    }

    /// The same edge with its ends mapped by `id` (a tile's local ids to the scene's).
    pub(super) fn mapped(&self, id: impl Fn(u32) -> u32) -> Edge {
        Edge {
            w: self.w,
            i: id(self.i),
            j: id(self.j),
        }
    }
}

impl Geometry {
    /// The geometric part of the weight of edge `(i, j)` of length `d` under `p`'s weights.
    pub(super) fn geometric(&self, p: &SegmentParams, i: usize, j: usize, d: f32) -> f32 {
        let geo = self;
        let (ni, nj) = (geo.normals[i], geo.normals[j]);
        let dot = (ni[0] * nj[0] + ni[1] * nj[1] + ni[2] * nj[2])
            .abs()
            .min(1.0);
        let normal = (1.0 - dot) * geo.flatness[i].min(geo.flatness[j]);
        let (ri, rj) = (geo.size[i], geo.size[j]);
        let sum = (ri + rj).max(f32::MIN_POSITIVE);
        let gap = (d - 2.0 * (ri + rj)).max(0.0) / sum;
        let shape = if ri > 0.0 && rj > 0.0 {
            (ri / rj).ln().abs()
        } else {
            0.0
        };
        p.normal_weight * normal + p.distance_weight * gap + p.shape_weight * shape
    }
}

/// The distance `|a − b|` of two means (scene units).
pub(super) fn distance(a: [f32; 3], b: [f32; 3]) -> f32 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// The edge weights from their geometric part ([`Geometry::geometric`]) and, with a masks'
/// record, the mask term (module doc).
pub(super) struct Weigher<'a> {
    pub(super) p: &'a SegmentParams,
    pub(super) masks: Option<&'a MaskRecord>,
}

impl Weigher<'_> {
    /// The mask disagreement `m ∈ [0, 1]` of `(i, j)`: the record's, or
    /// [`SegmentParams::mask_unknown`] when the two share no recorded view; `None` without a
    /// record.
    fn disagreement(&self, i: usize, j: usize) -> Option<f32> {
        self.masks
            .map(|r| self.known_or_unknown(r.disagreement(i, j)))
    }

    /// The weight of edge `(i, j)` whose geometric part is `geometric`: that plus the mask
    /// term (≥ 0; non-finite → `f32::MAX`).
    #[cfg(test)]
    pub(super) fn weight(&self, geometric: f32, i: usize, j: usize) -> f32 {
        self.weight_with(geometric, self.disagreement(i, j))
    }

    /// The weight of an edge whose geometric part is `geometric` and whose mask disagreement
    /// is `m` (`None`: no record): `geometric + mask_weight · m` (≥ 0; non-finite →
    /// `f32::MAX`).
    pub(super) fn weight_with(&self, geometric: f32, m: Option<f32>) -> f32 {
        let mut w = geometric;
        if let Some(m) = m {
            w += self.p.mask_weight * m;
        }
        if w.is_finite() { w.max(0.0) } else { f32::MAX }
    }

    /// A mask disagreement of two rows of the record (e.g. [`MaskRecord::disagreement_between`]),
    /// or [`SegmentParams::mask_unknown`] when they share no recorded view (`None`): the value
    /// [`Weigher::weight`] adds for the two Gaussians, bit for bit.
    pub(super) fn known_or_unknown(&self, m: Option<f32>) -> f32 {
        m.unwrap_or(self.p.mask_unknown)
    }

    /// Prefetches the record rows of `e`'s ends ([`MaskRecord::prefetch`]); nothing without a
    /// record.
    #[inline(always)]
    pub(super) fn prefetch_ends(&self, e: &Edge) {
        if let Some(r) = self.masks {
            r.prefetch(e.i as usize);
            r.prefetch(e.j as usize);
        }
    }

    /// Whether the minimum-size pass may join across `e`: always without a record; with one,
    /// unless the masks disagree on it more than [`SegmentParams::mask_veto`].
    pub(super) fn may_absorb(&self, e: &Edge) -> bool {
        self.disagreement(e.i as usize, e.j as usize)
            .is_none_or(|m| m <= self.p.mask_veto)
    }
}
