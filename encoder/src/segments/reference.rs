//! The segmentation as it was before the grid search and the parallel tiles: an R*-tree k-NN
//! per tile and its halo, and the passes tile after tile over the global forest. Kept as the
//! tests' oracle: the faster implementation must give the same ids.

#![allow(clippy::unwrap_used)]

use std::sync::atomic::{AtomicBool, Ordering};

use rayon::prelude::*;
use rstar::RTree;
use rstar::primitives::GeomWithData;
use slag_common::mask_record::MaskRecord;
use slag_common::scene::Gaussians;
use slag_common::segments::canonical_ids;

use super::SegmentParams;
use super::forest::Forest;
use super::graph::resolve_max_edge;
use super::neighbours::{NO_NEIGHBOUR, Neighbours};
use super::regions::Regions;
use super::weights::{Edge, Geometry, Weigher, distance, geometry};

/// The segment ids (canonical) of `g` by the old implementation.
pub(super) fn segment_ids(
    g: &Gaussians,
    p: &SegmentParams,
    masks: Option<&MaskRecord>,
) -> Vec<u32> {
    let geo = geometry(g);
    let h = resolve_max_edge(p, &geo);
    let (ax, tile_of, rects) = plan_tiles(&g.means, p.tile_gaussians);
    let nb = neighbour_graph(g, p, h, ax, &tile_of, &rects);
    let w = Weigher { p, masks };
    let mut forest = merge(g, p, &geo, &w, &nb, &tile_of, rects.len());
    let roots: Vec<u32> = (0..g.len() as u32).map(|i| forest.find(i)).collect();
    canonical_ids(&roots).0
}

/// Every tile's k-NN into one [`Neighbours`].
pub(super) fn neighbour_graph(
    g: &Gaussians,
    p: &SegmentParams,
    h: f32,
    ax: [usize; 2],
    tile_of: &[u32],
    rects: &[([f32; 2], [f32; 2])],
) -> Neighbours {
    let mut nb = Neighbours {
        k: p.neighbours,
        ids: vec![NO_NEIGHBOUR; g.len() * p.neighbours],
    };
    let go = AtomicBool::new(false);
    for (t, rect) in rects.iter().enumerate() {
        tile_neighbours(t as u32, &g.means, tile_of, ax, *rect, p, h, &go, &mut nb);
    }
    nb
}

/// The k nearest neighbours of tile `t`'s Gaussians, written into `nb`: the k-NN over the tile
/// plus a halo of width `h`, which holds every neighbour within `h`. Once `stop` is set the
/// remaining Gaussians get none: the caller discards such a partial result.
#[allow(clippy::too_many_arguments)]
pub(super) fn tile_neighbours(
    t: u32,
    means: &[[f32; 3]],
    tile_of: &[u32],
    ax: [usize; 2],
    rect: ([f32; 2], [f32; 2]),
    p: &SegmentParams,
    h: f32,
    stop: &AtomicBool,
    nb: &mut Neighbours,
) {
    let (lo, hi) = rect;
    let inside = |m: &[f32; 3]| (0..2).all(|k| m[ax[k]] >= lo[k] - h && m[ax[k]] <= hi[k] + h);
    let members: Vec<u32> = (0..means.len() as u32)
        .into_par_iter()
        .filter(|&i| tile_of[i as usize] == t || inside(&means[i as usize]))
        .collect();
    let tree: RTree<GeomWithData<[f32; 3], u32>> = RTree::bulk_load(
        members
            .iter()
            .map(|&i| GeomWithData::new(means[i as usize], i))
            .collect(),
    );
    let k = p.neighbours;
    let h2 = h * h;
    let found: Vec<(u32, Vec<u32>)> = members
        .par_iter()
        .filter(|&&i| tile_of[i as usize] == t)
        .map(|&i| {
            if stop.load(Ordering::Relaxed) {
                return (i, Vec::new());
            }
            let mi = means[i as usize];
            // The k nearest other Gaussians within h, ties by id: take every candidate up to the
            // k-th distance, including all that tie with it, then sort by (distance, id).
            let mut cand: Vec<(f32, u32)> = Vec::with_capacity(k + 4);
            for (g, d2) in tree.nearest_neighbor_iter_with_distance_2(&mi) {
                if d2 > h2 {
                    break;
                }
                if cand.len() > k && d2 > cand[k].0 {
                    break;
                }
                cand.push((d2, g.data));
            }
            cand.retain(|c| c.1 != i);
            cand.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            cand.truncate(k);
            (i, cand.into_iter().map(|c| c.1).collect())
        })
        .collect();
    for (i, js) in found {
        let slots = &mut nb.ids[i as usize * nb.k..(i as usize + 1) * nb.k];
        slots.fill(NO_NEIGHBOUR);
        slots[..js.len()].copy_from_slice(&js);
    }
}

/// The graph's edges of tile `t` from the neighbour lists: inner edges (both ends in the
/// tile), ascending, and border edges (one end outside), unordered.
fn edges_of_tile(
    t: u32,
    means: &[[f32; 3]],
    geo: &Geometry,
    tile_of: &[u32],
    nb: &Neighbours,
    w: &Weigher,
) -> (Vec<Edge>, Vec<Edge>) {
    let (inner, border): (Vec<Vec<Edge>>, Vec<Vec<Edge>>) = (0..means.len() as u32)
        .into_par_iter()
        .filter(|&i| tile_of[i as usize] == t)
        .map(|i| {
            let (mut inn, mut bor) = (Vec::new(), Vec::new());
            for j in nb.of(i as usize) {
                let d = distance(means[i as usize], means[j as usize]);
                let (i_, j_) = (i as usize, j as usize);
                let e = Edge {
                    w: w.weight(geo.geometric(w.p, i_, j_, d), i_, j_).to_bits(),
                    i: i.min(j),
                    j: i.max(j),
                };
                if tile_of[j as usize] == t {
                    inn.push(e);
                } else {
                    bor.push(e);
                }
            }
            (inn, bor)
        })
        .unzip();
    let mut inner: Vec<Edge> = inner.into_iter().flatten().collect();
    inner.par_sort_unstable();
    inner.dedup();
    (inner, border.into_iter().flatten().collect())
}

/// The two passes over the tiles' edges, tile after tile; each border edge joins by its two
/// ends' merge thresholds where it stands in the tile's order of edges.
fn merge(
    g: &Gaussians,
    p: &SegmentParams,
    geo: &Geometry,
    w: &Weigher,
    nb: &Neighbours,
    tile_of: &[u32],
    tiles: usize,
) -> Forest {
    let mut forest = Forest::singletons(g.len());
    let mut regions = w
        .masks
        .filter(|_| p.region_veto < 1.0)
        .map(|r| Regions::new(r, p.region_veto));
    let mut border: Vec<Edge> = Vec::new();
    for t in 0..tiles {
        border.extend(edges_of_tile(t as u32, &g.means, geo, tile_of, nb, w).1);
    }
    border.par_sort_unstable();
    border.dedup();
    let mut met = vec![[Default::default(); 2]; border.len()];
    for t in 0..tiles {
        let (inner, _) = edges_of_tile(t as u32, &g.means, geo, tile_of, nb, w);
        // Each end in this tile, in the border's order; noted before the first inner edge
        // that comes after its edge.
        let ends: Vec<(usize, usize, u32)> = border
            .iter()
            .enumerate()
            .flat_map(|(k, e)| [(k, 0, e.i), (k, 1, e.j)])
            .filter(|&(_, _, x)| tile_of[x as usize] == t as u32)
            .collect();
        let mut next = 0;
        for e in inner.iter().map(Some).chain([None]) {
            while next < ends.len() && e.is_none_or(|e| border[ends[next].0] < *e) {
                let (k, side, x) = ends[next];
                met[k][side] = forest.component_of(x);
                next += 1;
            }
            if let Some(e) = e {
                forest.criterion_pass_in(std::slice::from_ref(e), p.threshold, regions.as_mut());
            }
        }
    }
    forest.border_pass_in(&border, &met, p.threshold, regions.as_mut());
    if p.min_size > 1 {
        let allowed = |e: &Edge| w.may_absorb(e);
        for t in 0..tiles {
            let (inner, _) = edges_of_tile(t as u32, &g.means, geo, tile_of, nb, w);
            forest.min_size_pass_in(&inner, p.min_size, allowed, regions.as_mut());
        }
        forest.min_size_pass_in(&border, p.min_size, allowed, regions.as_mut());
    }
    forest
}

/// Every edge of `g`'s graph in ascending order (one tile).
pub(super) fn all_edges(g: &Gaussians, p: &SegmentParams) -> Vec<Edge> {
    let geo = geometry(g);
    let h = resolve_max_edge(p, &geo);
    let (ax, one, rects) = plan_tiles(&g.means, usize::MAX);
    let nb = neighbour_graph(g, p, h, ax, &one, &rects);
    let w = Weigher { p, masks: None };
    let (all, none) = edges_of_tile(0, &g.means, &geo, &one, &nb, &w);
    assert!(none.is_empty());
    all
}

/// The tiles as [`super::tiles::plan_tiles`] made them on one thread: the same splits over a
/// permutation of Gaussian ids, the median selected through the ids.
#[allow(clippy::type_complexity)]
pub(super) fn plan_tiles(
    means: &[[f32; 3]],
    cap: usize,
) -> ([usize; 2], Vec<u32>, Vec<([f32; 2], [f32; 2])>) {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for m in means {
        for a in 0..3 {
            lo[a] = lo[a].min(m[a]);
            hi[a] = hi[a].max(m[a]);
        }
    }
    let mut axes = [0usize, 1, 2];
    axes.sort_by(|&a, &b| (hi[b] - lo[b]).total_cmp(&(hi[a] - lo[a])).then(a.cmp(&b)));
    let ax = [axes[0], axes[1]];
    let mut perm: Vec<u32> = (0..means.len() as u32).collect();
    let mut tile_of = vec![0u32; means.len()];
    let mut rects = Vec::new();
    let mut stack = vec![(0usize, perm.len())];
    while let Some((a, b)) = stack.pop() {
        if a == b {
            continue;
        }
        let rows = &mut perm[a..b];
        let (mut rlo, mut rhi) = ([f32::INFINITY; 2], [f32::NEG_INFINITY; 2]);
        for &r in rows.iter() {
            for k in 0..2 {
                rlo[k] = rlo[k].min(means[r as usize][ax[k]]);
                rhi[k] = rhi[k].max(means[r as usize][ax[k]]);
            }
        }
        if rows.len() <= cap {
            let t = rects.len() as u32;
            rows.iter().for_each(|&r| tile_of[r as usize] = t);
            rects.push((rlo, rhi));
            continue;
        }
        let k = if rhi[0] - rlo[0] >= rhi[1] - rlo[1] {
            0
        } else {
            1
        };
        let mid = rows.len() / 2;
        rows.select_nth_unstable_by(mid, |&x, &y| {
            means[x as usize][ax[k]]
                .total_cmp(&means[y as usize][ax[k]])
                .then(x.cmp(&y))
        });
        stack.push((a + mid, b));
        stack.push((a, a + mid));
    }
    (ax, tile_of, rects)
}
