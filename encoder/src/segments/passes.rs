//! The two Felzenszwalb–Huttenlocher passes over the tiles' edges (module doc, "Bounded memory
//! and parallel passes: tiles"). The border edges are weighed first. A tile's inner edges join
//! only its own Gaussians, and before the border edges every component lies in one tile: so the
//! tiles' criterion passes are independent and run in parallel, each on a forest of its own over
//! the tile's Gaussians (local ids keep the order of the scene's ids, so the edge order, the joins
//! and the roots are those of one forest over the scene), each noting the components its ends of
//! border edges meet where those edges fall in its order. Their forests then make the scene's
//! forest, which takes the border edges by those components and the minimum-size pass.
//! That pass runs over each tile's edges in order, then over the border edges. Of a tile's
//! edges it needs only those that its tile's pass picks, in parallel, right after the tile's
//! criterion pass: still between two components, with an end in one below the minimum size
//! ([`may_join_later`]), and not refused by the mask veto; and of those, the first between each
//! pair of the tile's components ([`first_per_pair`]). Components only grow, so the pass would
//! skip the others; and the picking, the veto's reads of the scene's record included, runs
//! beside the other tiles' passes instead of after them all.
//! While one wave of tiles runs its criterion passes, the next wave's edges are weighed
//! and sorted on the other threads.

use std::time::Instant;

use rayon::prelude::*;

use super::forest::{Component, Forest};
use super::graph::{EdgeSource, TileMembers, border_edges, tile_edges};
use super::regions::Regions;
use super::weights::{Edge, Weigher};
use super::{SegmentControl, SegmentParams, SegmentTimings};

/// One tile's criterion pass: each of its Gaussians' root and component (local ids), the
/// components its ends of border edges met where each edge stands in the order (`(k, side,
/// component)`: edge `k` of the scene's border edges, side 0 for its end `i`, 1 for `j`), the
/// edges the minimum-size pass could join across (the first per pair of components,
/// [`first_per_pair`]; scene ids, in order), its edge count, and the seconds of
/// its edges' weights, their sort, the pass and the pick.
struct TilePass {
    roots: Vec<u32>,
    components: Vec<Component>,
    met: Vec<(u32, usize, Component)>,
    kept: Vec<Edge>,
    inner: u64,
    seconds: [f64; 4],
}

/// One tile's inner edges, weighed and sorted (local ids), waiting for its criterion pass; the
/// seconds of the weights and of the sort.
struct BuiltTile {
    t: u32,
    inner: Vec<Edge>,
    seconds: [f64; 2],
}

/// Tile `t`'s inner edges with their weights (on all the pool's threads), sorted by `(w, i, j)`
/// in parallel (a total order: the same order whatever the threads).
fn build_tile(t: u32, src: &EdgeSource, w: &Weigher) -> BuiltTile {
    let clock = Instant::now();
    let mut inner = tile_edges(t, src, w);
    let edges_s = clock.elapsed().as_secs_f64();
    let clock = Instant::now();
    inner.par_sort_unstable();
    BuiltTile {
        t,
        inner,
        seconds: [edges_s, clock.elapsed().as_secs_f64()],
    }
}

/// Where each of `ends` (`(k, node)`: border edge `k` of `border`, its end `node` of the tile,
/// ascending in `k`) stands in the tile's sorted `edges`: the count of edges before border edge
/// `k` in the order `(w, i, j)` of scene ids (`id` maps an edge's ids to the scene's), with
/// `node` as given.
fn stops_in(
    edges: &[Edge],
    border: &[Edge],
    ends: &[(u32, u32)],
    id: impl Fn(u32) -> u32,
) -> Vec<(usize, u32)> {
    let mut at = 0;
    ends.iter()
        .map(|&(k, node)| {
            let b = &border[k as usize];
            at += edges[at..].partition_point(|e| (e.w, id(e.i), id(e.j)) < (b.w, b.i, b.j));
            (at, node)
        })
        .collect()
}

/// Each tile's ends of the border edges (`border`, scene ids, ascending): `(k, local id)` per
/// end in the tile, ascending in `k`.
fn border_ends(border: &[Edge], tm: &TileMembers) -> Vec<Vec<(u32, u32)>> {
    let mut ends = vec![Vec::new(); tm.members.len()];
    for (k, e) in border.iter().enumerate() {
        for end in [e.i, e.j] {
            let (t, l) = tm.place[end as usize];
            ends[t as usize].push((k as u32, l));
        }
    }
    ends
}

impl BuiltTile {
    /// The tile's criterion pass (one thread), on a forest of its own over its `members` (scene
    /// ids, ascending), noting the components its `ends` of the scene's `border` edges meet
    /// where each border edge stands in the order ([`Forest::criterion_pass_with_stops`]), then
    /// its edges for the minimum-size pass, picked in parallel: of the edges the pass could
    /// join across ([`may_join_later`], [`Weigher::may_absorb`]), the first per pair of its
    /// components ([`first_per_pair`]).
    fn criterion(
        self,
        w: &Weigher,
        members: &[u32],
        (border, ends): (&[Edge], &[(u32, u32)]),
    ) -> TilePass {
        let p = w.p;
        let clock = Instant::now();
        let mut f = Forest::singletons(members.len());
        let stops = stops_in(&self.inner, border, ends, |l| members[l as usize]);
        let at_stops = f.criterion_pass_with_stops(&self.inner, p.threshold, &stops, None);
        let side = |k: u32, l: u32| usize::from(border[k as usize].i != members[l as usize]);
        let met = ends
            .iter()
            .zip(at_stops)
            .map(|(&(k, l), c)| (k, side(k, l), c))
            .collect();
        let criterion_s = clock.elapsed().as_secs_f64();
        let clock = Instant::now();
        // Each element's root once, so that the pick reads one entry per end, not a path; and
        // whether its component is below the minimum size, one byte per element, so that the
        // many edges between two large components are refused without reading their roots.
        let (roots, components) = f.into_roots();
        let small: Vec<bool> = roots
            .par_iter()
            .map(|&r| components[r as usize].size() < p.min_size)
            .collect();
        let lookup = (|l: u32| roots[l as usize], |l: u32| small[l as usize]);
        let global = |e: &Edge| e.mapped(|l| members[l as usize]);
        let kept = if p.min_size > 1 {
            let tests = (
                |e: &Edge| may_join_later(&lookup, e),
                |e: &Edge| w.may_absorb(&global(e)),
            );
            first_per_pair(&self.inner, lookup.0, tests)
                .iter()
                .map(global)
                .collect()
        } else {
            Vec::new()
        };
        let [edges_s, sort_s] = self.seconds;
        TilePass {
            roots,
            components,
            met,
            kept,
            inner: self.inner.len() as u64,
            seconds: [edges_s, sort_s, criterion_s, clock.elapsed().as_secs_f64()],
        }
    }
}

/// The edges of `edges` (in order, in their own ids; `id` maps their ends to scene ids) that
/// the minimum-size pass could join across once the forest (`root` of each element, and
/// whether an element's component is `small`, below [`SegmentParams::min_size`]) has grown
/// further, picked in parallel:
/// those between two components with an end in one of fewer than
/// [`SegmentParams::min_size`] Gaussians now that `w` lets it join ([`Weigher::may_absorb`],
/// checked last: it reads the scene's record). The pass over them alone joins what the pass
/// over all of `edges` joins: components only grow, so an edge inside one component or
/// between two of the minimum size or more now never qualifies, and the mask veto is the
/// edge's own. None with a minimum size of 1 (no such pass).
fn min_size_candidates(
    (root, small): (impl Fn(u32) -> u32 + Sync, impl Fn(u32) -> bool + Sync),
    edges: &[Edge],
    w: &Weigher,
    id: impl Fn(u32) -> u32 + Sync,
) -> Vec<Edge> {
    let min = w.p.min_size;
    if min <= 1 {
        return Vec::new();
    }
    let global = |e: &Edge| e.mapped(&id);
    let lookup = (root, small);
    let candidates: Vec<Edge> = edges
        .par_iter()
        .filter(|e| may_join_later(&lookup, e))
        .copied()
        .collect();
    // The veto reads both ends' rows of the scene's record, at random places: each chunk's
    // edges prefetch the rows of the edge some edges ahead of them.
    candidates
        .par_chunks(4096)
        .flat_map_iter(|chunk| {
            chunk.iter().enumerate().filter_map(|(k, e)| {
                if let Some(ahead) = chunk.get(k + RECORD_PREFETCH_AHEAD) {
                    w.prefetch_ends(&global(ahead));
                }
                w.may_absorb(&global(e)).then_some(*e)
            })
        })
        .collect()
}

/// Whether the minimum-size pass could still join across `e` once the forest (`root` of each
/// element, and whether an element's component is `small`, below [`SegmentParams::min_size`])
/// has grown further, as far as the forest tells: `e` lies between two components, one of them
/// small. Components only grow, so an edge inside one component or between two of the minimum
/// size or more never qualifies later.
fn may_join_later((root, small): &(impl Fn(u32) -> u32, impl Fn(u32) -> bool), e: &Edge) -> bool {
    (small(e.i) || small(e.j)) && root(e.i) != root(e.j)
}

/// The first edge of `edges` (in order) between each pair of components (`root` of each end:
/// the components of the forest the edges are picked on) of those that are `candidate` (for
/// the minimum-size pass: [`may_join_later`]) and that `absorbs` (the mask veto,
/// [`Weigher::may_absorb`]); the edges after it between the same two components go. The
/// minimum-size pass would pass them by without a join: when the first comes, its two
/// components are already one (and stay one), or it joins them, or neither is below the
/// minimum size (and neither ever will be again, since components only grow); and the mask
/// veto is each edge's own. Not for a pass with the regions' veto, whose answer for two
/// components may change as they grow. The pass's edges shrink many times over (about 29 times
/// on a 2M terrain), and so do the memory and the one-thread time of the pass after the tiles.
///
/// In parallel over chunks of [`PICK_CHUNK`] edges, each keeping its first edge per pair, then
/// the first of all in order. `absorbs`, which reads the scene's record at two random places,
/// is asked of a candidate only while its chunk holds no edge of its pair yet: about once per
/// pair and chunk instead of once per candidate (a 2M tile of 17.5M edges: 2,502,994
/// candidates, 86,942 pairs; the pick took 0.28 s where the veto of every candidate, then the
/// first per pair, took 0.43–0.46 s, two threads).
pub(super) fn first_per_pair(
    edges: &[Edge],
    root: impl Fn(u32) -> u32 + Sync,
    (candidate, absorbs): (impl Fn(&Edge) -> bool + Sync, impl Fn(&Edge) -> bool + Sync),
) -> Vec<Edge> {
    let pair = |e: &Edge| {
        let (a, b) = (root(e.i), root(e.j));
        u64::from(a.min(b)) << 32 | u64::from(a.max(b))
    };
    let firsts: Vec<Vec<Edge>> = edges
        .par_chunks(PICK_CHUNK)
        .map(|chunk| {
            let mut kept = rustc_hash::FxHashSet::default();
            let first = |e: &&Edge| {
                let key = pair(e);
                !kept.contains(&key) && absorbs(e) && kept.insert(key)
            };
            chunk
                .iter()
                .filter(|e| candidate(e))
                .filter(first)
                .copied()
                .collect()
        })
        .collect();
    let mut seen = rustc_hash::FxHashSet::default();
    firsts
        .into_iter()
        .flatten()
        .filter(|e| seen.insert(pair(e)))
        .collect()
}

/// The edges per chunk of [`first_per_pair`]: large enough that a chunk meets most of its
/// pairs more than once (smaller chunks ask the veto nearly once per candidate: 0.51–0.53 s on
/// the tile above with chunks of 65,536 edges).
pub(super) const PICK_CHUNK: usize = 1 << 20;

/// How many edges ahead the pick prefetches the record rows of an edge's ends
/// ([`Weigher::prefetch_ends`]): far enough for the misses to land before the edge comes.
const RECORD_PREFETCH_AHEAD: usize = 8;

/// How many tiles may hold their edges at once: the pool's threads, fewer where the largest
/// tile's bytes at `bytes_per_gaussian` would pass `budget` (the control's in-flight bytes,
/// [`super::TILES_IN_FLIGHT_BYTES`] by default); at least one.
fn tiles_at_once(tm: &TileMembers, bytes_per_gaussian: usize, budget: usize) -> usize {
    let largest = tm.members.iter().map(Vec::len).max().unwrap_or(0);
    let bytes = (largest * bytes_per_gaussian).max(1);
    rayon::current_num_threads().min(budget / bytes).max(1)
}

/// What a tile in flight holds per Gaussian, as far as the tiles built so far tell: its edges
/// (the most per Gaussian of any tile built, a quarter more for the tiles to come; `2k`, the
/// most there can be, before any) and its rows of the record (`record_bytes`).
struct InFlight {
    most_edges: f64,
    k: usize,
    record_bytes: usize,
}

impl InFlight {
    fn bytes_per_gaussian(&self) -> usize {
        let edges = if self.most_edges > 0.0 {
            (1.25 * self.most_edges).min(2.0 * self.k as f64)
        } else {
            2.0 * self.k as f64
        };
        (edges * std::mem::size_of::<Edge>() as f64).ceil() as usize + self.record_bytes
    }

    fn saw(&mut self, built: &[BuiltTile], tm: &TileMembers) {
        for b in built {
            let members = tm.members[b.t as usize].len().max(1) as f64;
            let edges = b.inner.len() as f64 / members;
            self.most_edges = self.most_edges.max(edges);
        }
    }
}

/// The tiles' criterion passes: the scene's forest after them, the components each border
/// edge's ends (`i`, `j`) met where it stands in the order, each tile's edges that the
/// minimum-size pass could join across ([`min_size_candidates`] in the tiles one after the other,
/// [`first_per_pair`] in the tiles on forests of their own; scene ids, in order) and the inner
/// edges' count.
struct Tiled {
    forest: Forest,
    met: Vec<[Component; 2]>,
    kept: Vec<Vec<Edge>>,
    inner: u64,
}

/// The two passes (module doc) over a scene of `gaussians` Gaussians: its forest (`None` once
/// stopped), the edge count and the border-edge count; their stages' seconds added to `st` (the
/// tiles', summed over tiles).
pub(super) fn merge(
    gaussians: usize,
    p: &SegmentParams,
    ctl: &SegmentControl,
    w: &Weigher,
    src: &EdgeSource,
    st: &mut SegmentTimings,
) -> (Option<Forest>, u64, u64) {
    let tm = src.ids;
    let mut regions = w
        .masks
        .filter(|_| p.region_veto < 1.0)
        .map(|r| ctl.run(|| Regions::new(r, p.region_veto)));
    let clock = Instant::now();
    let border = ctl.run(|| border_edges(src, w));
    st.weights += clock.elapsed().as_secs_f64();
    if ctl.stopped() {
        return (None, 0, 0);
    }
    let run = Run {
        gaussians,
        p,
        ctl,
        w,
        src,
        tm,
        ends: border_ends(&border, tm),
        border: &border,
    };
    let tiled = match regions.as_mut() {
        None => run.parallel_tiles(st),
        Some(r) => run.serial_tiles(r, st),
    };
    let Some(Tiled {
        mut forest,
        met,
        kept,
        inner,
    }) = tiled
    else {
        return (None, 0, 0);
    };
    st.tile_passes = clock.elapsed().as_secs_f64();
    crate::memory::log_rss("segments: tile passes");
    let clock = Instant::now();
    forest.border_pass_in(&border, &met, p.threshold, regions.as_mut());
    st.criterion += clock.elapsed().as_secs_f64();
    if p.min_size > 1 {
        let clock = Instant::now();
        let kept_count: usize = kept.iter().map(Vec::len).sum();
        // Each tile's list is freed once passed.
        for edges in kept {
            forest.min_size_pass_in(&edges, p.min_size, |_| true, regions.as_mut());
        }
        let allowed = |e: &Edge| w.may_absorb(e);
        forest.min_size_pass_in(&border, p.min_size, allowed, regions.as_mut());
        st.min_size += clock.elapsed().as_secs_f64();
        tracing::debug!(
            target: "slag_encoder::segments",
            kept = kept_count,
            border = border.len(),
            seconds = format!("{:.2}", clock.elapsed().as_secs_f64()),
            "minimum-size pass"
        );
    }
    let border_count = border.len() as u64;
    (Some(forest), inner + border_count, border_count)
}

/// What every tile's pass reads.
struct Run<'a> {
    /// The scene's Gaussian count.
    gaussians: usize,
    p: &'a SegmentParams,
    ctl: &'a SegmentControl,
    w: &'a Weigher<'a>,
    src: &'a EdgeSource<'a>,
    tm: &'a TileMembers,
    /// The scene's border edges ([`border_edges`]) and each tile's ends of them ([`border_ends`]).
    border: &'a [Edge],
    ends: Vec<Vec<(u32, u32)>>,
}

impl Run<'_> {
    /// The tiles' criterion passes, each on a forest of its own; `None` once stopped. The
    /// tiles go in waves, and while one wave runs its criterion passes (one thread per tile)
    /// the next wave's edges are weighed and sorted on the other threads; two waves of half
    /// [`tiles_at_once`] each hold edges at a time (one wave, not overlapped, where only one
    /// tile fits). Each wave's size is taken from the pool it runs on, so that a segmentation
    /// whose pool was widened (the encode ended) runs more tiles at once from then on; the
    /// tiles are independent, so the waves change no result.
    fn parallel_tiles(&self, st: &mut SegmentTimings) -> Option<Tiled> {
        let tiles = self.tm.members.len() as u32;
        let mut passes: Vec<TilePass> = Vec::with_capacity(tiles as usize);
        let (mut next, mut waiting) = (0u32, Vec::new());
        let mut in_flight = InFlight {
            most_edges: 0.0,
            k: self.p.neighbours,
            record_bytes: self.w.masks.map_or(0, |m| m.bytes_per_gaussian()),
        };
        while next < tiles || !waiting.is_empty() {
            let per = in_flight.bytes_per_gaussian();
            let budget = self.ctl.in_flight_bytes();
            let at_once = self.ctl.run(|| tiles_at_once(self.tm, per, budget));
            let wave = next..(next + (at_once / 2).max(1) as u32).min(tiles);
            next = wave.end;
            let prev = std::mem::take(&mut waiting);
            let clock = Instant::now();
            let (done, built) = if at_once >= 2 {
                self.ctl
                    .run(|| rayon::join(|| self.criteria(prev), || self.build(wave)))
            } else {
                let done = self.ctl.run(|| self.criteria(prev));
                (done, self.ctl.run(|| self.build(wave)))
            };
            if self.ctl.stopped() {
                return None;
            }
            tracing::debug!(
                target: "slag_encoder::segments",
                passed = done.len(),
                built = built.len(),
                at_once,
                budget_mib = budget >> 20,
                threads = self.ctl.run(rayon::current_num_threads),
                seconds = format!("{:.2}", clock.elapsed().as_secs_f64()),
                "tile wave"
            );
            passes.extend(done);
            in_flight.saw(&built, self.tm);
            waiting = built;
        }
        for pass in &passes {
            st.weights += pass.seconds[0];
            st.sort += pass.seconds[1];
            st.criterion += pass.seconds[2];
            st.min_size += pass.seconds[3];
        }
        let forest = self.ctl.run(|| self.scene_forest(&passes));
        let inner = passes.iter().map(|t| t.inner).sum();
        let mut met = vec![[Component::default(); 2]; self.border.len()];
        let mut kept = Vec::with_capacity(passes.len());
        for pass in passes {
            for (k, side, c) in pass.met {
                met[k as usize][side] = c;
            }
            kept.push(pass.kept);
        }
        Some(Tiled {
            forest,
            met,
            kept,
            inner,
        })
    }

    /// The edges of the tiles `wave`, weighed and sorted.
    fn build(&self, wave: std::ops::Range<u32>) -> Vec<BuiltTile> {
        wave.into_par_iter()
            .map(|t| build_tile(t, self.src, self.w))
            .collect()
    }

    /// The criterion passes of `built`, one thread per tile.
    fn criteria(&self, built: Vec<BuiltTile>) -> Vec<TilePass> {
        built
            .into_par_iter()
            .map(|b| {
                let t = b.t as usize;
                let ends = (self.border, &self.ends[t][..]);
                b.criterion(self.w, &self.tm.members[t], ends)
            })
            .collect()
    }

    /// The scene's forest from the tiles' own: each Gaussian's root and its component.
    fn scene_forest(&self, passes: &[TilePass]) -> Forest {
        let tm = self.tm;
        let (parent, components) = (0..tm.place.len())
            .into_par_iter()
            .map(|i| {
                let (t, l) = tm.place[i];
                let (t, l) = (t as usize, l as usize);
                let root = tm.members[t][passes[t].roots[l] as usize];
                (root, passes[t].components[l])
            })
            .unzip();
        Forest::from_parts(parent, components)
    }

    /// The tiles' criterion passes one after the other on the scene's forest, with the
    /// regions' veto, each with its pick of edges for the minimum-size pass; `None` once
    /// stopped.
    fn serial_tiles(&self, regions: &mut Regions, st: &mut SegmentTimings) -> Option<Tiled> {
        let tiles = self.tm.members.len();
        let mut forest = Forest::singletons(self.gaussians);
        let mut met = vec![[Component::default(); 2]; self.border.len()];
        let (mut kept, mut inner) = (Vec::with_capacity(tiles), 0);
        for t in 0..tiles {
            let clock = Instant::now();
            let mut local = self.ctl.run(|| tile_edges(t as u32, self.src, self.w));
            self.ctl.run(|| local.par_sort_unstable());
            if self.ctl.stopped() {
                return None;
            }
            st.weights += clock.elapsed().as_secs_f64();
            let clock = Instant::now();
            let m = &self.tm.members[t];
            let edges: Vec<Edge> = local.iter().map(|e| e.mapped(|l| m[l as usize])).collect();
            let ends: Vec<(u32, u32)> = self.ends[t]
                .iter()
                .map(|&(k, l)| (k, m[l as usize]))
                .collect();
            let stops = stops_in(&edges, self.border, &ends, |i| i);
            let at_stops =
                forest.criterion_pass_with_stops(&edges, self.p.threshold, &stops, Some(regions));
            for (&(k, x), c) in ends.iter().zip(at_stops) {
                met[k as usize][usize::from(self.border[k as usize].i != x)] = c;
            }
            inner += edges.len() as u64;
            st.criterion += clock.elapsed().as_secs_f64();
            let clock = Instant::now();
            kept.push(self.ctl.run(|| {
                let small = |x| forest.component(forest.root(x)).size() < self.p.min_size;
                let lookup = (|x| forest.root(x), small);
                min_size_candidates(lookup, &edges, self.w, |i| i)
            }));
            st.min_size += clock.elapsed().as_secs_f64();
        }
        Some(Tiled {
            forest,
            met,
            kept,
            inner,
        })
    }
}
