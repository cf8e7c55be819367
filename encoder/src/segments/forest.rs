//! The Felzenszwalb–Huttenlocher passes (module doc, "Segmentation") over a list of edges: the
//! union-find forest with each component's size and `Int`.

use rayon::prelude::*;

use super::regions::Regions;
use super::weights::Edge;
use crate::disjoint_sets::DisjointSets;

/// A Felzenszwalb–Huttenlocher component: its Gaussian count and `Int`, the largest edge weight
/// of its minimum spanning tree.
#[derive(Clone, Copy)]
pub(super) struct Component {
    size: u32,
    int: f32,
}

/// Union-find with the Felzenszwalb–Huttenlocher component data (size, `Int`).
pub(super) type Forest = DisjointSets<Component>;

impl Forest {
    /// Every Gaussian of `n` its own component.
    pub(super) fn singletons(n: usize) -> Self {
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
    pub(super) fn criterion_pass(&mut self, edges: &[Edge], tau: f32) {
        self.criterion_pass_in(edges, tau, None);
    }
    /// The merge criterion over `edges` in their order; with `regions`, two components whose
    /// regions' masks disagree are never joined, and a join merges their profiles.
    pub(super) fn criterion_pass_in(
        &mut self,
        edges: &[Edge],
        tau: f32,
        mut regions: Option<&mut Regions>,
    ) {
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
    /// [`Forest::criterion_pass_in`] over `edges`, and for each of `stops` (`(position, node)`,
    /// positions ascending, at most `edges.len()`) the merge threshold `Int + τ/|C|` of `node`'s
    /// component once the edges before `position` are passed: the components a border edge
    /// meets at its own place in the edge order, as far as the tile's edges tell (module doc,
    /// "Bounded memory and parallel passes: tiles"). One threshold per stop, in order.
    pub(super) fn criterion_pass_with_stops(
        &mut self,
        edges: &[Edge],
        tau: f32,
        stops: &[(usize, u32)],
        mut regions: Option<&mut Regions>,
    ) -> Vec<f32> {
        let mut at = 0;
        let mut thresholds = Vec::with_capacity(stops.len());
        for &(position, node) in stops {
            let position = position.clamp(at, edges.len());
            self.criterion_pass_in(&edges[at..position], tau, regions.as_deref_mut());
            at = position;
            thresholds.push(self.merge_threshold(node, tau));
        }
        self.criterion_pass_in(&edges[at..], tau, regions);
        thresholds
    }
    /// The merge threshold `Int + τ/|C|` of `x`'s component now: an edge to another component
    /// joins them when its weight is within both sides' thresholds.
    pub(super) fn merge_threshold(&mut self, x: u32, tau: f32) -> f32 {
        let root = self.find(x);
        let c = self.component(root);
        c.int + tau / c.size as f32
    }
    /// The border pass: joins across each of `edges` (in their order) whose weight is within
    /// `thresholds[k]`, the smaller of its two ends' merge thresholds where it stands in the edge
    /// order ([`Forest::criterion_pass_with_stops`]), unless both ends are already one component
    /// or `regions` refuses.
    pub(super) fn border_pass_in(
        &mut self,
        edges: &[Edge],
        thresholds: &[f32],
        mut regions: Option<&mut Regions>,
    ) {
        for (e, &t) in edges.iter().zip(thresholds) {
            let (a, b) = (self.find(e.i), self.find(e.j));
            if a != b && e.weight() <= t && regions.as_deref().is_none_or(|r| r.allows(a, b)) {
                self.join_regions(a, b, e.weight(), regions.as_deref_mut());
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
    /// Whether each Gaussian's component has fewer than `min_size` Gaussians now (in parallel,
    /// the forest read only). As components only grow, the minimum-size pass can join across
    /// an edge only if one of its ends is in such a component before the pass.
    pub(super) fn small_members(&self, min_size: usize) -> Vec<bool> {
        (0..self.len() as u32)
            .into_par_iter()
            .map(|x| (self.component(self.root(x)).size as usize) < min_size)
            .collect()
    }
    /// The minimum-size pass over `edges` in their order.
    /// Edges that `allowed` refuses are skipped (a mask border).
    #[cfg(test)]
    pub(super) fn min_size_pass(
        &mut self,
        edges: &[Edge],
        min_size: usize,
        allowed: impl Fn(&Edge) -> bool,
    ) {
        self.min_size_pass_in(edges, min_size, allowed, None);
    }
    /// [`Forest::min_size_pass`]; with `regions`, as [`Forest::criterion_pass_in`].
    pub(super) fn min_size_pass_in(
        &mut self,
        edges: &[Edge],
        min_size: usize,
        allowed: impl Fn(&Edge) -> bool,
        mut regions: Option<&mut Regions>,
    ) {
        for e in edges {
            let (a, b) = (self.find(e.i), self.find(e.j));
            if a != b
                && ((self.component(a).size as usize) < min_size
                    || (self.component(b).size as usize) < min_size)
                && allowed(e)
                && regions.as_deref().is_none_or(|r| r.allows(a, b))
            {
                self.join_regions(a, b, e.weight(), regions.as_deref_mut());
            }
        }
    }
}
