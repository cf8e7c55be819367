//! Objects in a query's answer: groups of matching Gaussians that a planner can use (where each
//! one is, how big it is, how sure the answer is), instead of one summary over every match.
//!
//! Every coordinate is in the answer's frame (the map frame, metres, when the manifest has a
//! scene-to-map transform; else the scene frame, scene units).
//!
//! [`group_objects`] turns the matches of one query into [`SceneObject`]s:
//! 1. **Grouping.** Matches are linked by single linkage: two matches whose means lie within
//!    [`ObjectParams::gap`] of each other (Euclidean, answer frame) are in the same group. The
//!    links are found exactly on a uniform grid of cell side `gap / √3` (two means in one cell
//!    are within the gap; cells up to two apart are compared pair by pair until one link is
//!    found), and the groups are the connected components (union-find), which do not depend on
//!    the order of the matches. Geometric segments decide which Gaussians match (score smoothing,
//!    [`crate::segments`]), not which matches form one object: linking the matches of one segment
//!    as well joined touching regions of one colour on snowmiku into an object of a quarter of
//!    the scene (5.8 × 4.1 × 2.1 scene units for "pink", against 2.7 × 1.7 × 0.8 by the gap
//!    alone) and changed nothing on the synthetic touching objects (docs/results/objects.md).
//!    The gap is [`ObjectParams::gap`] when given, else derived from the matches' own spacing
//!    ([`derived_gap`]: a multiple of their median nearest-neighbour distance), so a scene
//!    of any scale or density finds its objects without a gap chosen for it.
//! 2. **Suppression.** Groups of fewer than [`ObjectParams::min_gaussians`] matches are dropped
//!    (stray matches; counted in [`Objects::suppressed`]).
//! 3. **Description.** Per group: the id (FNV-1a 64 of the members' sorted Gaussian ids: the same
//!    members give the same id whatever their rank), the centroid weighted by `max(score, 0) ×
//!    opacity` (opacity = the sigmoid of the stored pre-sigmoid opacity, or 1 where the caller
//!    has none, so then the weight is the score alone; the plain mean where every weight is 0), the
//!    AABB and the PCA oriented box of the member means, the count, the max and mean score and
//!    the score mass `Σ max(score, 0) × opacity` (the sum of the centroid's weights). Boxes bound
//!    the Gaussians' means, not their ellipsoids.
//! 4. **Order.** By score mass, largest first (ties: more Gaussians, then the id); with
//!    [`ObjectParams::near`], by distance from that point to the centroid, nearest first. At most
//!    [`ObjectParams::max_objects`] are kept. The mass grows with how much of the scene answers
//!    the prompt and how well: a mean or a max score ranks a group of a dozen faint, confident
//!    Gaussians (often floaters of low opacity) above the large object the prompt names, while
//!    the mass counts each Gaussian as much as it is seen (its opacity) and agrees with the
//!    prompt (its score).

use std::collections::HashMap;

use crate::{Error, Result};

/// Single-linkage gap used when the matches give no spacing to derive one from (fewer than two
/// distinct means), answer-frame units (metres in the map frame).
pub const FALLBACK_GAP: f32 = 0.1;
/// The derived gap ([`derived_gap`]) is this multiple of the matches' median nearest-neighbour
/// distance.
pub const GAP_SPACING_MULTIPLE: f32 = 4.0;
/// At most this many matches (evenly spread over the input order) are asked for their nearest
/// neighbour when the gap is derived; the neighbours are searched among all matches.
pub const GAP_SAMPLE: usize = 4096;
/// Default minimum number of matching Gaussians of an object; smaller groups are dropped.
pub const DEFAULT_MIN_GAUSSIANS: usize = 10;
/// Default number of objects returned.
pub const DEFAULT_MAX_OBJECTS: usize = 20;
/// Largest `max_objects` accepted.
pub const MAX_OBJECTS_LIMIT: usize = 1000;

/// An oriented bounding box: the principal axes (PCA) of an object's Gaussian means.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct OrientedBox {
    /// Box centre, answer frame.
    pub center: [f32; 3],
    /// The three unit axes (rows), right-handed, largest extent first.
    pub axes: [[f32; 3]; 3],
    /// Full extents along each axis (metres in the map frame), same order as `axes`.
    pub extents: [f32; 3],
}

/// One object: a group of matching Gaussians.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SceneObject {
    /// Identifier, stable for the same scene, stored Gaussians and prompt (derived from the
    /// group's members, not from its rank).
    pub id: u64,
    /// Centroid weighted by score × opacity, answer frame.
    pub centroid: [f32; 3],
    /// Axis-aligned box `[min xyz, max xyz]`, answer frame.
    pub aabb: [[f32; 3]; 2],
    /// Oriented box (PCA of the members' means).
    pub obb: OrientedBox,
    /// Matching Gaussians in the group.
    pub gaussians: usize,
    /// Best score of a member.
    pub max_score: f32,
    /// Mean score of the members.
    pub mean_score: f32,
    /// Score mass `Σ max(score, 0) × opacity` over the members (opacity 1 where none is known):
    /// the objects' order without `near` (module doc).
    pub score_mass: f32,
}

/// How matches become objects (module doc).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ObjectParams {
    /// Single-linkage distance between two matches' means, answer-frame units (metres in the
    /// map frame); finite and > 0. `None` (the default): derived from the matches' own spacing,
    /// [`derived_gap`].
    pub gap: Option<f32>,
    /// Smallest object, in matching Gaussians (≥ 1). Default [`DEFAULT_MIN_GAUSSIANS`].
    pub min_gaussians: usize,
    /// Objects returned, 1..=[`MAX_OBJECTS_LIMIT`]. Default [`DEFAULT_MAX_OBJECTS`].
    pub max_objects: usize,
    /// Sort by distance of the centroid from this point (the robot; answer frame) instead of by
    /// score.
    pub near: Option<[f32; 3]>,
}

impl Default for ObjectParams {
    fn default() -> Self {
        ObjectParams {
            gap: None,
            min_gaussians: DEFAULT_MIN_GAUSSIANS,
            max_objects: DEFAULT_MAX_OBJECTS,
            near: None,
        }
    }
}

impl ObjectParams {
    /// Checks every field's domain.
    ///
    /// Errors: [`Error::Param`] naming `gap`, `min_gaussians`, `max_objects` or `near`.
    pub fn validate(&self) -> Result<()> {
        if let Some(gap) = self.gap.filter(|g| !(g.is_finite() && *g > 0.0)) {
            return Err(Error::param(
                "gap",
                gap,
                "a finite distance > 0 in the answer's frame (metres in the map frame)",
            ));
        }
        if self.min_gaussians == 0 {
            return Err(Error::param("min_gaussians", 0, "an integer ≥ 1"));
        }
        if !(1..=MAX_OBJECTS_LIMIT).contains(&self.max_objects) {
            return Err(Error::param(
                "max_objects",
                self.max_objects,
                format!("an integer in 1..={MAX_OBJECTS_LIMIT}"),
            ));
        }
        if let Some(p) = self.near.filter(|p| !p.iter().all(|v| v.is_finite())) {
            return Err(Error::param(
                "near",
                format!("{p:?}"),
                "three finite coordinates x,y,z in the answer's frame",
            ));
        }
        Ok(())
    }
}

/// The matches of one query, one entry per matching Gaussian, all slices of the same length.
#[derive(Debug, Clone, Copy)]
pub struct Matches<'a> {
    /// Source-`.ply` Gaussian ids.
    pub ids: &'a [u32],
    /// Means, answer frame.
    pub positions: &'a [[f32; 3]],
    /// Scores (cosine or relevancy).
    pub scores: &'a [f32],
    /// Opacities in 0..=1 (the sigmoid of the stored pre-sigmoid opacity; 1 for a Gaussian
    /// without one); `None`: the centroid is weighted by score alone.
    pub opacities: Option<&'a [f32]>,
}

/// The objects of one query.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Objects {
    /// The objects, in answer order (module doc), at most `max_objects`.
    pub objects: Vec<SceneObject>,
    /// Per match (same order as [`Matches`]): the index in `objects` of its object, `None` for
    /// matches in a suppressed group or in an object beyond `max_objects`.
    pub member_of: Vec<Option<u32>>,
    /// Groups dropped for having fewer than `min_gaussians` matches.
    pub suppressed: usize,
    /// Groups at or above the minimum (returned or not).
    pub groups: usize,
    /// The single-linkage gap used: [`ObjectParams::gap`], or the one derived from the matches.
    pub gap: f32,
}

/// Groups `m` into objects (module doc).
///
/// Errors: [`Error::Param`] for parameters out of their domain ([`ObjectParams::validate`]);
/// [`Error::Internal`] when the slices of `m` differ in length.
pub fn group_objects(m: &Matches<'_>, p: &ObjectParams) -> Result<Objects> {
    p.validate()?;
    let n = m.ids.len();
    if m.positions.len() != n || m.scores.len() != n || m.opacities.is_some_and(|o| o.len() != n) {
        return Err(Error::internal(
            "group_objects: ids, positions, scores and opacities differ in length",
        ));
    }
    let gap = p.gap.unwrap_or_else(|| derived_gap(m.positions));
    let mut uf = UnionFind::new(n);
    link_within_gap(m.positions, gap, &mut uf);
    // Components, members in input order; components ordered by their first member.
    let mut comp_of_root: HashMap<usize, usize> = HashMap::new();
    let mut comps: Vec<Vec<usize>> = Vec::new();
    for i in 0..n {
        let r = uf.find(i);
        let c = *comp_of_root.entry(r).or_insert_with(|| {
            comps.push(Vec::new());
            comps.len() - 1
        });
        comps[c].push(i);
    }
    let mut suppressed = 0;
    let mut described: Vec<(SceneObject, Vec<usize>)> = Vec::new();
    for members in comps {
        if members.len() < p.min_gaussians {
            suppressed += 1;
            continue;
        }
        described.push((describe(m, &members), members));
    }
    let groups = described.len();
    match p.near {
        Some(q) => described.sort_by(|a, b| {
            dist2(a.0.centroid, q)
                .total_cmp(&dist2(b.0.centroid, q))
                .then(a.0.id.cmp(&b.0.id))
        }),
        None => described.sort_by(|a, b| {
            b.0.score_mass
                .total_cmp(&a.0.score_mass)
                .then(b.0.gaussians.cmp(&a.0.gaussians))
                .then(a.0.id.cmp(&b.0.id))
        }),
    }
    described.truncate(p.max_objects);
    let mut member_of = vec![None; n];
    let mut objects = Vec::with_capacity(described.len());
    for (k, (o, members)) in described.into_iter().enumerate() {
        for i in members {
            member_of[i] = Some(k as u32);
        }
        objects.push(o);
    }
    Ok(Objects {
        objects,
        member_of,
        suppressed,
        groups,
        gap,
    })
}

/// The single-linkage gap of a set of means (answer frame): [`GAP_SPACING_MULTIPLE`] × the
/// median distance from a match to its nearest other match (over at most [`GAP_SAMPLE`]
/// matches, evenly spread over the input order, their neighbours searched among all of them;
/// coincident means are skipped), so that the matches of one surface, whose holes are a few
/// neighbour spacings wide, link into one object at any scene scale and density; and objects
/// further apart than a few spacings stay apart. [`FALLBACK_GAP`] when fewer than two distinct
/// finite means are given.
pub fn derived_gap(positions: &[[f32; 3]]) -> f32 {
    use rstar::RTree;
    let finite: Vec<[f32; 3]> = positions
        .iter()
        .copied()
        .filter(|p| p.iter().all(|v| v.is_finite()))
        .collect();
    if finite.len() < 2 {
        return FALLBACK_GAP;
    }
    let tree = RTree::bulk_load(finite.clone());
    let step = finite.len().div_ceil(GAP_SAMPLE).max(1);
    let mut nearest: Vec<f32> = finite
        .iter()
        .step_by(step)
        .filter_map(|q| {
            tree.nearest_neighbor_iter(q)
                .map(|p| dist2(*p, *q).sqrt())
                .find(|&d| d > 0.0)
        })
        .collect();
    if nearest.is_empty() {
        return FALLBACK_GAP;
    }
    let mid = nearest.len() / 2;
    let median = *nearest.select_nth_unstable_by(mid, f32::total_cmp).1;
    median * GAP_SPACING_MULTIPLE
}

fn dist2(a: [f32; 3], b: [f32; 3]) -> f32 {
    (0..3).map(|k| (a[k] - b[k]) * (a[k] - b[k])).sum()
}

/// Disjoint sets with path halving and union by size.
struct UnionFind {
    parent: Vec<usize>,
    size: Vec<usize>,
}

impl UnionFind {
    fn new(n: usize) -> Self {
        UnionFind {
            parent: (0..n).collect(),
            size: vec![1; n],
        }
    }
    fn find(&mut self, mut i: usize) -> usize {
        while self.parent[i] != i {
            self.parent[i] = self.parent[self.parent[i]];
            i = self.parent[i];
        }
        i
    }
    fn union(&mut self, a: usize, b: usize) -> bool {
        let (mut a, mut b) = (self.find(a), self.find(b));
        if a == b {
            return false;
        }
        if self.size[a] < self.size[b] {
            std::mem::swap(&mut a, &mut b);
        }
        self.parent[b] = a;
        self.size[a] += self.size[b];
        true
    }
}

/// Links every pair of points within `gap` (inclusive) in `uf`: exact single linkage on a grid of
/// cell side `gap / √3` (module doc). Non-finite points link to nothing.
fn link_within_gap(points: &[[f32; 3]], gap: f32, uf: &mut UnionFind) {
    let cell = f64::from(gap) / 3f64.sqrt();
    let gap2 = f64::from(gap) * f64::from(gap);
    let key = |p: &[f32; 3]| -> Option<[i64; 3]> {
        p.iter()
            .all(|v| v.is_finite())
            .then(|| [0, 1, 2].map(|a| (f64::from(p[a]) / cell).floor().clamp(-9e15, 9e15) as i64))
    };
    let mut cells: HashMap<[i64; 3], Vec<usize>> = HashMap::new();
    for (i, p) in points.iter().enumerate() {
        if let Some(k) = key(p) {
            cells.entry(k).or_default().push(i);
        }
    }
    // Within a cell every pair is within the gap (the cell's diagonal is the gap).
    for members in cells.values() {
        for &i in &members[1..] {
            uf.union(members[0], i);
        }
    }
    let mut keys: Vec<[i64; 3]> = cells.keys().copied().collect();
    keys.sort_unstable();
    let close = |i: usize, j: usize| -> bool {
        let (a, b) = (points[i], points[j]);
        (0..3)
            .map(|k| {
                let d = f64::from(a[k]) - f64::from(b[k]);
                d * d
            })
            .sum::<f64>()
            <= gap2
    };
    for k in &keys {
        let a = &cells[k];
        for dx in -2i64..=2 {
            for dy in -2i64..=2 {
                for dz in -2i64..=2 {
                    // Each unordered pair of cells once: the offset lexicographically positive.
                    if (dx, dy, dz) <= (0, 0, 0) {
                        continue;
                    }
                    let nk = [k[0] + dx, k[1] + dy, k[2] + dz];
                    let Some(b) = cells.get(&nk) else { continue };
                    if uf.find(a[0]) == uf.find(b[0]) {
                        continue;
                    }
                    'pairs: for &i in a {
                        for &j in b {
                            if close(i, j) {
                                uf.union(i, j);
                                break 'pairs;
                            }
                        }
                    }
                }
            }
        }
    }
}

/// FNV-1a 64 of the little-endian bytes of the sorted ids.
fn members_id(mut ids: Vec<u32>) -> u64 {
    ids.sort_unstable();
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for id in ids {
        for b in id.to_le_bytes() {
            h ^= u64::from(b);
            h = h.wrapping_mul(0x0100_0000_01b3);
        }
    }
    h
}

fn describe(m: &Matches<'_>, members: &[usize]) -> SceneObject {
    let n = members.len() as f64;
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    let (mut wsum, mut wpos, mut mean) = (0f64, [0f64; 3], [0f64; 3]);
    let (mut max_score, mut score_sum) = (f32::NEG_INFINITY, 0f64);
    for &i in members {
        let p = m.positions[i];
        let s = m.scores[i];
        max_score = max_score.max(s);
        score_sum += f64::from(s);
        let w = f64::from(s.max(0.0)) * m.opacities.map_or(1.0, |o| f64::from(o[i].max(0.0)));
        wsum += w;
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
            wpos[a] += w * f64::from(p[a]);
            mean[a] += f64::from(p[a]);
        }
    }
    let mean = mean.map(|v| v / n);
    let centroid = if wsum > 0.0 {
        wpos.map(|v| (v / wsum) as f32)
    } else {
        mean.map(|v| v as f32)
    };
    SceneObject {
        id: members_id(members.iter().map(|&i| m.ids[i]).collect()),
        centroid,
        aabb: [lo, hi],
        obb: oriented_box(m.positions, members, mean),
        gaussians: members.len(),
        max_score,
        mean_score: (score_sum / n) as f32,
        score_mass: wsum as f32,
    }
}

/// PCA box of the members' means: axes = eigenvectors of their covariance, each with its
/// largest-magnitude component made positive, ordered by extent (largest first; ties by
/// variance), the third replaced by the cross product of the first two (right-handed).
fn oriented_box(points: &[[f32; 3]], members: &[usize], mean: [f64; 3]) -> OrientedBox {
    let mut cov = [[0f64; 3]; 3];
    for &i in members {
        let d = [0, 1, 2].map(|a| f64::from(points[i][a]) - mean[a]);
        for r in 0..3 {
            for c in 0..3 {
                cov[r][c] += d[r] * d[c];
            }
        }
    }
    let (w, v) = crate::shards::eigen::jacobi_eigen(cov);
    let mut axes: Vec<([f64; 3], f64)> = (0..3)
        .map(|i| {
            let mut ax = [v[0][i], v[1][i], v[2][i]];
            let big = (0..3)
                .max_by(|&a, &b| ax[a].abs().total_cmp(&ax[b].abs()))
                .unwrap_or(0);
            if ax[big] < 0.0 {
                ax = ax.map(|x| -x);
            }
            (ax, w[i])
        })
        .collect();
    let span = |ax: &[f64; 3]| -> (f64, f64) {
        members
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &i| {
                let t: f64 = (0..3)
                    .map(|a| (f64::from(points[i][a]) - mean[a]) * ax[a])
                    .sum();
                (lo.min(t), hi.max(t))
            })
    };
    let mut with_span: Vec<([f64; 3], f64, (f64, f64))> =
        axes.drain(..).map(|(ax, w)| (ax, w, span(&ax))).collect();
    with_span.sort_by(|a, b| {
        (b.2.1 - b.2.0)
            .total_cmp(&(a.2.1 - a.2.0))
            .then(b.1.total_cmp(&a.1))
    });
    let (a0, a1) = (with_span[0].0, with_span[1].0);
    let a2 = [
        a0[1] * a1[2] - a0[2] * a1[1],
        a0[2] * a1[0] - a0[0] * a1[2],
        a0[0] * a1[1] - a0[1] * a1[0],
    ];
    // The third axis may have flipped sign: its span flips with it.
    let s2 = span(&a2);
    let spans = [with_span[0].2, with_span[1].2, s2];
    let dirs = [a0, a1, a2];
    let mut center = mean;
    for k in 0..3 {
        let mid = 0.5 * (spans[k].0 + spans[k].1);
        for a in 0..3 {
            center[a] += mid * dirs[k][a];
        }
    }
    OrientedBox {
        center: center.map(|v| v as f32),
        axes: dirs.map(|d| d.map(|v| v as f32)),
        extents: spans.map(|(lo, hi)| (hi - lo) as f32),
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64;

    /// `n` points uniform in the box `c ± h` (per axis).
    fn blob(rng: &mut SplitMix64, c: [f32; 3], h: [f32; 3], n: usize) -> Vec<[f32; 3]> {
        (0..n)
            .map(|_| [0, 1, 2].map(|a| c[a] + h[a] * (2.0 * rng.next_f64() as f32 - 1.0)))
            .collect()
    }

    fn run(pos: &[[f32; 3]], scores: &[f32], p: &ObjectParams) -> Objects {
        let ids: Vec<u32> = (0..pos.len() as u32).map(|i| i * 7 + 3).collect();
        group_objects(
            &Matches {
                ids: &ids,
                positions: pos,
                scores,
                opacities: None,
            },
            p,
        )
        .unwrap()
    }

    /// Default parameters with a gap of 0.25: the test blobs' points are 0.05–0.11 apart.
    fn wide() -> ObjectParams {
        ObjectParams {
            gap: Some(0.25),
            ..ObjectParams::default()
        }
    }

    /// Brute-force single linkage: the partition into components as sorted member lists.
    fn brute(pos: &[[f32; 3]], gap: f32) -> Vec<Vec<usize>> {
        let mut uf = UnionFind::new(pos.len());
        for i in 0..pos.len() {
            for j in i + 1..pos.len() {
                if f64::from(dist2(pos[i], pos[j])).sqrt() <= f64::from(gap) * (1.0 - 1e-6) {
                    uf.union(i, j);
                }
            }
        }
        let mut by_root: HashMap<usize, Vec<usize>> = HashMap::new();
        for i in 0..pos.len() {
            let r = uf.find(i);
            by_root.entry(r).or_default().push(i);
        }
        let mut v: Vec<Vec<usize>> = by_root.into_values().collect();
        v.sort();
        v
    }

    #[test]
    fn grid_linkage_equals_brute_force_single_linkage() {
        let mut rng = SplitMix64::new(5);
        for (n, side, gap) in [(300, 2.0f32, 0.15f32), (500, 5.0, 0.3), (200, 1.0, 0.05)] {
            let pos: Vec<[f32; 3]> = (0..n)
                .map(|_| [0; 3].map(|_| side * rng.next_f64() as f32))
                .collect();
            let mut uf = UnionFind::new(n);
            link_within_gap(&pos, gap, &mut uf);
            let mut by_root: HashMap<usize, Vec<usize>> = HashMap::new();
            for i in 0..n {
                let r = uf.find(i);
                by_root.entry(r).or_default().push(i);
            }
            let mut got: Vec<Vec<usize>> = by_root.into_values().collect();
            got.sort();
            // Pairs at exactly the gap (to rounding) may differ; random points hit none.
            assert_eq!(got, brute(&pos, gap), "n {n} side {side} gap {gap}");
            assert!(
                got.len() > 1 && got.len() < n,
                "{} groups: a trivial case",
                got.len()
            );
        }
    }

    #[test]
    fn two_separate_blobs_are_two_objects_with_their_boxes() {
        let mut rng = SplitMix64::new(1);
        let mut pos = blob(&mut rng, [0.0, 0.0, 0.0], [0.5, 0.2, 0.1], 400);
        pos.extend(blob(&mut rng, [3.0, 1.0, 0.0], [0.2, 0.2, 0.2], 300));
        // Three strays far from everything and from each other.
        pos.extend([[10.0, 10.0, 0.0], [-10.0, 5.0, 0.0], [0.0, -9.0, 4.0]]);
        let mut scores = vec![0.3f32; 400];
        scores.extend(vec![0.5f32; 300]);
        scores.extend([0.9, 0.9, 0.9]);
        let o = run(&pos, &scores, &wide());
        assert_eq!(o.objects.len(), 2);
        assert_eq!((o.groups, o.suppressed), (2, 3));
        // Sorted by score mass (400 × 0.3 = 120 < 300 × 0.5 = 150): the second blob first.
        let (a, b) = (&o.objects[0], &o.objects[1]);
        assert_eq!((a.gaussians, b.gaussians), (300, 400));
        assert!((a.mean_score - 0.5).abs() < 1e-6 && (b.max_score - 0.3).abs() < 1e-6);
        assert!((a.score_mass - 150.0).abs() < 1e-3 && (b.score_mass - 120.0).abs() < 1e-3);
        for (o, c, h) in [
            (a, [3.0, 1.0, 0.0], [0.2; 3]),
            (b, [0.0; 3], [0.5, 0.2, 0.1]),
        ] {
            for k in 0..3 {
                assert!((o.centroid[k] - c[k]).abs() < 0.05, "{:?}", o.centroid);
                assert!((o.aabb[0][k] - (c[k] - h[k])).abs() < 0.05, "{:?}", o.aabb);
                assert!((o.aabb[1][k] - (c[k] + h[k])).abs() < 0.05, "{:?}", o.aabb);
            }
        }
        // The elongated blob's oriented box: its longest axis is x, extents ≈ 1.0, 0.4, 0.2.
        assert!(b.obb.axes[0][0].abs() > 0.99, "{:?}", b.obb.axes);
        for (e, want) in b.obb.extents.iter().zip([1.0, 0.4, 0.2]) {
            assert!((e - want).abs() < 0.05, "{:?}", b.obb.extents);
        }
        // Members point at their object; strays at none.
        assert_eq!(o.member_of[0], Some(1));
        assert_eq!(o.member_of[400], Some(0));
        assert_eq!(o.member_of[700], None);
    }

    #[test]
    fn oriented_box_follows_a_rotated_slab_and_is_right_handed() {
        let mut rng = SplitMix64::new(9);
        let (c, s) = (0.6f32.cos(), 0.6f32.sin());
        // A 2 × 0.6 × 0.1 slab rotated by 0.6 rad about z.
        let pos: Vec<[f32; 3]> = blob(&mut rng, [0.0; 3], [1.0, 0.3, 0.05], 2000)
            .into_iter()
            .map(|p| [c * p[0] - s * p[1] + 5.0, s * p[0] + c * p[1], p[2] + 1.0])
            .collect();
        let o = run(&pos, &vec![0.4; 2000], &ObjectParams::default());
        let b = &o.objects[0].obb;
        assert!(
            (b.axes[0][0] - c).abs() < 0.02 && (b.axes[0][1] - s).abs() < 0.02,
            "{b:?}"
        );
        for (e, want) in b.extents.iter().zip([2.0, 0.6, 0.1]) {
            assert!((e - want).abs() < 0.05, "{b:?}");
        }
        for (v, want) in b.center.iter().zip([5.0, 0.0, 1.0]) {
            assert!((v - want).abs() < 0.05, "{b:?}");
        }
        let [x, y, z] = b.axes;
        let cross = [
            x[1] * y[2] - x[2] * y[1],
            x[2] * y[0] - x[0] * y[2],
            x[0] * y[1] - x[1] * y[0],
        ];
        for k in 0..3 {
            assert!((cross[k] - z[k]).abs() < 1e-4, "{b:?}");
        }
    }

    #[test]
    fn ids_are_stable_and_order_independent_and_near_sorts_by_distance() {
        let mut rng = SplitMix64::new(2);
        let mut pos = blob(&mut rng, [0.0; 3], [0.2; 3], 50);
        pos.extend(blob(&mut rng, [5.0, 0.0, 0.0], [0.2; 3], 50));
        let scores: Vec<f32> = (0..100).map(|i| if i < 50 { 0.6 } else { 0.4 }).collect();
        let o = run(&pos, &scores, &wide());
        // Reversed input order: same ids, same objects.
        let ids: Vec<u32> = (0..100u32).map(|i| i * 7 + 3).rev().collect();
        let rpos: Vec<[f32; 3]> = pos.iter().rev().copied().collect();
        let rscores: Vec<f32> = scores.iter().rev().copied().collect();
        let r = group_objects(
            &Matches {
                ids: &ids,
                positions: &rpos,
                scores: &rscores,
                opacities: None,
            },
            &wide(),
        )
        .unwrap();
        assert_eq!(o.objects, r.objects);
        assert_ne!(o.objects[0].id, o.objects[1].id);
        // near the second blob: it comes first.
        let p = ObjectParams {
            near: Some([6.0, 0.0, 0.0]),
            ..wide()
        };
        let n = run(&pos, &scores, &p);
        assert_eq!(n.objects[0].id, o.objects[1].id);
        // max_objects keeps the first.
        let p = ObjectParams {
            max_objects: 1,
            ..wide()
        };
        let one = run(&pos, &scores, &p);
        assert_eq!(one.objects, vec![o.objects[0].clone()]);
        assert_eq!(one.groups, 2);
        assert_eq!(one.member_of.iter().filter(|m| m.is_some()).count(), 50);
    }

    #[test]
    fn a_large_object_outranks_a_tiny_confident_cluster() {
        let mut rng = SplitMix64::new(12);
        // A chair-sized object: 600 Gaussians at score 0.35, opaque; and 12 Gaussians at 0.9,
        // half transparent (a floater), 3 m away.
        let mut pos = blob(&mut rng, [0.0; 3], [0.2, 0.2, 0.3], 600);
        pos.extend(blob(&mut rng, [3.0, 0.0, 1.0], [0.02; 3], 12));
        let mut scores = vec![0.35f32; 600];
        scores.extend([0.9f32; 12]);
        let mut opacity = vec![0.95f32; 600];
        opacity.extend([0.5f32; 12]);
        let ids: Vec<u32> = (0..612).collect();
        let o = group_objects(
            &Matches {
                ids: &ids,
                positions: &pos,
                scores: &scores,
                opacities: Some(&opacity),
            },
            &ObjectParams::default(),
        )
        .unwrap();
        assert_eq!(o.objects.len(), 2);
        let (first, second) = (&o.objects[0], &o.objects[1]);
        // The large object first, although the cluster's mean and max score are higher.
        assert_eq!((first.gaussians, second.gaussians), (600, 12));
        assert!(second.mean_score > first.mean_score && second.max_score > first.max_score);
        assert!(
            (first.score_mass - 600.0 * 0.35 * 0.95).abs() < 0.05,
            "{first:?}"
        );
        assert!(
            (second.score_mass - 12.0 * 0.9 * 0.5).abs() < 1e-3,
            "{second:?}"
        );
        // Mass, not count: 60 Gaussians at 0.9 opaque (54) outrank 100 at 0.3 (30).
        let mut pos = blob(&mut rng, [0.0; 3], [0.1; 3], 100);
        pos.extend(blob(&mut rng, [3.0, 0.0, 0.0], [0.1; 3], 60));
        let mut scores = vec![0.3f32; 100];
        scores.extend([0.9f32; 60]);
        let o = run(&pos, &scores, &ObjectParams::default());
        assert_eq!(o.objects[0].gaussians, 60);
        assert!((o.objects[0].score_mass - 54.0).abs() < 1e-3);
    }

    #[test]
    fn centroid_is_weighted_by_score_and_opacity() {
        let pos = [[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.1, 0.0, 0.0]];
        let ids = [1, 2, 3];
        let p = ObjectParams {
            min_gaussians: 1,
            ..ObjectParams::default()
        };
        let with = |scores: &[f32], op: Option<&[f32]>| {
            group_objects(
                &Matches {
                    ids: &ids,
                    positions: &pos,
                    scores,
                    opacities: op,
                },
                &p,
            )
            .unwrap()
            .objects[0]
                .centroid[0]
        };
        assert!((with(&[1.0, 1.0, 1.0], None) - 0.05).abs() < 1e-6);
        // Score 3 at x = 0.1: (0 + 0.05 + 0.3) / 5.
        assert!((with(&[1.0, 1.0, 3.0], None) - 0.07).abs() < 1e-6);
        // Opacity 0 on the last one: (0 + 0.05) / 2.
        assert!((with(&[1.0, 1.0, 3.0], Some(&[1.0, 1.0, 0.0])) - 0.025).abs() < 1e-6);
        // Negative scores (a threshold-less query) carry no weight; all zero: the plain mean.
        assert!((with(&[-0.5, -0.2, -0.1], None) - 0.05).abs() < 1e-6);
    }

    #[test]
    fn bad_parameters_and_inconsistent_inputs_are_typed_errors() {
        let m = Matches {
            ids: &[1],
            positions: &[[0.0; 3]],
            scores: &[0.5],
            opacities: None,
        };
        // One bad field at a time, the rest default.
        type Breaks = fn(&mut ObjectParams);
        let cases: [(Breaks, &str); 6] = [
            (|p| p.gap = Some(0.0), "gap"),
            (|p| p.gap = Some(f32::NAN), "gap"),
            (|p| p.min_gaussians = 0, "min_gaussians"),
            (|p| p.max_objects = 0, "max_objects"),
            (|p| p.max_objects = 1001, "max_objects"),
            (|p| p.near = Some([0.0, f32::INFINITY, 0.0]), "near"),
        ];
        for (set, name) in cases {
            let mut p = ObjectParams::default();
            set(&mut p);
            match group_objects(&m, &p) {
                Err(Error::Param { name: n, .. }) => assert_eq!(n, name),
                other => panic!("{p:?}: {other:?}"),
            }
        }
        let bad = Matches {
            scores: &[0.5, 0.4],
            ..m
        };
        assert!(matches!(
            group_objects(&bad, &ObjectParams::default()),
            Err(Error::Internal(_))
        ));
        // No matches: no objects.
        let none = Matches {
            ids: &[],
            positions: &[],
            scores: &[],
            opacities: None,
        };
        assert_eq!(
            group_objects(&none, &ObjectParams::default()).unwrap(),
            Objects {
                gap: FALLBACK_GAP,
                ..Objects::default()
            }
        );
    }

    #[test]
    fn the_derived_gap_follows_the_scene_spacing_and_a_given_gap_wins() {
        // Two 20 × 20 sheets of points at spacing `s`, 30 spacings apart, at two scales: the
        // derived gap links each sheet and keeps the two apart, at either scale.
        for s in [0.01f32, 5.0] {
            let mut pos = Vec::new();
            for x0 in [0.0f32, 50.0 * s] {
                for i in 0..20 {
                    for j in 0..20 {
                        pos.push([x0 + i as f32 * s, j as f32 * s, 0.0]);
                    }
                }
            }
            let gap = derived_gap(&pos);
            assert!(
                (gap - GAP_SPACING_MULTIPLE * s).abs() < 1e-3 * s,
                "spacing {s}: gap {gap}"
            );
            let ids: Vec<u32> = (0..pos.len() as u32).collect();
            let scores = vec![0.5; pos.len()];
            let m = Matches {
                ids: &ids,
                positions: &pos,
                scores: &scores,
                opacities: None,
            };
            let o = group_objects(&m, &ObjectParams::default()).unwrap();
            assert_eq!(o.objects.len(), 2, "spacing {s}");
            assert_eq!(o.gap, gap);
            // An explicit gap wins: one smaller than the spacing leaves only single points.
            let tight = ObjectParams {
                gap: Some(0.5 * s),
                ..ObjectParams::default()
            };
            let t = group_objects(&m, &tight).unwrap();
            assert_eq!((t.objects.len(), t.gap), (0, 0.5 * s));
        }
        // Nothing to derive from: the fallback.
        assert_eq!(derived_gap(&[]), FALLBACK_GAP);
        assert_eq!(derived_gap(&[[1.0; 3], [1.0; 3]]), FALLBACK_GAP);
    }
}
