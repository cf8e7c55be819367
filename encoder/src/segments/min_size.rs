//! The minimum-size pass (module doc, "Segmentation" and "tiles") over the edge order "every
//! tile's inner edges, then the border edges", with the tiles' part run in parallel and the
//! same joins as one pass over that order.
//!
//! After the border pass, a component either lies in one tile (*local*) or was joined across a
//! border by it (*spanning*: it holds both ends of a border edge). A tile's inner edges touch
//! only its own Gaussians, so only its own local components and spanning ones. Each tile runs,
//! on a forest of its own over its local components, its edges in order: an edge between two
//! local components is applied as the one pass would; an edge with an end in a spanning
//! component, or in a local component that such an edge touched before (*held*), is deferred,
//! and its local ends become held. The deferred edges of every tile (in tile order, each in
//! its order) and then the border edges run afterwards on the scene's forest.
//!
//! This joins what the one pass joins. An applied edge reads and changes two local components
//! that are not held; no edge before it in the one pass's order that runs later here can touch
//! them: an earlier tile's edges touch that tile's own local components and spanning ones, and
//! its own tile's deferred edges touch held and spanning ones. So moving it ahead of those
//! changes neither what it sees nor what they see.

use rayon::prelude::*;

use super::forest::{Component, Forest};
use super::graph::TileMembers;
use super::weights::{Edge, Weigher};

/// The edges of each of `lists` (in its order), then of `border`, that the minimum-size pass
/// could join across, in parallel: those with an end in a component of fewer than `min_size`
/// Gaussians now that `w` lets it join ([`Weigher::may_absorb`], checked last: most edges
/// have no small end). The pass over them alone joins what the pass over all of the lists
/// joins: components only grow, so an edge between two components of `min_size` or more now
/// never qualifies, and the mask veto is the edge's own. Each list is freed once filtered.
pub(super) fn candidates(
    forest: &Forest,
    lists: Vec<Vec<Edge>>,
    border: Vec<Edge>,
    min_size: usize,
    w: &Weigher,
) -> (Vec<Vec<Edge>>, Vec<Edge>) {
    let small = forest.small_members(min_size);
    let small_end = |e: &&Edge| small[e.i as usize] || small[e.j as usize];
    let pick = |list: Vec<Edge>| -> Vec<Edge> {
        list.par_iter()
            .filter(|e| small_end(e) && w.may_absorb(e))
            .copied()
            .collect()
    };
    let lists = lists.into_iter().map(pick).collect();
    (lists, pick(border))
}

/// The minimum-size pass over `inner` (each tile's candidate edges, scene ids, in order; tile
/// `t`'s join only Gaussians of tile `t` of `tm`) and then `border` on `forest` (after the
/// border pass): the joins of [`Forest::min_size_pass_in`] over that order without a regions'
/// veto (module doc). `spanning`: [`spanning_roots`] before the pass. Returns the count of
/// joins made in parallel and of edges deferred, and the seconds of the parallel and the
/// serial part.
pub(super) fn tiled_min_size_pass(
    forest: &mut Forest,
    tm: &TileMembers,
    inner: Vec<Vec<Edge>>,
    border: &[Edge],
    spanning: &[bool],
    min_size: usize,
) -> ([usize; 2], [f64; 2]) {
    let clock = std::time::Instant::now();
    let scene: &Forest = forest;
    let tiles: Vec<TileOutcome> = inner
        .into_par_iter()
        .enumerate()
        .map(|(t, edges)| local_pass(scene, spanning, tm, t, edges, min_size))
        .collect();
    let parallel_s = clock.elapsed().as_secs_f64();
    let clock = std::time::Instant::now();
    let (mut joins, mut deferred) = (0, 0);
    for (t, tile) in tiles.iter().enumerate() {
        let members = &tm.members[t];
        for &(child, root, merged) in &tile.joins {
            forest.attach(members[child as usize], members[root as usize], merged);
        }
        joins += tile.joins.len();
        deferred += tile.deferred.len();
    }
    for tile in tiles {
        forest.min_size_pass_in(&tile.deferred, min_size, |_| true, None);
    }
    forest.min_size_pass_in(border, min_size, |_| true, None);
    (
        [joins, deferred],
        [parallel_s, clock.elapsed().as_secs_f64()],
    )
}

/// Whether each Gaussian is the root of a component that spans tiles, after the border pass:
/// the root of both ends of one of the scene's `border_edges` (`[N]`, true at those roots
/// only; a component joined across a border holds the border edge that joined it).
pub(super) fn spanning_roots(forest: &Forest, border_edges: &[Edge]) -> Vec<bool> {
    let mut spanning = vec![false; forest.len()];
    for e in border_edges {
        let (a, b) = (forest.root(e.i), forest.root(e.j));
        if a == b {
            spanning[a as usize] = true;
        }
    }
    spanning
}

/// One tile's part: its joins in order (`(child, root, merged)`, local ids: what
/// [`Forest::attach`] is to replay on the scene's forest) and the edges it deferred, in order.
struct TileOutcome {
    joins: Vec<(u32, u32, Component)>,
    deferred: Vec<Edge>,
}

/// Tile `t`'s edges run on a forest of its own over its Gaussians (local ids, `tm`'s places),
/// each local component starting as in `scene` (at its root's place): applied while both ends
/// are in local components not held, else deferred (module doc).
fn local_pass(
    scene: &Forest,
    spanning: &[bool],
    tm: &TileMembers,
    t: usize,
    edges: Vec<Edge>,
    min_size: usize,
) -> TileOutcome {
    let members = &tm.members[t];
    let mut out = TileOutcome {
        joins: Vec::new(),
        deferred: Vec::new(),
    };
    if edges.is_empty() {
        return out;
    }
    let components = members.iter().map(|&x| scene.component(x)).collect();
    let mut local = Forest::from_parts((0..members.len() as u32).collect(), components);
    let mut held = vec![false; members.len()];
    // The local root of Gaussian `x`'s component, `None` where it spans tiles.
    let local_root = |local: &mut Forest, x: u32| -> Option<u32> {
        let r = scene.root(x);
        (!spanning[r as usize]).then(|| local.find(tm.place[r as usize].1))
    };
    for e in edges {
        let (a, b) = (local_root(&mut local, e.i), local_root(&mut local, e.j));
        if a.is_some() && a == b {
            continue;
        }
        match (a, b) {
            (Some(a), Some(b)) if !held[a as usize] && !held[b as usize] => {
                if local.component(a).size() < min_size || local.component(b).size() < min_size {
                    let (child, root, merged) = local.join(a, b, e.weight());
                    out.joins.push((child, root, merged));
                }
            }
            _ => {
                for r in [a, b].into_iter().flatten() {
                    held[r as usize] = true;
                }
                out.deferred.push(e);
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lcg(s: &mut u64) -> u64 {
        *s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        *s >> 33
    }

    fn edge(w: u64, i: u32, j: u32) -> Edge {
        Edge {
            w: (w as f32 / 97.0).to_bits(),
            i: i.min(j),
            j: i.max(j),
        }
    }

    /// A scene of `n` Gaussians in `tiles` tiles as the passes leave it before the
    /// minimum-size pass: components of mixed sizes inside each tile (some below the minimum),
    /// then border edges, some joined across tiles; and each tile's candidate edges (inside
    /// it, in order) and the border's.
    #[allow(clippy::type_complexity)]
    fn scene(seed: u64, n: u32, tiles: u32) -> (Forest, TileMembers, Vec<Vec<Edge>>, Vec<Edge>) {
        let mut s = seed;
        let tile_of: Vec<u32> = (0..n)
            .map(|i| {
                if i < tiles {
                    i
                } else {
                    (lcg(&mut s) % tiles as u64) as u32
                }
            })
            .collect();
        let tm = TileMembers::new(&tile_of, tiles as usize);
        let mut f = Forest::singletons(n as usize);
        let pick = |s: &mut u64, t: usize| {
            let m = &tm.members[t];
            m[(lcg(s) % m.len() as u64) as usize]
        };
        for _ in 0..n / 2 {
            let t = (lcg(&mut s) % tiles as u64) as usize;
            let (a, b) = (pick(&mut s, t), pick(&mut s, t));
            let (a, b) = (f.find(a), f.find(b));
            if a != b && !lcg(&mut s).is_multiple_of(3) {
                f.join(a, b, 0.0);
            }
        }
        let mut border = Vec::new();
        for _ in 0..n / 20 {
            let (ta, tb) = (lcg(&mut s) % tiles as u64, lcg(&mut s) % tiles as u64);
            if ta == tb {
                continue;
            }
            let (a, b) = (pick(&mut s, ta as usize), pick(&mut s, tb as usize));
            border.push(edge(lcg(&mut s) % 50, a, b));
            let (ra, rb) = (f.find(a), f.find(b));
            if ra != rb && lcg(&mut s).is_multiple_of(2) {
                f.join(ra, rb, 0.0);
            }
        }
        border.sort();
        let inner = (0..tiles as usize)
            .map(|t| {
                let mut list: Vec<Edge> = (0..n / tiles)
                    .map(|_| edge(lcg(&mut s) % 50, pick(&mut s, t), pick(&mut s, t)))
                    .filter(|e| e.i != e.j)
                    .collect();
                list.sort();
                list
            })
            .collect();
        (f, tm, inner, border)
    }

    fn partition(f: &Forest) -> Vec<u32> {
        super::super::canonical_root_ids(&f.roots()).0
    }

    /// The tiled pass joins exactly what one pass over "every tile's edges, then the border
    /// edges" joins, on scenes where it both applies edges in parallel and defers some.
    #[test]
    fn tiled_pass_equals_one_pass_over_the_tile_grouped_order() {
        let (mut joined_in_parallel, mut deferred_somewhere) = (false, false);
        for seed in 0..40u64 {
            let n = 300 + (seed as u32 * 37) % 900;
            let tiles = 2 + (seed as u32 % 5);
            let min_size = 2 + (seed as usize % 9);
            let (mut one, _, inner, border) = scene(seed, n, tiles);
            let order: Vec<Edge> = inner.iter().flatten().chain(&border).copied().collect();
            one.min_size_pass(&order, min_size, |_| true);
            let (mut tiled, tm, inner, border) = scene(seed, n, tiles);
            let spanning = spanning_roots(&tiled, &border);
            let ([joins, deferred], _) =
                tiled_min_size_pass(&mut tiled, &tm, inner, &border, &spanning, min_size);
            assert_eq!(partition(&tiled), partition(&one), "seed {seed}");
            let sizes = |f: &Forest| {
                (0..n)
                    .map(|x| f.component(f.root(x)).size())
                    .collect::<Vec<_>>()
            };
            assert_eq!(sizes(&tiled), sizes(&one), "seed {seed}");
            deferred_somewhere |= deferred > 0;
            joined_in_parallel |= joins > 0;
        }
        assert!(deferred_somewhere && joined_in_parallel);
    }
}
