//! Bounded top-k selection and exact merging of per-thread results.
//!
//! Order used everywhere: higher score first, equal scores by lower row first. This is a total
//! order on `(score, row)` for non-NaN scores, so the selected set and its order are unique and do
//! not depend on how rows were split between threads.

use std::cmp::Ordering;
use std::collections::BinaryHeap;

/// One scored row of a [`VectorStore`](super::VectorStore).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Hit {
    /// Row index in the store (`0..store.len()`); map it to a Gaussian with `store.ids()[row]`.
    pub row: usize,
    /// Combined score (plain cosine for one query with unit rows and a unit query).
    pub score: f32,
}

/// `Ordering::Less` when `a` ranks before `b` (higher score, then lower row).
#[inline]
pub fn rank_cmp(a: &Hit, b: &Hit) -> Ordering {
    b.score.total_cmp(&a.score).then(a.row.cmp(&b.row))
}

/// Heap entry whose `Ord` puts the *worst* hit on top of a max-heap.
#[derive(Debug, Clone, Copy)]
struct Worst(Hit);

impl PartialEq for Worst {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other) == Ordering::Equal
    }
}
impl Eq for Worst {}
impl PartialOrd for Worst {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Worst {
    fn cmp(&self, other: &Self) -> Ordering {
        // Worse rank = greater.
        rank_cmp(&self.0, &other.0)
    }
}

/// Keeps the `k` best hits seen so far in O(k) memory.
#[derive(Debug, Clone)]
pub struct TopK {
    k: usize,
    heap: BinaryHeap<Worst>,
    /// Score of the current worst kept hit once full (`-inf` until then): a cheap pre-filter.
    floor: f32,
}

impl TopK {
    /// An empty selector for the `k` best hits (`k = 0` keeps nothing).
    pub fn new(k: usize) -> Self {
        TopK {
            k,
            heap: BinaryHeap::with_capacity(k.min(1 << 16)),
            floor: f32::NEG_INFINITY,
        }
    }

    /// Offers a hit. NaN scores are never kept.
    #[inline]
    pub fn push(&mut self, row: usize, score: f32) {
        // Fast reject: strictly below the current floor (ties go through the exact compare).
        if score < self.floor || score.is_nan() || self.k == 0 {
            return;
        }
        let hit = Hit { row, score };
        if self.heap.len() < self.k {
            self.heap.push(Worst(hit));
            if self.heap.len() == self.k {
                self.floor = self.heap.peek().map_or(f32::NEG_INFINITY, |w| w.0.score);
            }
        } else {
            let replaced = match self.heap.peek_mut() {
                Some(mut top) if rank_cmp(&hit, &top.0) == Ordering::Less => {
                    *top = Worst(hit);
                    true
                }
                _ => false,
            };
            if replaced {
                self.floor = self.heap.peek().map_or(f32::NEG_INFINITY, |w| w.0.score);
            }
        }
    }

    /// Merges another selector (same `k`) into this one; the result is exactly the top-k of the
    /// union of both inputs.
    pub fn merge(mut self, other: TopK) -> TopK {
        let (mut big, small) = if self.heap.len() >= other.heap.len() {
            (std::mem::replace(&mut self, TopK::new(0)), other)
        } else {
            (other, self)
        };
        for w in small.heap {
            big.push(w.0.row, w.0.score);
        }
        big
    }

    /// The kept hits, best first (higher score, then lower row).
    pub fn into_sorted(self) -> Vec<Hit> {
        let mut v: Vec<Hit> = self.heap.into_iter().map(|w| w.0).collect();
        v.sort_unstable_by(rank_cmp);
        v
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn topk_keeps_best_with_ties_by_row_and_merges_exactly() {
        let scores = [0.5f32, 0.9, 0.5, 0.1, 0.9, f32::NAN, 0.5, -1.0];
        let mut all: Vec<Hit> = scores
            .iter()
            .enumerate()
            .filter(|(_, s)| !s.is_nan())
            .map(|(row, &score)| Hit { row, score })
            .collect();
        all.sort_by(rank_cmp);
        for k in 0..=9 {
            let mut one = TopK::new(k);
            for (i, &s) in scores.iter().enumerate() {
                one.push(i, s);
            }
            let want: Vec<Hit> = all.iter().copied().take(k).collect();
            assert_eq!(one.into_sorted(), want, "k={k}");
            // Split at every point and merge.
            for cut in 0..=scores.len() {
                let (mut a, mut b) = (TopK::new(k), TopK::new(k));
                for (i, &s) in scores.iter().enumerate() {
                    if i < cut { a.push(i, s) } else { b.push(i, s) }
                }
                assert_eq!(b.merge(a).into_sorted(), want, "k={k} cut={cut}");
            }
        }
    }
}
