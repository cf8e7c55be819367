//! The k-nearest-neighbour graph of the Gaussian means ([`super::grid`]) and its edges with
//! their weights, tile by tile (module doc, "Bounded memory: tiles").

use rayon::prelude::*;

use super::SegmentParams;
use super::weights::{Edge, Geometry, Weigher, distance};

/// Each Gaussian's neighbours in the graph: `k` slots per Gaussian, the nearest other means
/// within `max_edge` in ascending `(distance, id)` order, [`NO_NEIGHBOUR`] in unused slots.
/// 4 bytes per slot (40 per Gaussian at k = 10) and 4 for the slots' place, for the whole
/// scene: the k-NN search runs once and before the masks are known (beside the encode).
pub(super) struct Neighbours {
    pub(super) k: usize,
    /// The slots, `k` per Gaussian, in the order of `pos_of`.
    pub(super) ids: Vec<u32>,
    /// Where Gaussian `i`'s slots start, in units of `k`; `None`: at `i`.
    pub(super) pos_of: Option<Vec<u32>>,
}

/// Slot of [`Neighbours`] without a neighbour.
pub(super) const NO_NEIGHBOUR: u32 = u32::MAX;

impl Neighbours {
    pub(super) fn of(&self, i: usize) -> impl Iterator<Item = u32> + '_ {
        let at = self.pos_of.as_ref().map_or(i, |p| p[i] as usize);
        self.ids[at * self.k..(at + 1) * self.k]
            .iter()
            .copied()
            .take_while(|&j| j != NO_NEIGHBOUR)
    }
}

impl Neighbours {
    /// The same lists with Gaussian `i`'s slots at `i` (no `pos_of`): an edge's weight then
    /// reads its far end's list from one place rather than two. Parallel; for a moment both
    /// copies of the slots are held.
    fn in_id_order(self) -> Self {
        let Some(pos_of) = &self.pos_of else {
            return self;
        };
        let k = self.k.max(1);
        let mut ids = vec![NO_NEIGHBOUR; self.ids.len()];
        ids.par_chunks_mut(k)
            .zip(pos_of.par_iter())
            .for_each(|(out, &at)| {
                let at = at as usize * k;
                out.copy_from_slice(&self.ids[at..at + k]);
            });
        Neighbours {
            k: self.k,
            ids,
            pos_of: None,
        }
    }
}

/// The whole scene's k-NN graph within `h`, each Gaussian's list at its id, searched on
/// `ctl`'s pool (a pool widened meanwhile takes over the searches left); `None` once `ctl` was
/// stopped.
pub(super) fn neighbour_graph(
    means: &[[f32; 3]],
    p: &SegmentParams,
    h: f32,
    ctl: &super::SegmentControl,
) -> Option<Neighbours> {
    let nb = super::grid::neighbours(means, p.neighbours, h, ctl);
    (!ctl.is_stopped()).then(|| ctl.run(|| nb.in_id_order()))
}

/// A tile's Gaussians: their ids, ascending, and where each Gaussian of the scene stands.
pub(super) struct TileMembers {
    /// Each tile's Gaussian ids, ascending.
    pub(super) members: Vec<Vec<u32>>,
    /// Gaussian `i`'s tile `t` and place `l` in it, side by side (one read for an edge's far
    /// end): `i` is `members[t][l]`.
    pub(super) place: Vec<(u32, u32)>,
}

impl TileMembers {
    pub(super) fn new(tile_of: &[u32], tiles: usize) -> Self {
        let mut members = vec![Vec::new(); tiles];
        let mut place = vec![(0u32, 0u32); tile_of.len()];
        for (i, &t) in tile_of.iter().enumerate() {
            let m = &mut members[t as usize];
            place[i] = (t, m.len() as u32);
            m.push(i as u32);
        }
        TileMembers { members, place }
    }
}

/// The geometric part of every neighbour slot's edge weight ([`Geometry::geometric`] of
/// Gaussian `i` and its slot's neighbour `j`), `k` per Gaussian in the scene's id order (slot `s`
/// of Gaussian `i` at `i k + s`), 0 in unused slots. It needs no masks, so it is computed
/// before the masks' record arrives (beside the encode); afterwards an edge's weight only adds
/// the mask term. 4 bytes per slot (40 per Gaussian at k = 10).
pub(super) fn slot_geometry(
    means: &[[f32; 3]],
    nb: &Neighbours,
    geo: &Geometry,
    p: &SegmentParams,
) -> Vec<f32> {
    let mut out = vec![0.0f32; means.len() * nb.k];
    out.par_chunks_mut(nb.k.max(1) * 1024)
        .enumerate()
        .for_each(|(c, part)| {
            for (l, slots) in part.chunks_mut(nb.k.max(1)).enumerate() {
                let i = c * 1024 + l;
                for (s, j) in nb.of(i).enumerate() {
                    let d = distance(means[i], means[j as usize]);
                    slots[s] = geo.geometric(p, i, j as usize, d);
                }
            }
        });
    out
}

/// The graph's edges owned by tile `t`'s Gaussians: the inner ones (both ends in the tile) in
/// the tile's local ids (`members` order, which keeps the ids' order), and the border ones
/// (one end outside), in scene ids; both unordered. `geometric` is [`slot_geometry`]'s.
///
/// An edge `(i, j)` of Gaussian `i` has the weight `w(i, j)` (the weights are not exactly
/// symmetric in rounding); when `j` lists `i` too, `w(j, i)` is an edge as well unless both
/// weights are the same (one edge then): the edges of each Gaussian's list, deduplicated.
pub(super) fn tile_edges(
    t: u32,
    geometric: &[f32],
    tiles: &TileMembers,
    nb: &Neighbours,
    w: &Weigher,
) -> (Vec<Edge>, Vec<Edge>) {
    let (members, k) = (&tiles.members[t as usize], nb.k);
    let parts: Vec<(Vec<Edge>, Vec<Edge>)> = members
        .par_chunks(4096)
        .map(|chunk| {
            let (mut inner, mut border) = (Vec::new(), Vec::new());
            for &i in chunk {
                let iu = i as usize;
                for (s, j) in nb.of(iu).enumerate() {
                    let ju = j as usize;
                    let back = nb.of(ju).position(|x| x == i);
                    if back.is_some() && j < i {
                        continue;
                    }
                    let wij = w.weight(geometric[iu * k + s], iu, ju).to_bits();
                    let wji =
                        back.map_or(wij, |b| w.weight(geometric[ju * k + b], ju, iu).to_bits());
                    let (lo, hi) = (i.min(j), i.max(j));
                    let (tj, lj) = tiles.place[ju];
                    let (out, lo, hi) = if tj == t {
                        let li = tiles.place[iu].1;
                        let (a, b) = if i < j { (li, lj) } else { (lj, li) };
                        (&mut inner, a, b)
                    } else {
                        (&mut border, lo, hi)
                    };
                    out.push(Edge {
                        w: wij,
                        i: lo,
                        j: hi,
                    });
                    if wji != wij {
                        out.push(Edge {
                            w: wji,
                            i: lo,
                            j: hi,
                        });
                    }
                }
            }
            (inner, border)
        })
        .collect();
    let (mut inner, mut border) = (Vec::new(), Vec::new());
    for (a, b) in parts {
        inner.extend(a);
        border.extend(b);
    }
    (inner, border)
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
