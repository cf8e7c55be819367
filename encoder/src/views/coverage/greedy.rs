//! The greedy choice of the coverage selection (the parent module's doc): per Gaussian the
//! chosen views counted as its distinct viewpoints, each view's gain over them, and the lazy
//! greedy order, its stale views re-evaluated together.

use std::cmp::Reverse;
use std::collections::BinaryHeap;

use glam::DVec3;
use rayon::prelude::*;

use super::{CoverageRule, SeenSet, ViewCoverage};

/// The greedy's state: per Gaussian the candidate views counted as its distinct viewpoints
/// (`min_views` slots, `u32::MAX` = empty, filled from the front).
struct Viewpoints<'a> {
    slots: Vec<u32>,
    per: usize,
    cos_max: f64,
    means: &'a [[f32; 3]],
    centres: &'a [DVec3],
    /// Per Gaussian its footprint in fixed-point steps ([`ViewCoverage`]).
    footprint: &'a [u64],
}

/// What a view adds: the footprint of its new pairs (fixed-point steps), then the pairs.
pub(in crate::views) type Gain = (u64, u64);

/// Gaussians per parallel chunk of the greedy (a multiple of 64, the bitsets' word).
const CHUNK: usize = 1 << 14;

impl Viewpoints<'_> {
    /// Whether view `v` adds a distinct viewpoint to Gaussian `g` (`slots` = `g`'s slots): `g`
    /// has fewer than `per`, and `v`'s direction to it is at least the angle away from each.
    fn adds(&self, g: usize, v: usize, slots: &[u32]) -> bool {
        if slots[self.per - 1] != u32::MAX {
            return false;
        }
        if slots[0] == u32::MAX {
            // No viewpoint yet: any view adds the first (no direction to compare).
            return true;
        }
        let m = self.means[g].map(f64::from);
        let m = DVec3::new(m[0], m[1], m[2]);
        let dir = (m - self.centres[v]).normalize_or_zero();
        slots
            .iter()
            .take_while(|&&u| u != u32::MAX)
            .all(|&u| dir.dot((m - self.centres[u as usize]).normalize_or_zero()) <= self.cos_max)
    }

    /// What view `v` (seeing `seen`) would add (integer sums: exact in any order), its
    /// Gaussians split into chunks over the threads.
    fn gain(&self, v: usize, seen: &SeenSet) -> Gain {
        let n = self.means.len();
        (0..n.div_ceil(CHUNK))
            .into_par_iter()
            .map(|c| self.gain_in(v, seen, c * CHUNK, ((c + 1) * CHUNK).min(n)))
            .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1))
    }

    /// What view `v` (seeing `seen`) would add through its Gaussians in `lo..hi` (`lo` a
    /// multiple of 64), on the calling thread.
    fn gain_in(&self, v: usize, seen: &SeenSet, lo: usize, hi: usize) -> Gain {
        let (mut weight, mut count) = (0u64, 0u64);
        seen.for_each_in(lo, hi, |g| {
            let s = &self.slots[g * self.per..(g + 1) * self.per];
            if self.adds(g, v, s) {
                weight += self.footprint[g];
                count += 1;
            }
        });
        (weight, count)
    }

    /// The gains of `views` (each seeing `seen[v]`): one view spread over the threads, several
    /// each on a thread of its own.
    fn gains(&self, views: &[usize], seen: &[SeenSet]) -> Vec<(usize, Gain)> {
        match views {
            [v] => vec![(*v, self.gain(*v, &seen[*v]))],
            _ => views
                .par_iter()
                .map(|&v| (v, self.gain_in(v, &seen[v], 0, self.means.len())))
                .collect(),
        }
    }

    /// Counts view `v` (seeing `seen`) as a viewpoint of every Gaussian it adds one to.
    fn choose(&mut self, v: usize, seen: &SeenSet) {
        let n = self.means.len();
        let per = self.per;
        let mut slots = std::mem::take(&mut self.slots);
        slots
            .par_chunks_mut(CHUNK * per)
            .enumerate()
            .for_each(|(c, chunk)| {
                let lo = c * CHUNK;
                seen.for_each_in(lo, (lo + CHUNK).min(n), |g| {
                    let s = &mut chunk[(g - lo) * per..(g - lo + 1) * per];
                    if self.adds(g, v, s)
                        && let Some(free) = s.iter_mut().find(|u| **u == u32::MAX)
                    {
                        *free = v as u32;
                    }
                });
            });
        self.slots = slots;
    }
}

/// A view in the greedy's heap: its gain when last evaluated (an upper bound of its gain now:
/// gains only fall), its index (ties to the lower), and the round it was evaluated in (current
/// when it equals the views chosen so far).
type Entry = (Gain, Reverse<usize>, usize);

/// How many stale views the greedy re-evaluates together: at most `views`, and, past the first,
/// no more than `seen` seen Gaussians in all (a view that sees many is re-evaluated alone,
/// spread over the threads, so that no thread works through a large view the lazy greedy
/// would not have needed).
#[derive(Debug, Clone, Copy)]
pub(in crate::views) struct AtOnce {
    pub(in crate::views) views: usize,
    pub(in crate::views) seen: usize,
}

impl AtOnce {
    /// Twice the threads' views, up to four chunks of Gaussians a thread.
    pub(super) fn for_threads() -> Self {
        let threads = rayon::current_num_threads().max(1);
        AtOnce {
            views: 2 * threads,
            seen: 4 * CHUNK * threads,
        }
    }
}

/// The stale view `first`, popped, and the stale views that now top `heap` after it, popped too
/// (within `at_once` for views of `sizes` seen Gaussians; none past a current view or one that
/// adds no pair), for one parallel re-evaluation. Re-evaluating more views than the lazy
/// greedy would, one at a time, changes no choice: a current view is chosen only when its gain
/// is at least every other view's bound, so the choice is the view of the largest gain now
/// (ties to the lower index), however many bounds were tightened first.
fn stale_on_top(
    heap: &mut BinaryHeap<Entry>,
    (first, round): (usize, usize),
    at_once: AtOnce,
    sizes: &[usize],
) -> Vec<usize> {
    let mut batch = vec![first];
    let mut seen = sizes[first];
    while batch.len() < at_once.views {
        match heap.peek() {
            Some(&((_, pairs), Reverse(v), r))
                if r != round && pairs > 0 && seen + sizes[v] <= at_once.seen =>
            {
                seen += sizes[v];
            }
            _ => break,
        }
        if let Some((_, Reverse(v), _)) = heap.pop() {
            batch.push(v);
        }
    }
    batch
}

/// The greedy order over the measured views (module doc): `(view index, gain)` until no view
/// adds a pair, or, with `early`, until the first view the stopping rule refuses (its gain
/// below [`CoverageRule::min_gain`] of the first; gains only fall, so no later view is kept
/// either) or `cap + 1` views, whichever comes first; and the final per-Gaussian viewpoint
/// slots (`min_views` each). Returns whether the order is complete (no view left that adds a
/// pair). Stale views are re-evaluated together within `at_once` ([`stale_on_top`]; the order
/// is the same for any [`AtOnce`]).
pub(in crate::views) fn greedy(
    coverage: &ViewCoverage,
    means: &[[f32; 3]],
    centres: &[DVec3],
    rule: &CoverageRule,
    early: Option<Option<usize>>,
    at_once: AtOnce,
) -> (Vec<(usize, Gain)>, Vec<u32>, bool) {
    let per = rule.min_views.max(1);
    let mut state = Viewpoints {
        slots: vec![u32::MAX; means.len() * per],
        per,
        cos_max: rule.min_angle_deg.to_radians().cos(),
        means,
        centres,
        footprint: &coverage.footprint,
    };
    // Max-heap on (gain, lowest index); the round tells whether the gain is current.
    let all: Vec<usize> = (0..coverage.seen.len()).collect();
    let sizes: Vec<usize> = coverage.seen.par_iter().map(SeenSet::len).collect();
    let mut heap: BinaryHeap<Entry> = state
        .gains(&all, &coverage.seen)
        .into_iter()
        .map(|(v, g)| (g, Reverse(v), 0))
        .collect();
    let mut order: Vec<(usize, Gain)> = Vec::new();
    while let Some((gain, Reverse(v), round)) = heap.pop() {
        if gain.1 == 0 {
            return (order, state.slots, true);
        }
        if round != order.len() {
            let stale = stale_on_top(&mut heap, (v, order.len()), at_once, &sizes);
            let fresh = state.gains(&stale, &coverage.seen);
            heap.extend(fresh.into_iter().map(|(u, g)| (g, Reverse(u), order.len())));
            continue;
        }
        state.choose(v, &coverage.seen[v]);
        order.push((v, gain));
        if let Some(cap) = early {
            let first = order[0].1.0;
            let refused = (gain.0 as f64) < rule.min_gain * first as f64;
            if refused || cap.is_some_and(|c| order.len() > c) {
                return (order, state.slots, heap.is_empty());
            }
        }
    }
    (order, state.slots, true)
}
