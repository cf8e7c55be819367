//! The k-nearest-neighbour graph of the Gaussian means, built tile by tile over each tile plus
//! its halo (module doc, "Bounded memory: tiles with a halo"), and its edges with their weights.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use rayon::prelude::*;
use rstar::RTree;
use rstar::primitives::GeomWithData;
use slag_common::scene::Gaussians;

use super::weights::{Edge, Geometry, Weigher};
use super::{SegmentControl, SegmentParams, SegmentTimings};

/// Each Gaussian's neighbours in the graph: `k` slots per Gaussian, the nearest other means
/// within `max_edge` in ascending `(distance, id)` order, [`NO_NEIGHBOUR`] in unused slots.
/// 4 bytes per slot (40 per Gaussian at k = 10), for the whole scene: the k-NN search, the costly
/// part of the graph, runs once and before the masks are known (beside the encode).
pub(super) struct Neighbours {
    pub(super) k: usize,
    pub(super) ids: Vec<u32>,
}

/// Slot of [`Neighbours`] without a neighbour.
pub(super) const NO_NEIGHBOUR: u32 = u32::MAX;

impl Neighbours {
    pub(super) fn of(&self, i: usize) -> impl Iterator<Item = u32> + '_ {
        self.ids[i * self.k..(i + 1) * self.k]
            .iter()
            .copied()
            .take_while(|&j| j != NO_NEIGHBOUR)
    }
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
pub(super) fn edges_of_tile(
    t: u32,
    means: &[[f32; 3]],
    tile_of: &[u32],
    nb: &Neighbours,
    w: &Weigher,
    st: &mut SegmentTimings,
) -> (Vec<Edge>, Vec<Edge>) {
    let clock = Instant::now();
    let (inner, border): (Vec<Vec<Edge>>, Vec<Vec<Edge>>) = (0..means.len() as u32)
        .into_par_iter()
        .filter(|&i| tile_of[i as usize] == t)
        .map(|i| {
            let (mut inn, mut bor) = (Vec::new(), Vec::new());
            for j in nb.of(i as usize) {
                let (a, b) = (means[i as usize], means[j as usize]);
                let d =
                    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
                let e = Edge {
                    w: w.weight(i as usize, j as usize, d).to_bits(),
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
    let border: Vec<Edge> = border.into_iter().flatten().collect();
    st.weights += clock.elapsed().as_secs_f64();
    let clock = Instant::now();
    inner.par_sort_unstable();
    inner.dedup();
    st.sort += clock.elapsed().as_secs_f64();
    (inner, border)
}

/// The graph's edges of tile `t` (k-NN and weights in one go; the tests' reference).
#[cfg(test)]
#[allow(clippy::too_many_arguments)]
pub(super) fn tile_edges(
    t: u32,
    means: &[[f32; 3]],
    tile_of: &[u32],
    ax: [usize; 2],
    rect: ([f32; 2], [f32; 2]),
    geo: &Geometry,
    p: &SegmentParams,
    h: f32,
    stop: &AtomicBool,
) -> (Vec<Edge>, Vec<Edge>) {
    let mut nb = Neighbours {
        k: p.neighbours,
        ids: vec![NO_NEIGHBOUR; means.len() * p.neighbours],
    };
    tile_neighbours(t, means, tile_of, ax, rect, p, h, stop, &mut nb);
    let w = Weigher {
        p,
        geo,
        masks: None,
    };
    edges_of_tile(t, means, tile_of, &nb, &w, &mut SegmentTimings::default())
}

/// `max_edge` for `p` and `geo`: the given one, or 10 × the median largest standard deviation.
pub(super) fn resolve_max_edge(p: &SegmentParams, geo: &Geometry) -> f32 {
    if let Some(m) = p.max_edge {
        return m;
    }
    let mut s: Vec<f32> = geo.size.iter().copied().filter(|v| v.is_finite()).collect();
    if s.is_empty() {
        return 1.0;
    }
    let mid = s.len() / 2;
    s.select_nth_unstable_by(mid, f32::total_cmp);
    let m = 10.0 * s[mid];
    if m.is_finite() && m > 0.0 { m } else { 1.0 }
}

/// Every tile's k-NN into one [`Neighbours`]; `None` once stopped.
#[allow(clippy::type_complexity)]
pub(super) fn neighbour_graph(
    g: &Gaussians,
    p: &SegmentParams,
    ctl: &SegmentControl,
    h: f32,
    ax: [usize; 2],
    tile_of: &[u32],
    rects: &[([f32; 2], [f32; 2])],
) -> Option<Neighbours> {
    let mut nb = Neighbours {
        k: p.neighbours,
        ids: vec![NO_NEIGHBOUR; g.len() * p.neighbours],
    };
    for (t, rect) in rects.iter().enumerate() {
        ctl.run(|| {
            tile_neighbours(
                t as u32, &g.means, tile_of, ax, *rect, p, h, &ctl.stop, &mut nb,
            )
        });
        if ctl.stopped() {
            return None;
        }
    }
    Some(nb)
}
