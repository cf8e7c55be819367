//! Disjoint-set forest (union-find) with path compression and data per component: what both
//! graph segmenters share, the image one ([`crate::masks::graph`], union by rank, pixel counts)
//! and the one over Gaussians ([`crate::segments`], union by size, `Int`). Each brings its own
//! component data `C` and union rule (an inherent `impl DisjointSets<ItsComponent>`).

/// Parent pointers over the elements `0..n` (a root is its own parent) and, per root, the data
/// `C` of its set.
pub(crate) struct DisjointSets<C> {
    parent: Vec<u32>,
    components: Vec<C>,
}

impl<C: Copy> DisjointSets<C> {
    /// `n` singleton sets, each with the data `singleton`.
    pub(crate) fn new(n: usize, singleton: C) -> Self {
        DisjointSets {
            parent: (0..n as u32).collect(),
            components: vec![singleton; n],
        }
    }

    /// The sets given by each element's parent (a root is its own) and the data of each root
    /// (at its index; the other entries are not read).
    pub(crate) fn from_parts(parent: Vec<u32>, components: Vec<C>) -> Self {
        DisjointSets { parent, components }
    }

    /// Each element's root and the data array (meaningful at the roots).
    pub(crate) fn into_roots(mut self) -> (Vec<u32>, Vec<C>) {
        let roots = (0..self.parent.len() as u32)
            .map(|x| self.find(x))
            .collect();
        (roots, self.components)
    }

    /// The root of `x`'s set; points every element on the path from `x` straight at it.
    pub(crate) fn find(&mut self, x: u32) -> u32 {
        let root = self.root(x);
        let mut x = x;
        while self.parent[x as usize] != root {
            let next = self.parent[x as usize];
            self.parent[x as usize] = root;
            x = next;
        }
        root
    }

    /// Asks the CPU to bring `x`'s parent entry into its cache ahead of a [`DisjointSets::find`]
    /// of `x`: a hint that changes no result. A pass over edges in weight order reads the
    /// forest at random places, each read a cache miss on a large forest; prefetching the ends
    /// of an edge some edges ahead overlaps those misses ([`slag_common::cache::prefetch`]).
    /// No-op out of range.
    #[inline(always)]
    pub(crate) fn prefetch(&self, x: u32) {
        if let Some(p) = self.parent.get(x as usize) {
            slag_common::cache::prefetch(p);
        }
    }

    /// The second step of [`DisjointSets::prefetch`], some steps later, once `x`'s parent entry
    /// has arrived: prefetches the parent entry and the data of `x`'s parent. Paths are short
    /// after compression, so that parent is most often the root, whose data the pass reads
    /// next. A hint that changes no result; no-op out of range.
    #[inline(always)]
    pub(crate) fn prefetch_parent(&self, x: u32) {
        if let Some(&p) = self.parent.get(x as usize) {
            if let Some(pp) = self.parent.get(p as usize) {
                slag_common::cache::prefetch(pp);
            }
            if let Some(c) = self.components.get(p as usize) {
                slag_common::cache::prefetch(c);
            }
        }
    }

    /// The root of `x`'s set, without compressing its path (so that threads may share the
    /// forest).
    pub(crate) fn root(&self, x: u32) -> u32 {
        let mut root = x;
        while self.parent[root as usize] != root {
            root = self.parent[root as usize];
        }
        root
    }

    /// The number of elements.
    pub(crate) fn len(&self) -> usize {
        self.parent.len()
    }

    /// The data of the set whose root is `root` (meaningless for an element that is not a root).
    pub(crate) fn component(&self, root: u32) -> C {
        self.components[root as usize]
    }

    /// Joins the set of root `child` into the set of root `root`, which stays the root and
    /// whose data becomes `merged`.
    pub(crate) fn attach(&mut self, child: u32, root: u32, merged: C) {
        self.parent[child as usize] = root;
        self.components[root as usize] = merged;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn attached_sets_share_a_root_and_its_data_and_paths_are_compressed() {
        let mut s = DisjointSets::new(5, 1u32);
        s.attach(1, 0, 2);
        s.attach(2, 1, 3);
        s.attach(4, 3, 2);
        assert_eq!(
            (s.root(2), s.parent[2]),
            (0, 1),
            "root() leaves the path as it is"
        );
        assert_eq!(s.find(2), 0);
        assert_eq!(s.parent[2], 0, "the path from 2 now points at the root");
        assert_eq!((s.find(4), s.component(3)), (3, 2));
        assert_ne!(s.find(4), s.find(1));
        s.attach(3, 0, 5);
        assert_eq!((0..5).map(|x| s.find(x)).collect::<Vec<_>>(), vec![0; 5]);
        assert_eq!(s.component(0), 5);
    }
}
