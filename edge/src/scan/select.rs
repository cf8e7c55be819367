//! Bounded top-k selection and exact merging of per-thread results.
//!
//! Order used everywhere: higher score first, equal scores by lower row first. This is a total
//! order on `(score, row)` for non-NaN scores, so the selected set and its order are unique and do
//! not depend on how rows were split between threads.

use std::cmp::Ordering;

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

/// Keeps the `k` best hits seen so far in O(k) memory: candidates at or above the current floor
/// go into a buffer of up to `2k + 64` hits, which is then cut back to the best `k`
/// (`select_nth_unstable`, O(k)), raising the floor to the `k`-th best score. Amortised O(1) per
/// offered hit (a binary heap costs O(log k) per accepted one).
#[derive(Debug, Clone)]
pub struct TopK {
    k: usize,
    buf: Vec<Hit>,
    /// Score of the `k`-th best hit at the last cut (`-inf` before): rows strictly below it can
    /// never be selected.
    floor: f32,
}

impl TopK {
    /// An empty selector for the `k` best hits (`k = 0` keeps nothing).
    pub fn new(k: usize) -> Self {
        TopK {
            k,
            buf: Vec::new(),
            floor: f32::NEG_INFINITY,
        }
    }

    /// Buffer length that triggers a cut.
    fn limit(&self) -> usize {
        self.k.saturating_mul(2).saturating_add(64)
    }

    /// Cuts the buffer back to its best `k` hits and raises the floor.
    fn cut(&mut self) {
        if self.buf.len() > self.k {
            if self.k == 0 {
                self.buf.clear();
                return;
            }
            self.buf.select_nth_unstable_by(self.k - 1, rank_cmp);
            self.buf.truncate(self.k);
            self.floor = self.buf[self.k - 1].score;
        }
    }

    /// Offers a hit. NaN scores are never kept.
    #[inline]
    pub fn push(&mut self, row: usize, score: f32) {
        // Strictly below the floor (or NaN): never selected. Ties go in; the cut orders them.
        if score.is_nan() || score < self.floor || self.k == 0 {
            return;
        }
        self.buf.push(Hit { row, score });
        if self.buf.len() >= self.limit() {
            self.cut();
        }
    }

    /// Merges another selector (same `k`) into this one; the result is exactly the top-k of the
    /// union of both inputs.
    pub fn merge(mut self, mut other: TopK) -> TopK {
        if self.buf.len() < other.buf.len() {
            std::mem::swap(&mut self, &mut other);
        }
        for h in other.buf {
            self.push(h.row, h.score);
        }
        self
    }

    /// The kept hits, best first (higher score, then lower row).
    pub fn into_sorted(mut self) -> Vec<Hit> {
        self.cut();
        let mut v = self.buf;
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
