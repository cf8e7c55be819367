//! The greedy choice of the coverage selection (the parent module's doc): per Gaussian the
//! chosen views counted as its distinct viewpoints, each view's gain over them, and the lazy
//! greedy order, its stale views re-evaluated together.
//!
//! Whether a view adds a viewpoint to a Gaussian only ever turns from yes to no (slots fill up
//! and are never emptied, and a direction too close to a counted one stays too close). So once
//! a view has been re-evaluated, the Gaussians it no longer adds to are dropped from its list
//! ([`Live`]): later re-evaluations, the bulk of the greedy on a large scene, walk only the
//! Gaussians that can still count. The gains are the same integers, so the order is too.

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

/// The Gaussians an evaluation of a view walks: its seen set, or its live list ([`Live`]).
#[derive(Clone, Copy)]
enum Source<'a> {
    Seen(&'a SeenSet),
    Live(&'a [u32]),
}

impl Source<'_> {
    /// Calls `f` with every id in `lo..hi` (`lo` a multiple of 64), ascending.
    fn for_each_in(self, lo: usize, hi: usize, mut f: impl FnMut(usize)) {
        match self {
            Source::Seen(seen) => seen.for_each_in(lo, hi, f),
            Source::Live(ids) => {
                let start = ids.partition_point(|&i| (i as usize) < lo);
                ids[start..]
                    .iter()
                    .take_while(|&&i| (i as usize) < hi)
                    .for_each(|&i| f(i as usize));
            }
        }
    }
}

/// Gaussians per parallel chunk of the greedy (a multiple of 64, the bitsets' word).
const CHUNK: usize = 1 << 14;

/// A re-evaluated view keeps the list of the Gaussians it still adds to when the list is at
/// most 1 / this of what it walked (bounding the lists' memory by a quarter of the seen sets).
const LIVE_SHARE: usize = 4;

/// Per view, the ascending ids of the Gaussians it may still add a viewpoint to (`None`: its
/// whole seen set). Each list holds every Gaussian the view adds to now.
type Live = Vec<Option<Vec<u32>>>;

/// What the greedy walked: gain evaluations, the Gaussians they visited, and how many of them
/// left a narrowed live list.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(in crate::views) struct GreedyWork {
    pub(in crate::views) evaluations: u64,
    pub(in crate::views) visited: u64,
    pub(in crate::views) lists_kept: u64,
}

/// One evaluation of a view: its gain, the Gaussians walked and, when asked for, the ids it
/// adds to (ascending).
struct Evaluated {
    gain: Gain,
    walked: u64,
    adding: Option<Vec<u32>>,
}

impl Evaluated {
    fn empty(keep: bool) -> Self {
        Evaluated {
            gain: (0, 0),
            walked: 0,
            adding: keep.then(Vec::new),
        }
    }

    /// `self` then `next` (the ids of `next` follow `self`'s).
    fn then(mut self, next: Evaluated) -> Self {
        self.gain = (self.gain.0 + next.gain.0, self.gain.1 + next.gain.1);
        self.walked += next.walked;
        if let (Some(a), Some(b)) = (self.adding.as_mut(), next.adding) {
            a.extend(b);
        }
        self
    }
}

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

    /// Evaluates view `v` over its Gaussians in `lo..hi` that may still count (`lo` a multiple
    /// of 64; `from`: its live list, else its seen set), on the calling thread.
    fn evaluate_in(
        &self,
        v: usize,
        from: Source<'_>,
        lo: usize,
        hi: usize,
        keep: bool,
    ) -> Evaluated {
        let mut out = Evaluated::empty(keep);
        let mut visit = |g: usize| {
            out.walked += 1;
            let s = &self.slots[g * self.per..(g + 1) * self.per];
            if self.adds(g, v, s) {
                out.gain.0 += self.footprint[g];
                out.gain.1 += 1;
                if let Some(a) = out.adding.as_mut() {
                    a.push(g as u32);
                }
            }
        };
        from.for_each_in(lo, hi, &mut visit);
        out
    }

    /// What view `v` would add (integer sums: exact in any order), its Gaussians split into
    /// chunks over the threads.
    fn evaluate(&self, v: usize, from: Source<'_>, keep: bool) -> Evaluated {
        let n = self.means.len();
        (0..n.div_ceil(CHUNK))
            .into_par_iter()
            .map(|c| self.evaluate_in(v, from, c * CHUNK, ((c + 1) * CHUNK).min(n), keep))
            .collect::<Vec<_>>()
            .into_iter()
            .fold(Evaluated::empty(keep), Evaluated::then)
    }

    /// The gains of `views`, each spread over the threads in chunks of Gaussians (rayon
    /// balances the chunks of several views: a view's short live list leaves no thread idle
    /// while another's long seen set is walked). With `live` (and its share), each view's live list is narrowed to the Gaussians it
    /// adds to now when that list is at most 1 / share of what was walked ([`LIVE_SHARE`]);
    /// `work` counts what was walked.
    fn gains(
        &self,
        views: &[usize],
        seen: &[SeenSet],
        mut live: Option<(&mut Live, usize)>,
        work: &mut GreedyWork,
    ) -> Vec<(usize, Gain)> {
        let keep = live.is_some();
        let source = |v: usize| match live.as_ref().and_then(|(l, _)| l[v].as_deref()) {
            Some(ids) => Source::Live(ids),
            None => Source::Seen(&seen[v]),
        };
        let evaluated: Vec<(usize, Evaluated)> = views
            .par_iter()
            .map(|&v| (v, self.evaluate(v, source(v), keep)))
            .collect();
        work.evaluations += evaluated.len() as u64;
        evaluated
            .into_iter()
            .map(|(v, e)| {
                work.visited += e.walked;
                if let (Some((live, share)), Some(adding)) = (live.as_mut(), e.adding)
                    && adding.len() * *share <= e.walked as usize
                {
                    live[v] = Some(adding);
                    work.lists_kept += 1;
                }
                (v, e.gain)
            })
            .collect()
    }

    /// Counts view `v` as a viewpoint of every Gaussian it adds one to (walking `from`).
    fn choose(&mut self, v: usize, from: Source<'_>) {
        let n = self.means.len();
        let per = self.per;
        let mut slots = std::mem::take(&mut self.slots);
        slots
            .par_chunks_mut(CHUNK * per)
            .enumerate()
            .for_each(|(c, chunk)| {
                let lo = c * CHUNK;
                let mut count = |g: usize| {
                    let s = &mut chunk[(g - lo) * per..(g - lo + 1) * per];
                    if self.adds(g, v, s)
                        && let Some(free) = s.iter_mut().find(|u| **u == u32::MAX)
                    {
                        *free = v as u32;
                    }
                };
                from.for_each_in(lo, (lo + CHUNK).min(n), &mut count);
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
    let live = Some(LIVE_SHARE);
    let (result, work) = greedy_counted(coverage, (means, centres), rule, early, at_once, live);
    tracing::debug!(
        evaluations = work.evaluations,
        visited = work.visited,
        lists_kept = work.lists_kept,
        "coverage greedy"
    );
    result
}

/// [`greedy`], with the live lists ([`Live`], kept at `live_share` as [`LIVE_SHARE`]) or without
/// (`None`): the same order either way; and what it walked.
pub(in crate::views) fn greedy_counted(
    coverage: &ViewCoverage,
    (means, centres): (&[[f32; 3]], &[DVec3]),
    rule: &CoverageRule,
    early: Option<Option<usize>>,
    at_once: AtOnce,
    live_share: Option<usize>,
) -> ((Vec<(usize, Gain)>, Vec<u32>, bool), GreedyWork) {
    let per = rule.min_views.max(1);
    let mut state = Viewpoints {
        slots: vec![u32::MAX; means.len() * per],
        per,
        cos_max: rule.min_angle_deg.to_radians().cos(),
        means,
        centres,
        footprint: &coverage.footprint,
    };
    let mut work = GreedyWork::default();
    let mut live: Live = vec![None; coverage.seen.len()];
    // Max-heap on (gain, lowest index); the round tells whether the gain is current. The first
    // evaluation finds every Gaussian adding (no viewpoint yet): no list to narrow.
    let all: Vec<usize> = (0..coverage.seen.len()).collect();
    let mut sizes: Vec<usize> = coverage.seen.par_iter().map(SeenSet::len).collect();
    let mut heap: BinaryHeap<Entry> = state
        .gains(&all, &coverage.seen, None, &mut work)
        .into_iter()
        .map(|(v, g)| (g, Reverse(v), 0))
        .collect();
    let mut order: Vec<(usize, Gain)> = Vec::new();
    let done =
        |order, state: Viewpoints<'_>, complete, work| ((order, state.slots, complete), work);
    while let Some((gain, Reverse(v), round)) = heap.pop() {
        if gain.1 == 0 {
            return done(order, state, true, work);
        }
        if round != order.len() {
            let stale = stale_on_top(&mut heap, (v, order.len()), at_once, &sizes);
            let lists = live_share.map(|share| (&mut live, share.max(1)));
            let fresh = state.gains(&stale, &coverage.seen, lists, &mut work);
            for &u in &stale {
                if let Some(ids) = &live[u] {
                    sizes[u] = ids.len();
                }
            }
            heap.extend(fresh.into_iter().map(|(u, g)| (g, Reverse(u), order.len())));
            continue;
        }
        let from = match &live[v] {
            Some(ids) => Source::Live(ids),
            None => Source::Seen(&coverage.seen[v]),
        };
        state.choose(v, from);
        // A chosen view adds nothing more to any Gaussian: its list is no longer needed.
        live[v] = None;
        order.push((v, gain));
        if let Some(cap) = early {
            let first = order[0].1.0;
            let refused = (gain.0 as f64) < rule.min_gain * first as f64;
            if refused || cap.is_some_and(|c| order.len() > c) {
                let complete = heap.is_empty();
                return done(order, state, complete, work);
            }
        }
    }
    done(order, state, true, work)
}
