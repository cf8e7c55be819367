//! Geometric segments of the Gaussians (the paper's prediction-filtering segments): a
//! Felzenszwalb–Huttenlocher graph segmentation (Felzenszwalb & Huttenlocher, "Efficient
//! Graph-Based Image Segmentation", IJCV 2004) run, as ScanNet's Segmentator runs it over a mesh,
//! over a k-nearest-neighbour graph of the Gaussian means (`rstar`).
//!
//! # Graph and weights (geometry only, never colour)
//!
//! Each Gaussian `i` has a centre `μ_i`, standard deviations `σ_i` (sorted `σ_min ≤ σ_mid ≤
//! σ_max`, scene units) and a rotation `q_i` (w, x, y, z). Its normal `n_i` is its shortest axis,
//! `R(q_i) e_argmin σ`, sign-free; its flatness `f_i = 1 − σ_min/σ_mid ∈ [0, 1]` says how well
//! that normal is defined (a disk: 1, a sphere: 0). Every Gaussian is joined to its
//! [`SegmentParams::neighbours`] nearest means (ties broken by Gaussian id), edges longer than
//! [`SegmentParams::max_edge`] dropped. The weight of edge `(i, j)`, `d = |μ_i − μ_j|`,
//! `r = σ_max`:
//!
//! `w = w_n (1 − |n_i·n_j|) min(f_i, f_j) + w_d max(0, d − 2(r_i + r_j)) / (r_i + r_j)
//!    + w_s |ln(r_i / r_j)|`
//!
//! (normal term: Segmentator's `1 − n_i·n_j` made sign-free, as a splat's axis has no side;
//! distance term: zero while the two splats overlap at 2σ, then the gap in units of their size;
//! shape term: the ratio of their sizes).
//!
//! # Segmentation
//!
//! Edges in ascending `(w, i, j)` order; components `C1 ∋ i`, `C2 ∋ j` merge when
//! `w ≤ min(Int(C1) + τ/|C1|, Int(C2) + τ/|C2|)` (`Int`: the largest weight of the component's
//! spanning tree, `τ` = [`SegmentParams::threshold`]); then, as Segmentator does, the edges once
//! more in the same order, merging wherever either side has fewer than
//! [`SegmentParams::min_size`] Gaussians. Ids are numbered by each segment's smallest Gaussian
//! id ([`slag_common::segments::canonical_ids`]): the result is deterministic, whatever the
//! thread count.
//!
//! # Region mask profiles (optional veto)
//!
//! With a masks' record and [`SegmentParams::region_veto`] below 1, each component also carries
//! a *mask profile*: its Gaussians' recorded `(view, dominant mask, a_kj)` entries summed per
//! `(view, mask)` (at most 64 entries, the heaviest kept; ties to the smaller key). The region
//! disagreement of two profiles is, over the views both hold, `1 − Σ_v W_v · Σ_m min(p_a(m|v),
//! p_b(m|v)) / Σ_v W_v` with `p(m|v)` a profile's share of its view-`v` weight in mask `m` and
//! `W_v = min(W_a(v), W_b(v))` (no shared view: no veto). Neither pass joins two components
//! whose disagreement exceeds the veto. Memory: 8 bytes per profile entry, at most the record's
//! (64 bytes per Gaussian with 8 slots) plus a vector header per Gaussian. Off by default: on
//! snowmiku it made more, smaller segments but no purer ones than a smaller minimum size does at
//! the same count (docs/results/prediction-filtering.md).
//!
//! # Bounded memory: tiles with a halo
//!
//! The graph is never held whole. The Gaussians are cut into tiles of at most
//! [`SegmentParams::tile_gaussians`] by median splits on the two world axes of largest extent;
//! each tile's k-NN is computed over the tile plus a halo of width `max_edge` around it, which
//! holds every neighbour an edge can reach, so each Gaussian's edges are exactly those of the
//! whole scene. Per tile, the edges inside it run the merge criterion; the edges that cross a tile
//! border are kept (a few per border Gaussian) and run it afterwards in a second union-find pass
//! over the same components (their `Int` and sizes carried over); the minimum-size pass then
//! goes over each tile's edges again (recomputed, not stored) and the border edges last. Memory:
//! 40 bytes per Gaussian for the whole scene (means, normals, flatness, size, tile, union-find)
//! plus one tile's tree and edges and the border edges.
//!
//! With one tile this is exactly the algorithm above. With several, it is exactly the same
//! algorithm over the edge order "every tile's inner edges (ascending), then the border edges
//! (ascending)" instead of one ascending order; a segment that no tile border cuts comes out the
//! same either way. `tests::tiles_equal_the_tile_grouped_order` checks this statement.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use rayon::prelude::*;
use rstar::RTree;
use rstar::primitives::GeomWithData;
use serde::{Deserialize, Serialize};
use slag_common::mask_record::MaskRecord;
use slag_common::scene::Gaussians;
use slag_common::segments::{Segments, canonical_ids};
use slag_common::{Error, Result};

use crate::check::require;
use crate::disjoint_sets::DisjointSets;

/// Settings of the segmentation; [`SegmentParams::default`] are the documented defaults.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SegmentParams {
    /// Nearest neighbours per Gaussian in the graph, k (default 10).
    pub neighbours: usize,
    /// Felzenszwalb–Huttenlocher scale τ: a component of size |C| accepts an edge up to
    /// `Int(C) + τ/|C|`; larger → larger, fewer segments (default 0.5).
    pub threshold: f32,
    /// Segments below this many Gaussians are merged into a neighbour (default 20, as
    /// Segmentator's `segMinVerts`).
    pub min_size: usize,
    /// Longest edge, scene units; also the tiles' halo width. `None` (default): 10 × the median
    /// of the Gaussians' largest standard deviation.
    pub max_edge: Option<f32>,
    /// Weight of the normal term `w_n` (default 1).
    pub normal_weight: f32,
    /// Weight of the distance (gap) term `w_d` (default 1).
    pub distance_weight: f32,
    /// Weight of the shape (size-ratio) term `w_s` (default 0.1).
    pub shape_weight: f32,
    /// Most Gaussians per tile (default 2,000,000); bounds the memory of the k-NN graph.
    pub tile_gaussians: usize,
    /// Weight of the mask term `w_m`: an edge whose ends fall in different masks in every view
    /// that records both gets `w_m` added (default 1; 0: geometry only). Used only with a
    /// masks' record.
    pub mask_weight: f32,
    /// The mask disagreement assumed for an edge whose ends share no recorded view (default
    /// 0.5: no evidence either way).
    pub mask_unknown: f32,
    /// The minimum-size pass does not join across an edge whose mask disagreement exceeds this
    /// (default 0.5: a border seen in more than half the shared evidence); 1: it joins
    /// anything, as without masks.
    pub mask_veto: f32,
    /// Two segments never join, in either pass, when their *regions'* mask disagreement exceeds
    /// this (module doc, "Region mask profiles"); default 1: no region veto (on snowmiku it
    /// gave no purer segments than smaller segments do). Used only with a masks' record.
    pub region_veto: f32,
}

impl Default for SegmentParams {
    fn default() -> Self {
        SegmentParams {
            neighbours: 10,
            threshold: 0.5,
            min_size: 20,
            max_edge: None,
            normal_weight: 1.0,
            distance_weight: 1.0,
            shape_weight: 0.1,
            tile_gaussians: 2_000_000,
            mask_weight: 1.0,
            mask_unknown: 0.5,
            mask_veto: 0.5,
            region_veto: 1.0,
        }
    }
}

impl SegmentParams {
    /// Checks every setting.
    ///
    /// Errors: [`Error::Param`] naming the setting (`neighbours`, `threshold`, `max_edge`,
    /// `tile_gaussians`, a weight) when outside its domain.
    pub fn validate(&self) -> Result<()> {
        let (k, tau) = (self.neighbours, self.threshold);
        require(
            (1..=256).contains(&k),
            "neighbours",
            k,
            "1 to 256 nearest neighbours per Gaussian (e.g. 10)",
        )?;
        require(
            tau.is_finite() && tau >= 0.0,
            "threshold",
            tau,
            "a finite scale τ ≥ 0 (e.g. 0.5)",
        )?;
        if let Some(m) = self.max_edge {
            let ok = m.is_finite() && m > 0.0;
            require(ok, "max_edge", m, "a positive length in scene units")?;
        }
        for (name, w) in [
            ("normal_weight", self.normal_weight),
            ("distance_weight", self.distance_weight),
            ("shape_weight", self.shape_weight),
            ("mask_weight", self.mask_weight),
        ] {
            require(w.is_finite() && w >= 0.0, name, w, "a finite weight ≥ 0")?;
        }
        for (name, v) in [
            ("mask_unknown", self.mask_unknown),
            ("mask_veto", self.mask_veto),
            ("region_veto", self.region_veto),
        ] {
            require((0.0..=1.0).contains(&v), name, v, "a share in [0, 1]")?;
        }
        require(
            self.tile_gaussians > k,
            "tile_gaussians",
            self.tile_gaussians,
            format!("more than neighbours ({k}) Gaussians per tile"),
        )
    }
}

/// What one segmentation did (for logs and reports).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SegmentStats {
    /// Gaussians segmented.
    pub gaussians: usize,
    /// Segments made.
    pub segments: u32,
    /// Tiles the scene was cut into.
    pub tiles: usize,
    /// Edges of the graph (each undirected edge once).
    pub edges: u64,
    /// Of those, edges across tile borders.
    pub border_edges: u64,
    /// The longest edge used (scene units): the given or derived `max_edge`.
    pub max_edge: f32,
    /// Slots per Gaussian of the masks' record the edges were weighed with; `None`: geometry
    /// only.
    pub mask_record: Option<usize>,
    /// Wall time, seconds.
    pub seconds: f64,
}

/// Per-Gaussian geometry the weights need.
struct Geometry {
    normals: Vec<[f32; 3]>,
    flatness: Vec<f32>,
    size: Vec<f32>,
}

fn geometry(g: &Gaussians) -> Geometry {
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
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
struct Edge {
    w: u32,
    i: u32,
    j: u32,
}

impl Edge {
    fn weight(&self) -> f32 {
        f32::from_bits(self.w)
    }
}

/// The edge weights: the geometric terms and, with a masks' record, the mask term (module doc).
struct Weigher<'a> {
    p: &'a SegmentParams,
    geo: &'a Geometry,
    masks: Option<&'a MaskRecord>,
}

impl Weigher<'_> {
    /// The geometric part of the weight of edge `(i, j)` of length `d`.
    fn geometric(&self, i: usize, j: usize, d: f32) -> f32 {
        let (p, geo) = (self.p, self.geo);
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

    /// The mask disagreement `m ∈ [0, 1]` of `(i, j)`: the record's, or
    /// [`SegmentParams::mask_unknown`] when the two share no recorded view; `None` without a
    /// record.
    fn disagreement(&self, i: usize, j: usize) -> Option<f32> {
        self.masks
            .map(|r| r.disagreement(i, j).unwrap_or(self.p.mask_unknown))
    }

    /// The weight of edge `(i, j)` of length `d` (≥ 0; non-finite → `f32::MAX`).
    fn weight(&self, i: usize, j: usize, d: f32) -> f32 {
        let mut w = self.geometric(i, j, d);
        if let Some(m) = self.disagreement(i, j) {
            w += self.p.mask_weight * m;
        }
        if w.is_finite() { w.max(0.0) } else { f32::MAX }
    }

    /// Whether the minimum-size pass may join across `e`: always without a record; with one,
    /// unless the masks disagree on it more than [`SegmentParams::mask_veto`].
    fn may_absorb(&self, e: &Edge) -> bool {
        self.disagreement(e.i as usize, e.j as usize)
            .is_none_or(|m| m <= self.p.mask_veto)
    }
}

/// A Felzenszwalb–Huttenlocher component: its Gaussian count and `Int`, the largest edge weight
/// of its minimum spanning tree.
#[derive(Clone, Copy)]
struct Component {
    size: u32,
    int: f32,
}

/// Union-find with the Felzenszwalb–Huttenlocher component data (size, `Int`).
type Forest = DisjointSets<Component>;

impl Forest {
    /// Every Gaussian of `n` its own component.
    fn singletons(n: usize) -> Self {
        DisjointSets::new(n, Component { size: 1, int: 0.0 })
    }
    /// Joins the components of roots `a` and `b` (union by size, ties to the smaller root id,
    /// so the result does not depend on anything but the edge order); `Int` of the union is
    /// the largest of `w` and both sides'.
    fn join(&mut self, a: u32, b: u32, w: f32) {
        let (ca, cb) = (self.component(a), self.component(b));
        let (big, small) = if ca.size > cb.size || (ca.size == cb.size && a < b) {
            (a, b)
        } else {
            (b, a)
        };
        let merged = Component {
            size: ca.size + cb.size,
            int: ca.int.max(cb.int).max(w),
        };
        self.attach(small, big, merged);
    }
    /// The merge criterion over `edges` in their order.
    #[cfg(test)]
    fn criterion_pass(&mut self, edges: &[Edge], tau: f32) {
        self.criterion_pass_in(edges, tau, None);
    }
    /// The merge criterion over `edges` in their order; with `regions`, two components whose
    /// regions' masks disagree are never joined, and a join merges their profiles.
    fn criterion_pass_in(&mut self, edges: &[Edge], tau: f32, mut regions: Option<&mut Regions>) {
        for e in edges {
            let (a, b) = (self.find(e.i), self.find(e.j));
            if a == b {
                continue;
            }
            let w = e.weight();
            let (ca, cb) = (self.component(a), self.component(b));
            let ta = ca.int + tau / ca.size as f32;
            let tb = cb.int + tau / cb.size as f32;
            if w <= ta.min(tb) && regions.as_deref().is_none_or(|r| r.allows(a, b)) {
                self.join_regions(a, b, w, regions.as_deref_mut());
            }
        }
    }
    /// [`Forest::join`], and the profiles of `regions` merged into the new root.
    fn join_regions(&mut self, a: u32, b: u32, w: f32, regions: Option<&mut Regions>) {
        self.join(a, b, w);
        if let Some(r) = regions {
            let root = self.find(a);
            r.absorb(root, if root == a { b } else { a });
        }
    }
    /// The minimum-size pass over `edges` in their order.
    /// Edges that `allowed` refuses are skipped (a mask border).
    #[cfg(test)]
    fn min_size_pass(&mut self, edges: &[Edge], min_size: usize, allowed: impl Fn(&Edge) -> bool) {
        self.min_size_pass_in(edges, min_size, allowed, None);
    }
    /// [`Forest::min_size_pass`]; with `regions`, as [`Forest::criterion_pass_in`].
    fn min_size_pass_in(
        &mut self,
        edges: &[Edge],
        min_size: usize,
        allowed: impl Fn(&Edge) -> bool,
        mut regions: Option<&mut Regions>,
    ) {
        for e in edges {
            let (a, b) = (self.find(e.i), self.find(e.j));
            if a != b
                && allowed(e)
                && ((self.component(a).size as usize) < min_size
                    || (self.component(b).size as usize) < min_size)
                && regions.as_deref().is_none_or(|r| r.allows(a, b))
            {
                self.join_regions(a, b, e.weight(), regions.as_deref_mut());
            }
        }
    }
}

/// Most entries of one region's mask profile ([`Regions`]); beyond it the lightest go.
const PROFILE_CAP: usize = 64;

/// Each component's *mask profile* (module doc, "Region mask profiles"): the record's
/// `(view, mask, a_kj)` entries of its Gaussians, summed per `(view, mask)`, sorted by
/// `(view, mask)`, at most [`PROFILE_CAP`] entries (the heaviest; ties to the smaller key).
/// Indexed by union-find root; a non-root's profile is empty.
struct Regions {
    profiles: Vec<Vec<(u16, u16, f32)>>,
    veto: f32,
}

impl Regions {
    /// Every Gaussian its own region, with its recorded slots.
    fn new(record: &MaskRecord, veto: f32) -> Self {
        let profiles = (0..record.len())
            .into_par_iter()
            .map(|i| {
                let mut p: Vec<(u16, u16, f32)> =
                    record.of(i).map(|s| (s.view, s.mask, s.weight)).collect();
                p.sort_by_key(|e| (e.0, e.1));
                p
            })
            .collect();
        Regions { profiles, veto }
    }

    /// Whether the regions of roots `a` and `b` may join: unless their disagreement exceeds
    /// the veto (no shared view: they may).
    fn allows(&self, a: u32, b: u32) -> bool {
        self.veto >= 1.0
            || region_disagreement(&self.profiles[a as usize], &self.profiles[b as usize])
                .is_none_or(|d| d <= self.veto)
    }

    /// Root `into` took root `from` in: its profile is the sum of both.
    fn absorb(&mut self, into: u32, from: u32) {
        let b = std::mem::take(&mut self.profiles[from as usize]);
        let a = std::mem::take(&mut self.profiles[into as usize]);
        self.profiles[into as usize] = merge_profiles(&a, &b);
    }
}

/// The sum of two profiles (sorted by `(view, mask)`), cut to the [`PROFILE_CAP`] heaviest.
fn merge_profiles(a: &[(u16, u16, f32)], b: &[(u16, u16, f32)]) -> Vec<(u16, u16, f32)> {
    let mut out: Vec<(u16, u16, f32)> = Vec::with_capacity(a.len() + b.len());
    let (mut i, mut j) = (0, 0);
    while i < a.len() || j < b.len() {
        let take_a = j >= b.len() || (i < a.len() && (a[i].0, a[i].1) <= (b[j].0, b[j].1));
        let e = if take_a {
            i += 1;
            a[i - 1]
        } else {
            j += 1;
            b[j - 1]
        };
        match out.last_mut() {
            Some(l) if (l.0, l.1) == (e.0, e.1) => l.2 += e.2,
            _ => out.push(e),
        }
    }
    if out.len() > PROFILE_CAP {
        out.sort_by(|x, y| y.2.total_cmp(&x.2).then((x.0, x.1).cmp(&(y.0, y.1))));
        out.truncate(PROFILE_CAP);
        out.sort_by_key(|e| (e.0, e.1));
    }
    out
}

/// The mask disagreement of two regions' profiles, in `[0, 1]`: over the views both hold, one
/// minus the overlap `Σ_m min(p_a(m | v), p_b(m | v))` of their mask distributions, each view
/// counting `min(W_a(v), W_b(v))` (its total weight in either). `None` without a shared view.
fn region_disagreement(a: &[(u16, u16, f32)], b: &[(u16, u16, f32)]) -> Option<f32> {
    let view_total = |p: &[(u16, u16, f32)], from: usize| -> (u16, f32, usize) {
        let v = p[from].0;
        let mut k = from;
        let mut t = 0.0;
        while k < p.len() && p[k].0 == v {
            t += p[k].2;
            k += 1;
        }
        (v, t, k)
    };
    let (mut i, mut j) = (0, 0);
    let (mut agree, mut total) = (0.0f32, 0.0f32);
    while i < a.len() && j < b.len() {
        let (va, ta, ea) = view_total(a, i);
        let (vb, tb, eb) = view_total(b, j);
        if va < vb {
            i = ea;
            continue;
        }
        if vb < va {
            j = eb;
            continue;
        }
        if ta > 0.0 && tb > 0.0 {
            let mut overlap = 0.0f32;
            let (mut x, mut y) = (i, j);
            while x < ea && y < eb {
                match a[x].1.cmp(&b[y].1) {
                    std::cmp::Ordering::Less => x += 1,
                    std::cmp::Ordering::Greater => y += 1,
                    std::cmp::Ordering::Equal => {
                        overlap += (a[x].2 / ta).min(b[y].2 / tb);
                        x += 1;
                        y += 1;
                    }
                }
            }
            let w = ta.min(tb);
            agree += w * overlap.min(1.0);
            total += w;
        }
        i = ea;
        j = eb;
    }
    (total > 0.0 && total.is_finite()).then(|| (1.0 - agree / total).clamp(0.0, 1.0))
}

/// Tiles: median splits on the two world axes of largest extent until each holds at most
/// `cap` Gaussians. Returns each Gaussian's tile and each tile's rectangle `(lo, hi)` on those
/// axes (bounds of its Gaussians).
#[allow(clippy::type_complexity)]
fn plan_tiles(means: &[[f32; 3]], cap: usize) -> ([usize; 2], Vec<u32>, Vec<([f32; 2], [f32; 2])>) {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for m in means {
        for a in 0..3 {
            lo[a] = lo[a].min(m[a]);
            hi[a] = hi[a].max(m[a]);
        }
    }
    let mut axes = [0usize, 1, 2];
    axes.sort_by(|&a, &b| (hi[b] - lo[b]).total_cmp(&(hi[a] - lo[a])).then(a.cmp(&b)));
    let ax = [axes[0], axes[1]];
    let mut perm: Vec<u32> = (0..means.len() as u32).collect();
    let mut tile_of = vec![0u32; means.len()];
    let mut rects = Vec::new();
    let mut stack = vec![(0usize, perm.len())];
    while let Some((a, b)) = stack.pop() {
        if a == b {
            continue;
        }
        let rows = &mut perm[a..b];
        let (mut rlo, mut rhi) = ([f32::INFINITY; 2], [f32::NEG_INFINITY; 2]);
        for &r in rows.iter() {
            for k in 0..2 {
                rlo[k] = rlo[k].min(means[r as usize][ax[k]]);
                rhi[k] = rhi[k].max(means[r as usize][ax[k]]);
            }
        }
        if rows.len() <= cap {
            let t = rects.len() as u32;
            rows.iter().for_each(|&r| tile_of[r as usize] = t);
            rects.push((rlo, rhi));
            continue;
        }
        let k = if rhi[0] - rlo[0] >= rhi[1] - rlo[1] {
            0
        } else {
            1
        };
        let mid = rows.len() / 2;
        rows.select_nth_unstable_by(mid, |&x, &y| {
            means[x as usize][ax[k]]
                .total_cmp(&means[y as usize][ax[k]])
                .then(x.cmp(&y))
        });
        stack.push((a + mid, b));
        stack.push((a, a + mid));
    }
    (ax, tile_of, rects)
}

/// Each Gaussian's neighbours in the graph: `k` slots per Gaussian, the nearest other means
/// within `max_edge` in ascending `(distance, id)` order, [`NO_NEIGHBOUR`] in unused slots.
/// 4 bytes per slot (40 per Gaussian at k = 10), for the whole scene: the k-NN search, the costly
/// part of the graph, runs once and before the masks are known (beside the encode).
struct Neighbours {
    k: usize,
    ids: Vec<u32>,
}

/// Slot of [`Neighbours`] without a neighbour.
const NO_NEIGHBOUR: u32 = u32::MAX;

impl Neighbours {
    fn of(&self, i: usize) -> impl Iterator<Item = u32> + '_ {
        self.ids[i * self.k..(i + 1) * self.k]
            .iter()
            .copied()
            .take_while(|&j| j != NO_NEIGHBOUR)
    }
}

/// The k nearest neighbours of tile `t`'s Gaussians, written into `nb`: the k-NN over the tile
/// plus a halo of width `h`, which holds every neighbour within `h`. Once `stop` is set the
/// remaining Gaussians get none: the caller discards such a partial result.
#[allow(clippy::too_many_arguments)]
fn tile_neighbours(
    t: u32,
    means: &[[f32; 3]],
    tile_of: &[u32],
    ax: [usize; 2],
    rect: ([f32; 2], [f32; 2]),
    p: &SegmentParams,
    h: f32,
    stop: &AtomicBool,
    nb: &mut Neighbours,
) {
    let (lo, hi) = rect;
    let inside = |m: &[f32; 3]| (0..2).all(|k| m[ax[k]] >= lo[k] - h && m[ax[k]] <= hi[k] + h);
    let members: Vec<u32> = (0..means.len() as u32)
        .into_par_iter()
        .filter(|&i| tile_of[i as usize] == t || inside(&means[i as usize]))
        .collect();
    let tree: RTree<GeomWithData<[f32; 3], u32>> = RTree::bulk_load(
        members
            .iter()
            .map(|&i| GeomWithData::new(means[i as usize], i))
            .collect(),
    );
    let k = p.neighbours;
    let h2 = h * h;
    let found: Vec<(u32, Vec<u32>)> = members
        .par_iter()
        .filter(|&&i| tile_of[i as usize] == t)
        .map(|&i| {
            if stop.load(Ordering::Relaxed) {
                return (i, Vec::new());
            }
            let mi = means[i as usize];
            // The k nearest other Gaussians within h, ties by id: take every candidate up to the
            // k-th distance, including all that tie with it, then sort by (distance, id).
            let mut cand: Vec<(f32, u32)> = Vec::with_capacity(k + 4);
            for (g, d2) in tree.nearest_neighbor_iter_with_distance_2(&mi) {
                if d2 > h2 {
                    break;
                }
                if cand.len() > k && d2 > cand[k].0 {
                    break;
                }
                cand.push((d2, g.data));
            }
            cand.retain(|c| c.1 != i);
            cand.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            cand.truncate(k);
            (i, cand.into_iter().map(|c| c.1).collect())
        })
        .collect();
    for (i, js) in found {
        let slots = &mut nb.ids[i as usize * nb.k..(i as usize + 1) * nb.k];
        slots.fill(NO_NEIGHBOUR);
        slots[..js.len()].copy_from_slice(&js);
    }
}

/// The graph's edges of tile `t` from the neighbour lists: inner edges (both ends in the
/// tile), ascending, and border edges (one end outside), unordered.
fn edges_of_tile(
    t: u32,
    means: &[[f32; 3]],
    tile_of: &[u32],
    nb: &Neighbours,
    w: &Weigher,
) -> (Vec<Edge>, Vec<Edge>) {
    let (inner, border): (Vec<Vec<Edge>>, Vec<Vec<Edge>>) = (0..means.len() as u32)
        .into_par_iter()
        .filter(|&i| tile_of[i as usize] == t)
        .map(|i| {
            let (mut inn, mut bor) = (Vec::new(), Vec::new());
            for j in nb.of(i as usize) {
                let (a, b) = (means[i as usize], means[j as usize]);
                let d =
                    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
                let e = Edge {
                    w: w.weight(i as usize, j as usize, d).to_bits(),
                    i: i.min(j),
                    j: i.max(j),
                };
                if tile_of[j as usize] == t {
                    inn.push(e);
                } else {
                    bor.push(e);
                }
            }
            (inn, bor)
        })
        .unzip();
    let mut inner: Vec<Edge> = inner.into_iter().flatten().collect();
    inner.par_sort_unstable();
    inner.dedup();
    (inner, border.into_iter().flatten().collect())
}

/// The graph's edges of tile `t` (k-NN and weights in one go; the tests' reference).
#[cfg(test)]
#[allow(clippy::too_many_arguments)]
fn tile_edges(
    t: u32,
    means: &[[f32; 3]],
    tile_of: &[u32],
    ax: [usize; 2],
    rect: ([f32; 2], [f32; 2]),
    geo: &Geometry,
    p: &SegmentParams,
    h: f32,
    stop: &AtomicBool,
) -> (Vec<Edge>, Vec<Edge>) {
    let mut nb = Neighbours {
        k: p.neighbours,
        ids: vec![NO_NEIGHBOUR; means.len() * p.neighbours],
    };
    tile_neighbours(t, means, tile_of, ax, rect, p, h, stop, &mut nb);
    let w = Weigher {
        p,
        geo,
        masks: None,
    };
    edges_of_tile(t, means, tile_of, &nb, &w)
}

/// `max_edge` for `p` and `geo`: the given one, or 10 × the median largest standard deviation.
fn resolve_max_edge(p: &SegmentParams, geo: &Geometry) -> f32 {
    if let Some(m) = p.max_edge {
        return m;
    }
    let mut s: Vec<f32> = geo.size.iter().copied().filter(|v| v.is_finite()).collect();
    if s.is_empty() {
        return 1.0;
    }
    let mid = s.len() / 2;
    s.select_nth_unstable_by(mid, f32::total_cmp);
    let m = 10.0 * s[mid];
    if m.is_finite() && m > 0.0 { m } else { 1.0 }
}

/// Where [`segment_with`] runs its parallel stages, and whether it should give up. Another
/// thread may change both while it runs: the encode that runs a segmentation beside itself
/// starts it on a small pool, widens it when the encode is done, and stops it when the encode
/// failed.
#[derive(Debug, Default)]
pub struct SegmentControl {
    stop: AtomicBool,
    pool: Mutex<Option<Arc<rayon::ThreadPool>>>,
}

impl SegmentControl {
    /// Stages on `pool`; `None`: on the pool of the calling thread (rayon's global pool, or the
    /// one whose `install` runs the caller).
    pub fn new(pool: Option<rayon::ThreadPool>) -> Self {
        SegmentControl {
            stop: AtomicBool::new(false),
            pool: Mutex::new(pool.map(Arc::new)),
        }
    }

    /// The stages that start from now on run on `pool` (those under way finish where they are).
    pub fn set_pool(&self, pool: rayon::ThreadPool) {
        *self.pool.lock().unwrap_or_else(|e| e.into_inner()) = Some(Arc::new(pool));
    }

    /// Asks the segmentation to give up: [`segment_with`] returns `Ok(None)` soon after.
    pub fn stop(&self) {
        self.stop.store(true, Ordering::Relaxed);
    }

    fn stopped(&self) -> bool {
        self.stop.load(Ordering::Relaxed)
    }

    /// Whether [`SegmentControl::stop`] was called.
    pub fn is_stopped(&self) -> bool {
        self.stopped()
    }

    /// Runs `op` on the current pool choice.
    pub fn run<R: Send>(&self, op: impl FnOnce() -> R + Send) -> R {
        let pool = self.pool.lock().unwrap_or_else(|e| e.into_inner()).clone();
        match pool {
            Some(p) => p.install(op),
            None => op(),
        }
    }
}

/// Segments the Gaussians of `g` (module doc) and records `source_ply` in the result; with
/// `masks` (the encode's masks' record of the same `.ply`), the edges carry the mask term.
///
/// Runs on the current rayon pool (the global one, or the pool whose `install` calls it); the
/// result does not depend on its thread count.
///
/// Errors: [`Error::Param`] for settings [`SegmentParams::validate`] refuses, a scene of more
/// than `u32::MAX - 1` Gaussians ([`Error::Limit`]), arrays that disagree ([`Error::Internal`]),
/// non-finite means ([`Error::Invalid`]), a record of another scene ([`Error::Mismatch`]).
pub fn segment(
    g: &Gaussians,
    p: &SegmentParams,
    source_ply: &str,
    masks: Option<Arc<MaskRecord>>,
) -> Result<(Segments, SegmentStats)> {
    let ctl = SegmentControl::default();
    segment_with(g, p, source_ply, &ctl, || masks)?
        .ok_or_else(|| Error::internal("the segmentation stopped without being asked to"))
}

/// [`segment`] with its parallel stages on `ctl`'s pool of the moment (the serial union-find
/// passes run on the calling thread), given up once [`SegmentControl::stop`] was called:
/// `Ok(None)` then. The stop is looked at between the stages and for every Gaussian of the
/// k-nearest-neighbour search, so it takes effect within about one union-find pass. The result
/// is [`segment`]'s, whatever the pools.
///
/// `masks` is called once the neighbour graph is built (the k-NN search, the costly part, runs
/// before): the encode hands over its record there when its last view is done. It may block;
/// `None`: geometry only.
///
/// Errors: those of [`segment`].
pub fn segment_with(
    g: &Gaussians,
    p: &SegmentParams,
    source_ply: &str,
    ctl: &SegmentControl,
    masks: impl FnOnce() -> Option<Arc<MaskRecord>>,
) -> Result<Option<(Segments, SegmentStats)>> {
    p.validate()?;
    let t0 = Instant::now();
    let n = g.len();
    check_scene(g)?;
    let geo = ctl.run(|| geometry(g));
    if ctl.stopped() {
        return Ok(None);
    }
    let h = resolve_max_edge(p, &geo);
    let (ax, tile_of, rects) = plan_tiles(&g.means, p.tile_gaussians);
    let Some(nb) = neighbour_graph(g, p, ctl, h, ax, &tile_of, &rects) else {
        return Ok(None);
    };
    let record = masks();
    if ctl.stopped() {
        return Ok(None);
    }
    if let Some(r) = &record
        && r.len() != n
    {
        return Err(Error::mismatch(
            slag_common::Mismatched::Scene,
            format!(
                "the masks' record holds {} Gaussians but the scene has {n}: use the record \
                 of an encode of this .ply",
                r.len()
            ),
        ));
    }
    let w = Weigher {
        p,
        geo: &geo,
        masks: record.as_deref(),
    };
    let (forest, edges, border_edges) = merge(g, p, ctl, &w, &nb, &tile_of, rects.len());
    let mut forest = match forest {
        Some(f) => f,
        None => return Ok(None),
    };
    let roots: Vec<u32> = (0..n as u32).map(|i| forest.find(i)).collect();
    let (segments, segment_count) = canonical_ids(&roots);
    let stats = SegmentStats {
        gaussians: n,
        segments: segment_count,
        tiles: rects.len(),
        edges,
        border_edges,
        max_edge: h,
        mask_record: record.as_ref().map(|r| r.slots),
        seconds: t0.elapsed().as_secs_f64(),
    };
    let parameters = serde_json::to_string(&serde_json::json!({
        "params": p, "max_edge_used": h, "tiles": rects.len(),
        "mask_record_slots": record.as_ref().map(|r| r.slots),
    }))
    .unwrap_or_default();
    Ok(Some((
        Segments {
            segments,
            segment_count,
            source_ply: source_ply.to_string(),
            parameters,
        },
        stats,
    )))
}

/// The checks of [`segment`] on the scene's arrays.
fn check_scene(g: &Gaussians) -> Result<()> {
    let n = g.len();
    if n >= u32::MAX as usize {
        return Err(Error::limit(
            slag_common::Resource::ShardGaussians,
            n,
            u32::MAX - 1,
        ));
    }
    if g.scales.len() != n || g.rotations.len() != n {
        return Err(Error::internal(format!(
            "{n} means, {} scales, {} rotations",
            g.scales.len(),
            g.rotations.len()
        )));
    }
    if let Some(i) = g
        .means
        .iter()
        .position(|m| m.iter().any(|v| !v.is_finite()))
    {
        return Err(Error::Invalid(format!(
            "mean of Gaussian {i} is not finite"
        )));
    }
    Ok(())
}

/// Every tile's k-NN into one [`Neighbours`]; `None` once stopped.
#[allow(clippy::type_complexity)]
fn neighbour_graph(
    g: &Gaussians,
    p: &SegmentParams,
    ctl: &SegmentControl,
    h: f32,
    ax: [usize; 2],
    tile_of: &[u32],
    rects: &[([f32; 2], [f32; 2])],
) -> Option<Neighbours> {
    let mut nb = Neighbours {
        k: p.neighbours,
        ids: vec![NO_NEIGHBOUR; g.len() * p.neighbours],
    };
    for (t, rect) in rects.iter().enumerate() {
        ctl.run(|| {
            tile_neighbours(
                t as u32, &g.means, tile_of, ax, *rect, p, h, &ctl.stop, &mut nb,
            )
        });
        if ctl.stopped() {
            return None;
        }
    }
    Some(nb)
}

/// The two Felzenszwalb–Huttenlocher passes over the tiles' edges (module doc): the forest
/// (`None` once stopped), the edge count and the border-edge count.
fn merge(
    g: &Gaussians,
    p: &SegmentParams,
    ctl: &SegmentControl,
    w: &Weigher,
    nb: &Neighbours,
    tile_of: &[u32],
    tiles: usize,
) -> (Option<Forest>, u64, u64) {
    let mut forest = Forest::singletons(g.len());
    let mut regions = w
        .masks
        .filter(|_| p.region_veto < 1.0)
        .map(|r| ctl.run(|| Regions::new(r, p.region_veto)));
    let mut border: Vec<Edge> = Vec::new();
    let mut edges = 0u64;
    for t in 0..tiles {
        let (inner, b) = ctl.run(|| edges_of_tile(t as u32, &g.means, tile_of, nb, w));
        if ctl.stopped() {
            return (None, edges, 0);
        }
        forest.criterion_pass_in(&inner, p.threshold, regions.as_mut());
        edges += inner.len() as u64;
        border.extend(b);
    }
    ctl.run(|| border.par_sort_unstable());
    border.dedup();
    edges += border.len() as u64;
    forest.criterion_pass_in(&border, p.threshold, regions.as_mut());
    if p.min_size > 1 {
        let allowed = |e: &Edge| w.may_absorb(e);
        for t in 0..tiles {
            let (inner, _) = ctl.run(|| edges_of_tile(t as u32, &g.means, tile_of, nb, w));
            if ctl.stopped() {
                return (None, edges, border.len() as u64);
            }
            forest.min_size_pass_in(&inner, p.min_size, allowed, regions.as_mut());
        }
        forest.min_size_pass_in(&border, p.min_size, allowed, regions.as_mut());
    }
    (Some(forest), edges, border.len() as u64)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    /// A scene of flat Gaussians on planes: the floor z = 0 over `[0, 4]²`, a wall x = 0 over
    /// `y, z ∈ [0, 2]`, and a box (its top face at z = 1 over `[2.5, 3.5]²`) floating apart,
    /// on a grid of spacing 0.1 with a little deterministic jitter. Returns the Gaussians and
    /// each one's surface (0 floor, 1 wall, 2 box top).
    fn planes() -> (Gaussians, Vec<u8>) {
        let mut g = Gaussians::default();
        let mut label = Vec::new();
        let mut s = 7u64;
        let mut jitter = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 40) as f32 / (1u64 << 24) as f32 - 0.5) * 0.01
        };
        // Rotations taking the local z axis (smallest scale) to the plane's normal.
        let z_up = [1.0, 0.0, 0.0, 0.0];
        let x_normal = [0.5f32.sqrt(), 0.0, 0.5f32.sqrt(), 0.0]; // z → x
        let mut push = |m: [f32; 3], q: [f32; 4], l: u8, g: &mut Gaussians| {
            g.means.push(m);
            g.scales.push([0.05, 0.05, 0.002]);
            g.rotations.push(q);
            g.opacities.push(0.9);
            label.push(l);
        };
        for a in 0..40 {
            for b in 0..40 {
                let m = [
                    a as f32 * 0.1 + 0.05 + jitter(),
                    b as f32 * 0.1 + 0.05 + jitter(),
                    jitter(),
                ];
                push(m, z_up, 0, &mut g);
            }
        }
        for a in 0..20 {
            for b in 0..20 {
                let m = [
                    jitter(),
                    a as f32 * 0.1 + 0.05 + jitter(),
                    b as f32 * 0.1 + 0.15 + jitter(),
                ];
                push(m, x_normal, 1, &mut g);
            }
        }
        for a in 0..10 {
            for b in 0..10 {
                let m = [
                    2.5 + a as f32 * 0.1 + jitter(),
                    2.5 + b as f32 * 0.1 + jitter(),
                    1.0 + jitter(),
                ];
                push(m, z_up, 2, &mut g);
            }
        }
        (g, label)
    }

    fn params() -> SegmentParams {
        SegmentParams {
            max_edge: Some(0.5),
            ..SegmentParams::default()
        }
    }

    #[test]
    fn planes_become_their_own_segments() {
        let (g, label) = planes();
        let (s, stats) = segment(&g, &params(), "planes", None).unwrap();
        assert_eq!(stats.tiles, 1);
        // Each surface is one segment, and no segment mixes surfaces.
        for l in 0..3u8 {
            let ids: std::collections::BTreeSet<u32> = (0..g.len())
                .filter(|&i| label[i] == l)
                .map(|i| s.segments[i])
                .collect();
            assert_eq!(ids.len(), 1, "surface {l} split into {ids:?}");
        }
        assert_eq!(s.segment_count, 3, "{stats:?}");
        s.validate().unwrap();
    }

    #[test]
    fn deterministic_over_thread_counts() {
        let (g, _) = planes();
        let p = SegmentParams {
            tile_gaussians: 500,
            ..params()
        };
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let a = one.install(|| segment(&g, &p, "x", None).unwrap().0);
        let b = segment(&g, &p, "x", None).unwrap().0;
        assert_eq!(a, b);
    }

    /// The tiled result equals the same two passes over the whole graph with the edges in
    /// tile-grouped order (every tile's inner edges, then the border edges): the statement of
    /// the module doc, and one tile equals the untiled algorithm.
    #[test]
    fn tiles_equal_the_tile_grouped_order() {
        let (mut g, _) = planes();
        // Rough normals so that segments straddle tile borders.
        for (i, q) in g.rotations.iter_mut().enumerate() {
            let t = (i % 7) as f32 * 0.15;
            *q = [t.cos(), t.sin(), 0.0, 0.0];
        }
        let p = SegmentParams {
            tile_gaussians: 400,
            threshold: 0.2,
            ..params()
        };
        let (tiled, stats) = segment(&g, &p, "x", None).unwrap();
        assert!(stats.tiles > 4 && stats.border_edges > 0, "{stats:?}");
        // Reference: the whole graph from one tile, reordered by the tiling.
        let geo = geometry(&g);
        let h = resolve_max_edge(&p, &geo);
        let (ax1, one, r1) = plan_tiles(&g.means, usize::MAX);
        let go = AtomicBool::new(false);
        let (all, none) = tile_edges(0, &g.means, &one, ax1, r1[0], &geo, &p, h, &go);
        assert!(none.is_empty());
        let (_, tile_of, rects) = plan_tiles(&g.means, p.tile_gaussians);
        let mut order: Vec<Edge> = Vec::new();
        for t in 0..rects.len() as u32 {
            order.extend(
                all.iter()
                    .filter(|e| tile_of[e.i as usize] == t && tile_of[e.j as usize] == t),
            );
        }
        order.extend(
            all.iter()
                .filter(|e| tile_of[e.i as usize] != tile_of[e.j as usize]),
        );
        assert_eq!(order.len() as u64, stats.edges);
        let mut f = Forest::singletons(g.len());
        f.criterion_pass(&order, p.threshold);
        f.min_size_pass(&order, p.min_size, |_| true);
        let roots: Vec<u32> = (0..g.len() as u32).map(|i| f.find(i)).collect();
        assert_eq!(canonical_ids(&roots).0, tiled.segments);
        // One tile: the ascending order itself.
        let single = SegmentParams {
            tile_gaussians: usize::MAX,
            ..p
        };
        let (untiled, _) = segment(&g, &single, "x", None).unwrap();
        let mut f = Forest::singletons(g.len());
        f.criterion_pass(&all, p.threshold);
        f.min_size_pass(&all, p.min_size, |_| true);
        let roots: Vec<u32> = (0..g.len() as u32).map(|i| f.find(i)).collect();
        assert_eq!(canonical_ids(&roots).0, untiled.segments);
    }

    #[test]
    fn clean_planes_do_not_depend_on_tiles() {
        let (g, _) = planes();
        let a = segment(&g, &params(), "x", None).unwrap().0;
        let b = segment(
            &g,
            &SegmentParams {
                tile_gaussians: 300,
                ..params()
            },
            "x",
            None,
        )
        .unwrap()
        .0;
        // The same segments (the recorded parameters differ: the tile count).
        assert_eq!(a.segments, b.segments);
        assert_eq!(a.segment_count, 3);
    }

    #[test]
    fn a_stop_gives_no_result_and_pools_do_not_change_it() {
        let (g, _) = planes();
        let p = SegmentParams {
            tile_gaussians: 500,
            ..params()
        };
        let stopped = SegmentControl::default();
        stopped.stop();
        assert!(
            segment_with(&g, &p, "x", &stopped, || None)
                .unwrap()
                .is_none()
        );
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        let ctl = SegmentControl::new(Some(pool(1)));
        let narrow = segment_with(&g, &p, "x", &ctl, || None).unwrap().unwrap().0;
        ctl.set_pool(pool(3));
        let wide = segment_with(&g, &p, "x", &ctl, || None).unwrap().unwrap().0;
        let plain = segment(&g, &p, "x", None).unwrap().0;
        assert_eq!(narrow, plain);
        assert_eq!(wide, plain);
    }

    /// Two boxes of different classes touching each other and standing on the ground: the
    /// ground z = 0 over `[0, 4]²`, box A over `[1, 2] × [1, 2]`, height 0.6, box B over
    /// `[2, 3] × [1, 2]`, height 0.4 (A's wall x = 2 is B's; their front and back walls are
    /// coplanar), shells of discs tilted at random by up to ±30° (a trained 3DGS's normals
    /// are rough) at spacing 0.1 on each box's top and four sides. Returns
    /// the Gaussians and their instance (0 ground, 1 A, 2 B).
    fn touching_boxes() -> (Gaussians, Vec<u32>) {
        let mut g = Gaussians::default();
        let mut inst = Vec::new();
        let z_up = [1.0, 0.0, 0.0, 0.0];
        let h = 0.5f32.sqrt();
        let x_normal = [h, 0.0, h, 0.0];
        let y_normal = [h, h, 0.0, 0.0];
        let mut push = |m: [f32; 3], q: [f32; 4], l: u32| {
            // Tilted by up to ±30° about a varying axis, as a trained 3DGS's splats lie.
            let i = g.means.len() as u64;
            let u = |k: u64| ((i * 2_654_435_761 + k * 40_503) % 1000) as f32 / 1000.0 - 0.5;
            let (t, a) = (u(1) * 1.05, [u(2), u(3), u(4)]);
            let an = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt().max(1e-6);
            let (c, sn) = ((t / 2.0).cos(), (t / 2.0).sin() / an);
            let r = [c, sn * a[0], sn * a[1], sn * a[2]];
            let q = [
                r[0] * q[0] - r[1] * q[1] - r[2] * q[2] - r[3] * q[3],
                r[0] * q[1] + r[1] * q[0] + r[2] * q[3] - r[3] * q[2],
                r[0] * q[2] - r[1] * q[3] + r[2] * q[0] + r[3] * q[1],
                r[0] * q[3] + r[1] * q[2] - r[2] * q[1] + r[3] * q[0],
            ];
            g.means.push(m);
            g.scales.push([0.05, 0.05, 0.01]);
            g.rotations.push(q);
            g.opacities.push(0.9);
            inst.push(l);
        };
        let boxes = [
            ([1.0f32, 1.0], [2.0f32, 2.0], 0.6f32),
            ([2.0, 1.0], [3.0, 2.0], 0.4),
        ];
        for a in 0..40 {
            for b in 0..40 {
                let (x, y) = (a as f32 * 0.1 + 0.05, b as f32 * 0.1 + 0.05);
                if !boxes
                    .iter()
                    .any(|(lo, hi, _)| x > lo[0] && x < hi[0] && y > lo[1] && y < hi[1])
                {
                    push([x, y, 0.0], z_up, 0);
                }
            }
        }
        for (k, (lo, hi, top)) in boxes.iter().enumerate() {
            let l = k as u32 + 1;
            let steps = |a: f32, b: f32| {
                let n = ((b - a) / 0.1).round() as usize;
                (0..n).map(move |i| a + 0.05 + i as f32 * 0.1)
            };
            for x in steps(lo[0], hi[0]) {
                for y in steps(lo[1], hi[1]) {
                    push([x, y, *top], z_up, l);
                }
                for z in steps(0.0, *top) {
                    push([x, lo[1], z], y_normal, l);
                    push([x, hi[1], z], y_normal, l);
                }
            }
            for y in steps(lo[1], hi[1]) {
                for z in steps(0.0, *top) {
                    // The shared wall belongs to the taller box A only.
                    if k == 0 || (lo[0] - 2.0).abs() > 1e-6 {
                        push([lo[0], y, z], x_normal, l);
                    }
                    push([hi[0], y, z], x_normal, l);
                }
            }
        }
        (g, inst)
    }

    /// A masks' record as SAM-like masks would give it: 6 views; in each, every Gaussian's
    /// dominant mask is its instance, except that the ground is cut into two masks along a line
    /// that moves from view to view (SAM's over-segmentation of a large surface), and that a
    /// Gaussian within 0.1 of another instance takes that instance's mask in one view of three
    /// (masks bleeding over a border).
    fn record_of(g: &Gaussians, inst: &[u32]) -> MaskRecord {
        record_bleeding(g, inst, 3, 0.011)
    }

    /// [`record_of`] with the bleeding as a parameter: a Gaussian within `sqrt(r2)` of another
    /// instance takes its mask in one view of `every`.
    fn record_bleeding(g: &Gaussians, inst: &[u32], every: usize, r2: f32) -> MaskRecord {
        let n = g.len();
        let mut r = MaskRecord::new(n, 4, 6).unwrap();
        let tree: RTree<GeomWithData<[f32; 3], u32>> = RTree::bulk_load(
            (0..n as u32)
                .map(|i| GeomWithData::new(g.means[i as usize], i))
                .collect(),
        );
        for v in 0..6usize {
            let cut = 0.7 + 0.45 * v as f32;
            let entries = (0..n as u32).map(|i| {
                let m = g.means[i as usize];
                let mut l = inst[i as usize];
                if v % every == (i as usize) % every {
                    let near = tree
                        .locate_within_distance(m, r2)
                        .find(|o| inst[o.data as usize] != l);
                    if let Some(o) = near {
                        l = inst[o.data as usize];
                    }
                }
                let mask = if l == 0 {
                    u32::from(m[0] > cut) + 10
                } else {
                    l
                };
                (i, mask, 1.0 + (i as usize * 7 + v) as f32 % 5.0)
            });
            r.add_view(v, entries);
        }
        r
    }

    #[test]
    fn touching_objects_of_different_classes_come_apart_with_masks() {
        use crate::eval::segment_quality::{boundary_recall, purity};
        let (g, inst) = touching_boxes();
        let labels: Vec<Option<u32>> = inst.iter().map(|&l| Some(l)).collect();
        let p = params();
        let measure = |s: &Segments| {
            let pu = purity(&labels, &s.segments).unwrap().purity;
            let br = boundary_recall(&g.means, &labels, &s.segments, 8, 0.2).unwrap();
            (pu, br.recall)
        };
        let (geometric, _) = segment(&g, &p, "boxes", None).unwrap();
        let (geo_purity, geo_recall) = measure(&geometric);
        let record = Arc::new(record_of(&g, &inst));
        let (masked, stats) = segment(&g, &p, "boxes", Some(Arc::clone(&record))).unwrap();
        let (purity, recall) = measure(&masked);
        assert_eq!(stats.mask_record, Some(4));
        // Geometry alone joins the coplanar front and back walls of the two boxes (B's walls
        // end in A's segment); the masks keep them apart.
        assert!(
            geo_purity < 0.97,
            "geometry alone: purity {geo_purity}, boundary recall {geo_recall}"
        );
        assert!(
            purity >= 0.99 && recall >= 0.95 && purity > geo_purity,
            "with masks: purity {purity}, boundary recall {recall} ({} segments; geometry \
             alone {geo_purity}, {geo_recall})",
            masked.segment_count
        );
        // The ground is not shredded by its two moving masks, nor a box by the bleeding.
        assert!(
            masked.segment_count <= 16,
            "{} segments",
            masked.segment_count
        );
        // Tiles and thread counts do not change the result.
        let tiled = SegmentParams {
            tile_gaussians: 500,
            ..p
        };
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let a = one.install(|| {
            segment(&g, &tiled, "x", Some(Arc::clone(&record)))
                .unwrap()
                .0
        });
        let b = segment(&g, &tiled, "x", Some(Arc::clone(&record)))
            .unwrap()
            .0;
        assert_eq!(a, b);
        // A record of another scene is refused.
        let other = Arc::new(MaskRecord::new(3, 4, 6).unwrap());
        assert!(matches!(
            segment(&g, &p, "x", Some(other)),
            Err(Error::Mismatch { .. })
        ));
    }

    #[test]
    fn region_profiles_sum_cap_and_disagree() {
        let a = vec![(0u16, 1u16, 2.0f32), (0, 2, 2.0), (3, 1, 1.0)];
        let b = vec![(0u16, 1u16, 1.0f32), (1, 5, 4.0)];
        let m = merge_profiles(&a, &b);
        assert_eq!(m, vec![(0, 1, 3.0), (0, 2, 2.0), (1, 5, 4.0), (3, 1, 1.0)]);
        // Same distribution in the one shared view: no disagreement; disjoint masks: 1.
        assert_eq!(region_disagreement(&a, &a), Some(0.0));
        let other = vec![(0u16, 7u16, 5.0f32)];
        assert_eq!(region_disagreement(&a, &other), Some(1.0));
        // View 0: a is half mask 1, b all mask 1: overlap 0.5 (view 3 and 1 not shared).
        assert_eq!(region_disagreement(&a, &b), Some(0.5));
        assert_eq!(region_disagreement(&a, &[(9, 0, 1.0)]), None);
        assert_eq!(region_disagreement(&a, &[]), None);
        // The cap keeps the heaviest entries, in (view, mask) order.
        let many: Vec<(u16, u16, f32)> = (0..100u16).map(|k| (k, 0, f32::from(k))).collect();
        let capped = merge_profiles(&many, &[]);
        assert_eq!(capped.len(), PROFILE_CAP);
        assert_eq!(capped[0].0 as usize, 100 - PROFILE_CAP);
        assert!(capped.windows(2).all(|w| w[0].0 < w[1].0));
    }

    /// The region veto on its own: with the edges weighed by geometry alone (mask weight 0,
    /// no pairwise veto), the coplanar walls of the two touching boxes join; with the region
    /// veto, segments whose Gaussians' recorded masks disagree stay apart. Off (1), it changes
    /// nothing.
    #[test]
    fn the_region_veto_keeps_regions_of_different_masks_apart() {
        use crate::eval::segment_quality::purity;
        let (g, inst) = touching_boxes();
        let labels: Vec<Option<u32>> = inst.iter().map(|&l| Some(l)).collect();
        let record = Arc::new(record_bleeding(&g, &inst, 3, 0.0));
        let run = |region_veto: f32, tiles: usize| {
            let p = SegmentParams {
                region_veto,
                mask_weight: 0.0,
                mask_veto: 1.0,
                tile_gaussians: tiles,
                ..params()
            };
            let (s, _) = segment(&g, &p, "boxes", Some(Arc::clone(&record))).unwrap();
            (purity(&labels, &s.segments).unwrap().purity, s)
        };
        let (off, o) = run(1.0, usize::MAX);
        let (geometric, _) = segment(&g, &params(), "boxes", None).unwrap();
        assert_eq!(
            o.segments, geometric.segments,
            "region veto 1 is geometry alone here"
        );
        let (on, r) = run(0.5, usize::MAX);
        assert!(off < 0.97, "geometry alone: purity {off}");
        assert!(
            on >= 0.99 && r.segment_count <= 40,
            "region veto: purity {on} ({} segments); off {off} ({})",
            r.segment_count,
            o.segment_count
        );
        // Deterministic over thread counts with tiles.
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let a = one.install(|| run(0.5, 500).1);
        assert_eq!(a, run(0.5, 500).1);
    }

    #[test]
    fn bad_settings_are_refused() {
        let (g, _) = planes();
        for p in [
            SegmentParams {
                neighbours: 0,
                ..params()
            },
            SegmentParams {
                threshold: f32::NAN,
                ..params()
            },
            SegmentParams {
                max_edge: Some(-1.0),
                ..params()
            },
            SegmentParams {
                region_veto: 1.5,
                ..params()
            },
        ] {
            assert!(matches!(
                segment(&g, &p, "x", None),
                Err(Error::Param { .. })
            ));
        }
    }
}
