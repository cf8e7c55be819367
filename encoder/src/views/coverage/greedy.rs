//! The greedy choice of the coverage selection (the parent module's doc): per Gaussian the
//! chosen views counted as its distinct viewpoints, each view's gain over them, and the lazy
//! greedy order, its stale views re-evaluated together.
//!
//! **The greedy's order of the Gaussians.** The greedy renumbers the Gaussians in the Morton
//! order of their means ([`Renumbered`]) and holds each view's set as a sparse bitset of that
//! order ([`Words`]): a view sees a compact part of the scene, so its Gaussians fill few words
//! and their state is read in order, where the scene's own order (often random in space) reads
//! it at random. Beside the viewpoint slots it keeps one bit per Gaussian that still lacks
//! viewpoints, so a gain skips the Gaussians no view can add to 64 at a time. A gain is an integer sum over
//! Gaussians, each term depending on that Gaussian alone, so neither changes a gain or a choice.
//! Its memory: the words (each view's set freed as its words are made), and per Gaussian 28 bytes
//! beside its `4 · min_views` of slots (the order, the means and footprints in it, one bit).

use std::cmp::Reverse;
use std::collections::BinaryHeap;
use std::ops::Range;

use glam::DVec3;
use rayon::prelude::*;

use super::{CoverageRule, SeenSet, ViewCoverage};

/// A view's Gaussians in the greedy's order as a sparse bitset: the indices of the words that
/// hold any of them, ascending, and those words (bit `g % 64` of word `g / 64`).
#[derive(Debug, Default)]
struct Words {
    at: Vec<u32>,
    bits: Vec<u64>,
}

impl Words {
    /// The Gaussians of `set` below `n` by their greedy indices `local_of`.
    fn of(set: &SeenSet, n: usize, local_of: &[u32]) -> Self {
        let mut ids = Vec::with_capacity(set.len());
        set.for_each_in(0, n, |k| ids.push(local_of[k]));
        ids.sort_unstable();
        let mut words = Words::default();
        for id in ids {
            let (w, bit) = (id / 64, 1u64 << (id % 64));
            match (words.at.last(), words.bits.last_mut()) {
                (Some(&last), Some(bits)) if last == w => *bits |= bit,
                _ => {
                    words.at.push(w);
                    words.bits.push(bit);
                }
            }
        }
        words.at.shrink_to_fit();
        words.bits.shrink_to_fit();
        words
    }

    /// Gaussians in the set.
    fn len(&self) -> usize {
        self.bits.iter().map(|b| b.count_ones() as usize).sum()
    }
}

/// The measured sets in the greedy's order of the Gaussians (module doc).
struct Renumbered {
    /// Per scene Gaussian its index in the greedy's order.
    local_of: Vec<u32>,
    /// Per greedy index its Gaussian's mean, world frame.
    means: Vec<[f32; 3]>,
    /// Per greedy index its Gaussian's footprint, fixed-point steps ([`ViewCoverage`]).
    footprint: Vec<u64>,
    /// Per view its Gaussians by greedy index.
    words: Vec<Words>,
}

impl Renumbered {
    /// The sets `seen` (each freed once converted) with the `footprint`s of the scene Gaussians
    /// of `means` (ids at or past `means.len()` left out), renumbered in the Morton order of the
    /// means.
    fn new(seen: Vec<SeenSet>, footprint: &[u64], means: &[[f32; 3]]) -> Self {
        let n = means.len();
        let order = morton_order(means);
        let mut local_of = vec![0u32; n];
        for (l, &k) in order.iter().enumerate() {
            local_of[k as usize] = l as u32;
        }
        let footprint = order
            .par_iter()
            .map(|&k| footprint.get(k as usize).copied().unwrap_or(0))
            .collect();
        let means = order.par_iter().map(|&k| means[k as usize]).collect();
        drop(order);
        let words = seen
            .into_par_iter()
            .map(|set| Words::of(&set, n, &local_of))
            .collect();
        Renumbered {
            local_of,
            means,
            footprint,
            words,
        }
    }

    /// The slots `slots` (`per` per Gaussian, greedy order) in the scene's order.
    fn scene_slots(&self, slots: &[u32], per: usize) -> Vec<u32> {
        let mut out = vec![u32::MAX; self.local_of.len() * per];
        out.par_chunks_mut(per)
            .zip(self.local_of.par_iter())
            .for_each(|(o, &l)| o.copy_from_slice(&slots[l as usize * per..][..per]));
        out
    }
}

/// The scene indices of `means` in the Morton order of their quantized means (21 bits an axis
/// over the means' box), ties to the lower index; non-finite coordinates count as the box's
/// lower side.
fn morton_order(means: &[[f32; 3]]) -> Vec<u32> {
    let (lo, hi) = means
        .par_iter()
        .fold(
            || ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]),
            |(mut lo, mut hi), m| {
                for a in 0..3 {
                    if m[a].is_finite() {
                        lo[a] = lo[a].min(m[a]);
                        hi[a] = hi[a].max(m[a]);
                    }
                }
                (lo, hi)
            },
        )
        .reduce(
            || ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]),
            |a, b| {
                let lo = std::array::from_fn(|i| a.0[i].min(b.0[i]));
                let hi = std::array::from_fn(|i| a.1[i].max(b.1[i]));
                (lo, hi)
            },
        );
    const TOP: f64 = ((1u64 << 21) - 1) as f64;
    let code = |m: &[f32; 3]| {
        (0..3).fold(0u64, |c, a| {
            let span = (f64::from(hi[a]) - f64::from(lo[a])).max(f64::MIN_POSITIVE);
            let t = (f64::from(m[a]) - f64::from(lo[a])) / span;
            // `as` takes NaN to 0 and clamps.
            c | spread((t * TOP).clamp(0.0, TOP) as u64) << a
        })
    };
    let mut keyed: Vec<(u64, u32)> = means
        .par_iter()
        .enumerate()
        .map(|(k, m)| (code(m), k as u32))
        .collect();
    keyed.par_sort_unstable();
    keyed.into_par_iter().map(|(_, k)| k).collect()
}

/// The low 21 bits of `x` spread to every third bit.
fn spread(x: u64) -> u64 {
    let mut x = x & 0x1f_ffff;
    x = (x | x << 32) & 0x001f_0000_0000_ffff;
    x = (x | x << 16) & 0x001f_0000_ff00_00ff;
    x = (x | x << 8) & 0x100f_00f0_0f00_f00f;
    x = (x | x << 4) & 0x10c3_0c30_c30c_30c3;
    x = (x | x << 2) & 0x1249_2492_4924_9249;
    x
}

/// The greedy's state, in its order of the Gaussians: per Gaussian the candidate views counted
/// as its distinct viewpoints (`min_views` slots, `u32::MAX` = empty, filled from the front).
struct Viewpoints<'a> {
    slots: Vec<u32>,
    /// Bit `g`: Gaussian `g` has fewer than `per` viewpoints (a view may still add one).
    open: Vec<u64>,
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

    /// What view `v` would add through its Gaussians in the words `part` of `seen`, on the
    /// calling thread.
    fn gain_in(&self, v: usize, seen: &Words, part: Range<usize>) -> Gain {
        let (mut weight, mut count) = (0u64, 0u64);
        for (&w, &bits) in seen.at[part.clone()].iter().zip(&seen.bits[part]) {
            let w = w as usize;
            let mut bits = bits & self.open[w];
            while bits != 0 {
                let g = w * 64 + bits.trailing_zeros() as usize;
                bits &= bits - 1;
                if self.adds(g, v, &self.slots[g * self.per..(g + 1) * self.per]) {
                    weight += self.footprint[g];
                    count += 1;
                }
            }
        }
        (weight, count)
    }

    /// What view `v` (seeing `seen`) would add (integer sums: exact in any order), its words
    /// split over the threads.
    fn gain(&self, v: usize, seen: &Words) -> Gain {
        let len = seen.at.len();
        let step = len.div_ceil(8 * rayon::current_num_threads().max(1)).max(1);
        (0..len.div_ceil(step))
            .into_par_iter()
            .map(|p| self.gain_in(v, seen, p * step..((p + 1) * step).min(len)))
            .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1))
    }

    /// The gains of `views` (view `v` seeing `seen[v]`): one view spread over the threads,
    /// several each on a thread of its own.
    fn gains(&self, views: &[usize], seen: &[Words]) -> Vec<(usize, Gain)> {
        match views {
            [v] => vec![(*v, self.gain(*v, &seen[*v]))],
            _ => views
                .par_iter()
                .map(|&v| (v, self.gain_in(v, &seen[v], 0..seen[v].at.len())))
                .collect(),
        }
    }

    /// Counts view `v` (seeing `seen`) as a viewpoint of every Gaussian it adds one to, and
    /// closes those it gives their last one.
    fn choose(&mut self, v: usize, seen: &Words) {
        let per = self.per;
        let mut slots = std::mem::take(&mut self.slots);
        let mut open = std::mem::take(&mut self.open);
        slots
            .par_chunks_mut(CHUNK * per)
            .zip(open.par_chunks_mut(CHUNK / 64))
            .enumerate()
            .for_each(|(c, (chunk, words))| {
                let (lo, first_word) = (c * CHUNK, c * (CHUNK / 64));
                let first = seen.at.partition_point(|&w| (w as usize) < first_word);
                let at = seen.at[first..]
                    .iter()
                    .take_while(|&&w| (w as usize) < first_word + CHUNK / 64);
                for (&w, &bits) in at.zip(&seen.bits[first..]) {
                    let w = w as usize - first_word;
                    let mut bits = bits & words[w];
                    while bits != 0 {
                        let i = w * 64 + bits.trailing_zeros() as usize;
                        bits &= bits - 1;
                        let s = &mut chunk[i * per..(i + 1) * per];
                        if self.adds(lo + i, v, s)
                            && let Some(free) = s.iter_mut().find(|u| **u == u32::MAX)
                        {
                            *free = v as u32;
                            if s[per - 1] != u32::MAX {
                                words[w] &= !(1u64 << (i % 64));
                            }
                        }
                    }
                }
            });
        self.slots = slots;
        self.open = open;
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
/// slots (`min_views` each, the scene's order of `means`). Returns whether the order is complete
/// (no view left that adds a pair). Stale views are re-evaluated together within `at_once`
/// ([`stale_on_top`]; the order is the same for any [`AtOnce`]).
///
/// Takes the views' sets out of `coverage` (left with none: [`ViewCoverage::views`] 0), each
/// freed once the greedy holds it as [`Words`], so that the two forms are not held whole at
/// once.
pub(in crate::views) fn greedy(
    coverage: &mut ViewCoverage,
    means: &[[f32; 3]],
    centres: &[DVec3],
    rule: &CoverageRule,
    early: Option<Option<usize>>,
    at_once: AtOnce,
) -> (Vec<(usize, Gain)>, Vec<u32>, bool) {
    let per = rule.min_views.max(1);
    let seen = std::mem::take(&mut coverage.seen);
    let local = Renumbered::new(seen, &coverage.footprint, means);
    let n = means.len();
    let mut open = vec![!0u64; n.div_ceil(64)];
    if let Some(last) = open.last_mut()
        && n % 64 != 0
    {
        *last = (1u64 << (n % 64)) - 1;
    }
    let mut state = Viewpoints {
        slots: vec![u32::MAX; n * per],
        open,
        per,
        cos_max: rule.min_angle_deg.to_radians().cos(),
        means: &local.means,
        centres,
        footprint: &local.footprint,
    };
    let (order, complete) = lazy_order(&mut state, &local.words, rule, early, at_once);
    let slots = local.scene_slots(&state.slots, per);
    (order, slots, complete)
}

/// Bytes of the sparse bitsets the greedy holds for the sets of `coverage` over the Gaussians
/// of `means` (for the bench).
#[cfg(test)]
pub(super) fn words_bytes(coverage: &ViewCoverage, means: &[[f32; 3]]) -> usize {
    let local = Renumbered::new(coverage.seen.clone(), &coverage.footprint, means);
    let words: usize = local.words.iter().map(|w| w.at.len()).sum();
    words * (size_of::<u32>() + size_of::<u64>())
}

/// The lazy greedy over the views seeing `seen` from `state` (as [`greedy`]): the order, and
/// whether it is complete.
fn lazy_order(
    state: &mut Viewpoints,
    seen: &[Words],
    rule: &CoverageRule,
    early: Option<Option<usize>>,
    at_once: AtOnce,
) -> (Vec<(usize, Gain)>, bool) {
    // Max-heap on (gain, lowest index); the round tells whether the gain is current.
    let all: Vec<usize> = (0..seen.len()).collect();
    let sizes: Vec<usize> = seen.iter().map(Words::len).collect();
    let mut heap: BinaryHeap<Entry> = state
        .gains(&all, seen)
        .into_iter()
        .map(|(v, g)| (g, Reverse(v), 0))
        .collect();
    let mut order: Vec<(usize, Gain)> = Vec::new();
    while let Some((gain, Reverse(v), round)) = heap.pop() {
        if gain.1 == 0 {
            return (order, true);
        }
        if round != order.len() {
            let stale = stale_on_top(&mut heap, (v, order.len()), at_once, &sizes);
            let fresh = state.gains(&stale, seen);
            heap.extend(fresh.into_iter().map(|(u, g)| (g, Reverse(u), order.len())));
            continue;
        }
        state.choose(v, &seen[v]);
        order.push((v, gain));
        if let Some(cap) = early {
            let first = order[0].1.0;
            let refused = (gain.0 as f64) < rule.min_gain * first as f64;
            if refused || cap.is_some_and(|c| order.len() > c) {
                return (order, heap.is_empty());
            }
        }
    }
    (order, true)
}
