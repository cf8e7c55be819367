//! The Felzenszwalb–Huttenlocher passes (module doc, "Segmentation") over a list of edges: the
//! union-find forest with each component's size and `Int`.

use std::collections::HashMap;

use rayon::prelude::*;

use super::regions::Regions;
use super::weights::Edge;
use crate::disjoint_sets::DisjointSets;

/// A Felzenszwalb–Huttenlocher component: its Gaussian count and `Int`, the largest edge weight
/// of its minimum spanning tree.
#[derive(Clone, Copy, Default)]
pub(super) struct Component {
    size: u32,
    int: f32,
}

impl Component {
    /// Its Gaussian count.
    pub(super) fn size(&self) -> usize {
        self.size as usize
    }
}

/// Union-find with the Felzenszwalb–Huttenlocher component data (size, `Int`).
pub(super) type Forest = DisjointSets<Component>;

/// How many edges ahead a pass prefetches the forest entries of an edge's ends
/// ([`DisjointSets::prefetch`]): far enough ahead for a miss to land before the edge comes,
/// near enough for the line to be still in cache then.
const PREFETCH_AHEAD: usize = 16;

/// How many edges ahead a pass prefetches the entries of the ends' parents, read from the ends'
/// entries prefetched [`PREFETCH_AHEAD`] edges ahead ([`DisjointSets::prefetch_parent`]).
const PREFETCH_PARENTS_AHEAD: usize = 8;

impl Forest {
    /// For a pass at `edges[k]`: prefetches the forest entries of the ends of the edge
    /// [`PREFETCH_AHEAD`] after it, and those of the ends' parents of the edge
    /// [`PREFETCH_PARENTS_AHEAD`] after it: a find's two reads and the root's data, each in
    /// flight before its edge comes.
    #[inline(always)]
    fn prefetch_ends(&self, edges: &[Edge], k: usize) {
        if let Some(e) = edges.get(k + PREFETCH_AHEAD) {
            self.prefetch(e.i);
            self.prefetch(e.j);
        }
        if let Some(e) = edges.get(k + PREFETCH_PARENTS_AHEAD) {
            self.prefetch_parent(e.i);
            self.prefetch_parent(e.j);
        }
    }

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
        for (k, e) in edges.iter().enumerate() {
            self.prefetch_ends(edges, k);
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
    /// positions ascending, at most `edges.len()`) `node`'s component (size, `Int`) once the
    /// edges before `position` are passed: the component a border edge meets at its own place
    /// in the edge order, as far as the tile's edges tell (module doc, "Bounded memory and
    /// parallel passes: tiles"). One component per stop, in order.
    pub(super) fn criterion_pass_with_stops(
        &mut self,
        edges: &[Edge],
        tau: f32,
        stops: &[(usize, u32)],
        mut regions: Option<&mut Regions>,
    ) -> Vec<Component> {
        let mut at = 0;
        let mut states = Vec::with_capacity(stops.len());
        for &(position, node) in stops {
            let position = position.clamp(at, edges.len());
            self.criterion_pass_in(&edges[at..position], tau, regions.as_deref_mut());
            at = position;
            states.push(self.component_of(node));
        }
        self.criterion_pass_in(&edges[at..], tau, regions);
        states
    }
    /// `x`'s component now (size, `Int`).
    pub(super) fn component_of(&mut self, x: u32) -> Component {
        let root = self.find(x);
        self.component(root)
    }
    /// The border pass over `edges` (in their order), with `ends[k]` the components that edge
    /// `k`'s ends `i` and `j` met where it stands in the order
    /// ([`Forest::criterion_pass_with_stops`]). An edge joins its two components when its weight
    /// is within both sides' merge thresholds `Int + τ/|C|` (and `regions`, if any, allows),
    /// where a side is the component its end met, or, once border edges have joined that
    /// side's component to others, the group they make: its pieces' sizes summed (each
    /// piece's the largest seen at a join, this one's as it met the edge) and the largest of
    /// their `Int`s and the joins' weights. So a line of segments along a tile border is held
    /// to its growing size as one pass would hold it, instead of each join being judged alone.
    pub(super) fn border_pass_in(
        &mut self,
        edges: &[Edge],
        ends: &[[Component; 2]],
        tau: f32,
        mut regions: Option<&mut Regions>,
    ) {
        // The component after the tiles' passes (a "piece") that each end lies in.
        let pieces: Vec<[u32; 2]> = edges
            .iter()
            .map(|e| [self.find(e.i), self.find(e.j)])
            .collect();
        // Per group root: its pieces' sizes summed and its Int; per piece in a group: its size.
        let mut groups: HashMap<u32, (u64, f32)> = HashMap::new();
        let mut seen: HashMap<u32, u32> = HashMap::new();
        for ((e, met), piece) in edges.iter().zip(ends).zip(&pieces) {
            let roots = [self.find(e.i), self.find(e.j)];
            if roots[0] == roots[1] {
                continue;
            }
            let side = |s: usize| -> (u64, f32) {
                let c = met[s];
                match groups.get(&roots[s]) {
                    None => (c.size as u64, c.int),
                    Some(&(sum, int)) => {
                        let before = seen.get(&piece[s]).copied().unwrap_or(0);
                        (
                            sum - before as u64 + before.max(c.size) as u64,
                            int.max(c.int),
                        )
                    }
                }
            };
            let ((sa, ia), (sb, ib)) = (side(0), side(1));
            let w = e.weight();
            let ta = ia + tau / sa as f32;
            let tb = ib + tau / sb as f32;
            if w <= ta.min(tb)
                && regions
                    .as_deref()
                    .is_none_or(|r| r.allows(roots[0], roots[1]))
            {
                for s in 0..2 {
                    let before = seen.get(&piece[s]).copied().unwrap_or(0);
                    seen.insert(piece[s], before.max(met[s].size));
                    groups.remove(&roots[s]);
                }
                self.join_regions(roots[0], roots[1], w, regions.as_deref_mut());
                let root = self.find(roots[0]);
                groups.insert(root, (sa + sb, ia.max(ib).max(w)));
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
    /// Each element's root (`[N]`), found in parallel without changing the forest.
    pub(super) fn roots(&self) -> Vec<u32> {
        (0..self.len() as u32)
            .into_par_iter()
            .map(|x| self.root(x))
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
        for (k, e) in edges.iter().enumerate() {
            self.prefetch_ends(edges, k);
            let (a, b) = (self.find(e.i), self.find(e.j));
            if a != b
                && (self.component(a).size() < min_size || self.component(b).size() < min_size)
                && allowed(e)
                && regions.as_deref().is_none_or(|r| r.allows(a, b))
            {
                self.join_regions(a, b, e.weight(), regions.as_deref_mut());
            }
        }
    }
}
