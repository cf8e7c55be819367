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
