//! Disjoint-set forest (union-find) with path compression: the parent pointers that both graph
//! segmenters share, the image one ([`crate::masks::graph`]) and the one over Gaussians
//! ([`crate::segments`]). Each keeps its own union rule and per-component data (sizes, ranks,
//! `Int`) beside it, indexed by root.

/// Parent pointers over the elements `0..n`; a root is its own parent.
pub(crate) struct DisjointSets {
    parent: Vec<u32>,
}

impl DisjointSets {
    /// `n` singleton sets.
    pub(crate) fn new(n: usize) -> Self {
        DisjointSets {
            parent: (0..n as u32).collect(),
        }
    }

    /// The root of `x`'s set; points every element on the path from `x` straight at it.
    pub(crate) fn find(&mut self, x: u32) -> u32 {
        let mut root = x;
        while self.parent[root as usize] != root {
            root = self.parent[root as usize];
        }
        let mut x = x;
        while self.parent[x as usize] != root {
            let next = self.parent[x as usize];
            self.parent[x as usize] = root;
            x = next;
        }
        root
    }

    /// Joins the set of root `child` into the set of root `root` (`root` stays the root).
    pub(crate) fn attach(&mut self, child: u32, root: u32) {
        self.parent[child as usize] = root;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn attached_sets_share_a_root_and_paths_are_compressed() {
        let mut s = DisjointSets::new(5);
        s.attach(1, 0);
        s.attach(2, 1);
        s.attach(4, 3);
        assert_eq!(s.find(2), 0);
        assert_eq!(s.parent[2], 0, "the path from 2 now points at the root");
        assert_eq!(s.find(4), 3);
        assert_ne!(s.find(4), s.find(1));
        s.attach(3, 0);
        assert_eq!((0..5).map(|x| s.find(x)).collect::<Vec<_>>(), vec![0; 5]);
    }
}
