//! The k-NN lists of the neighbour graph: in id order ([`Neighbours`], the tests' reference) and
//! in space order ([`Ranked`], what the grid search ([`super::grid`]) returns and the graph's
//! edges ([`super::graph`]) read).

use rayon::prelude::*;

/// Each Gaussian's neighbours in the graph, at its id: `k` slots per Gaussian, the nearest
/// other means within `max_edge` in ascending `(distance, id)` order, [`NO_NEIGHBOUR`] in unused
/// slots (the tests' reference search; [`Ranked`] holds the same lists in space order).
#[cfg(test)]
pub(super) struct Neighbours {
    pub(super) k: usize,
    /// The slots, `k` per Gaussian, Gaussian `i`'s at `i k`.
    pub(super) ids: Vec<u32>,
}

/// Slot of [`Neighbours`] and [`Ranked`] without a neighbour.
pub(super) const NO_NEIGHBOUR: u32 = u32::MAX;

#[cfg(test)]
impl Neighbours {
    pub(super) fn of(&self, i: usize) -> impl Iterator<Item = u32> + '_ {
        self.ids[i * self.k..(i + 1) * self.k]
            .iter()
            .copied()
            .take_while(|&j| j != NO_NEIGHBOUR)
    }
}

/// The neighbour graph in *space order*: rank `r` is Gaussian `perm[r]`, the ranks following
/// the k-NN grid's cells in Morton order (ascending id within a cell), so that Gaussians near
/// in space sit near in memory. Each rank has `k` slots holding its neighbours' ranks (the
/// lists of [`Neighbours`], mapped). The per-Gaussian data an edge's weight reads (the far
/// end's list, the geometric parts, the masks' record of a tile) is laid out in this order:
/// in the scene's id order, which a trained `.ply` leaves unrelated to space, every edge reads
/// two far-apart places. 4 bytes per slot and 4 per Gaussian.
pub(super) struct Ranked {
    pub(super) k: usize,
    /// Rank → Gaussian id, `[N]`.
    pub(super) perm: Vec<u32>,
    /// The slots, `k` per rank, rank `r`'s at `r k`: neighbours' ranks.
    pub(super) slots: Vec<u32>,
}

impl Ranked {
    /// The lists `ids` (`k` slots per Gaussian in the order `order`, holding Gaussian ids)
    /// with their ids mapped to ranks, in place and in parallel; `order` becomes `perm`.
    pub(super) fn from_cell_order(k: usize, mut ids: Vec<u32>, order: Vec<u32>) -> Self {
        let mut rank_of = vec![0u32; order.len()];
        for (r, &i) in order.iter().enumerate() {
            rank_of[i as usize] = r as u32;
        }
        ids.par_iter_mut()
            .filter(|j| **j != NO_NEIGHBOUR)
            .for_each(|j| *j = rank_of[*j as usize]);
        Ranked {
            k,
            perm: order,
            slots: ids,
        }
    }

    /// The neighbours (ranks) of rank `r`.
    pub(super) fn of(&self, r: usize) -> impl Iterator<Item = u32> + '_ {
        self.slots[r * self.k..(r + 1) * self.k]
            .iter()
            .copied()
            .take_while(|&j| j != NO_NEIGHBOUR)
    }

    /// `values` (one per Gaussian, in id order) in rank order.
    pub(super) fn gather<T: Copy + Send + Sync>(&self, values: &[T]) -> Vec<T> {
        self.perm.par_iter().map(|&i| values[i as usize]).collect()
    }

    /// The same lists in id order, holding ids ([`Neighbours`]).
    #[cfg(test)]
    pub(super) fn in_id_order(&self) -> Neighbours {
        let k = self.k;
        let mut ids = vec![NO_NEIGHBOUR; self.slots.len()];
        for (r, &i) in self.perm.iter().enumerate() {
            for (s, j) in self.of(r).enumerate() {
                ids[i as usize * k + s] = self.perm[j as usize];
            }
        }
        Neighbours { k, ids }
    }
}
