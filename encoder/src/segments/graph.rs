//! The k-nearest-neighbour graph of the Gaussian means ([`super::grid`]) and its edges with
//! their weights, tile by tile (module doc, "Bounded memory: tiles").

use rayon::prelude::*;
use slag_common::mask_record::{MaskRecord, PackedRow};

use super::SegmentParams;
use super::neighbours::Ranked;
use super::weights::{Edge, Geometry, Weigher, distance};

/// The whole scene's k-NN graph within `h` in space order, searched on `ctl`'s pool (a pool
/// widened meanwhile takes over the searches left); `None` once `ctl` was stopped.
pub(super) fn neighbour_graph(
    means: &[[f32; 3]],
    p: &SegmentParams,
    h: f32,
    ctl: &super::SegmentControl,
) -> Option<Ranked> {
    let nb = super::grid::neighbours(means, p.neighbours, h, ctl);
    (!ctl.is_stopped()).then_some(nb)
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
/// rank `r` and its slot's neighbour), `k` per rank in rank order (slot `s` of rank `r` at
/// `r k + s`), 0 in unused slots; `means` and `geo` are in rank order ([`Ranked::gather`],
/// [`Geometry::permuted`]). It needs no masks, so it is computed before the masks' record
/// arrives (beside the encode); afterwards an edge's weight only adds the mask term. 4 bytes
/// per slot (40 per Gaussian at k = 10).
pub(super) fn slot_geometry(
    means: &[[f32; 3]],
    nb: &Ranked,
    geo: &Geometry,
    p: &SegmentParams,
) -> Vec<f32> {
    let mut out = vec![0.0f32; means.len() * nb.k];
    out.par_chunks_mut(nb.k.max(1) * 1024)
        .enumerate()
        .for_each(|(c, part)| {
            for (l, slots) in part.chunks_mut(nb.k.max(1)).enumerate() {
                let r = c * 1024 + l;
                for (s, rj) in nb.of(r).enumerate() {
                    let d = distance(means[r], means[rj as usize]);
                    slots[s] = geo.geometric(p, r, rj as usize, d);
                }
            }
        });
    out
}

/// What a tile's edges read: the graph in space order, the geometric parts ([`slot_geometry`]),
/// the tiles' ranks ([`TileMembers`] over ranks: each tile's ranks ascending, each rank's tile
/// and place there) and the tiles' Gaussian ids ([`TileMembers`] over ids).
pub(super) struct EdgeSource<'a> {
    pub(super) nb: &'a Ranked,
    pub(super) geometric: &'a [f32],
    pub(super) ranks: &'a TileMembers,
    pub(super) ids: &'a TileMembers,
}

/// The graph's edges inside tile `t` (both ends in the tile), in the tile's local ids
/// (`ids.members` order, which keeps the ids' order), unordered. The edges that cross the
/// tile's border are [`border_edges`]'.
///
/// An edge `(i, j)` of Gaussian `i` has the weight `w(i, j)` (the weights are not exactly
/// symmetric in rounding); when `j` lists `i` too, `w(j, i)` is an edge as well unless both
/// weights are the same (one edge then): the edges of each Gaussian's list, deduplicated
/// ([`slot_weights`]).
///
/// The tile's Gaussians are visited in space order, with their masks' record gathered in that
/// order first, each row packed into one cache line ([`MaskRecord::gather_packed`]; other slot
/// counts than the default: [`MaskRecord::gather`]): the reads an edge makes at its far end
/// land near those of its near end. The edges are those of the scene's id order, weight for
/// weight.
pub(super) fn tile_edges(t: u32, src: &EdgeSource, w: &Weigher) -> Vec<Edge> {
    let ranks = &src.ranks.members[t as usize];
    // The tile's Gaussians in space order: their ids, their local ids (in id order) and
    // their rows of the record.
    let ids: Vec<u32> = ranks.par_iter().map(|&r| src.nb.perm[r as usize]).collect();
    let local: Vec<u32> = ids
        .par_iter()
        .map(|&i| src.ids.place[i as usize].1)
        .collect();
    let rows = w.masks.map(|m| match m.gather_packed(&ids) {
        Some(lines) => TileRecord::Packed(lines),
        None => TileRecord::Rows(m.gather(&ids)),
    });
    let parts: Vec<Vec<Edge>> = ranks
        .par_chunks(4096)
        .enumerate()
        .map(|(c, chunk)| {
            let mut inner = Vec::new();
            for (l, &r) in chunk.iter().enumerate() {
                let (s, r) = (c * 4096 + l, r as usize);
                for (slot, rj) in src.nb.of(r).enumerate() {
                    let (tj, sj) = src.ranks.place[rj as usize];
                    if tj != t {
                        continue;
                    }
                    let record = rows.as_ref().map(|x| x.rows(s, sj as usize));
                    let Some((wij, wji)) = slot_weights(src, w, r, slot, record) else {
                        continue;
                    };
                    let (li, lj) = (local[s], local[sj as usize]);
                    let (lo, hi) = (li.min(lj), li.max(lj));
                    push_edges(&mut inner, wij, wji, lo, hi);
                }
            }
            inner
        })
        .collect();
    concatenate(parts)
}

/// `parts` one after the other in one list, copied in parallel. The list is allocated zeroed
/// (fresh pages from the system, first touched by the thread that copies into them), and each
/// part is freed once copied: the tile's edges are held about once at the end, not twice as a
/// concatenation holds them (the tiles in flight are budgeted by their edges' bytes). On a
/// 2M tile of 17.5M edges (two threads) this takes 0.07–0.13 s, where a copy on one thread into
/// a list reserved but not zeroed took 0.30–0.49 s.
fn concatenate(parts: Vec<Vec<Edge>>) -> Vec<Edge> {
    let mut edges: Vec<Edge> = bytemuck::zeroed_vec(parts.iter().map(Vec::len).sum());
    let mut rest = edges.as_mut_slice();
    let mut places = Vec::with_capacity(parts.len());
    for part in &parts {
        let (place, after) = std::mem::take(&mut rest).split_at_mut(part.len());
        places.push(place);
        rest = after;
    }
    parts
        .into_par_iter()
        .zip(places)
        .for_each(|(part, place)| place.copy_from_slice(&part));
    edges
}

/// Every edge of the graph whose ends lie in different tiles, in scene ids, ascending by
/// `(w, i, j)` and deduplicated: the same edges and weights that [`tile_edges`] gives inside a
/// tile. They are weighed before the tiles' passes so that each tile's pass can note, at each
/// border edge's place in the edge order, the component its end meets (module doc, "Bounded
/// memory and parallel passes: tiles"). About 0.1–0.2 % of the edges of a large scene.
pub(super) fn border_edges(src: &EdgeSource, w: &Weigher) -> Vec<Edge> {
    let n = src.nb.perm.len();
    let mut out: Vec<Edge> = (0..n)
        .into_par_iter()
        .with_min_len(4096)
        .flat_map_iter(|r| {
            let (t, i) = (src.ranks.place[r].0, src.nb.perm[r]);
            let mut edges = Vec::new();
            for (slot, rj) in src.nb.of(r).enumerate() {
                if src.ranks.place[rj as usize].0 == t {
                    continue;
                }
                let j = src.nb.perm[rj as usize];
                let record = w
                    .masks
                    .map(|m| RecordRows::Rows((m, i as usize), (m, j as usize)));
                if let Some((wij, wji)) = slot_weights(src, w, r, slot, record) {
                    push_edges(&mut edges, wij, wji, i.min(j), i.max(j));
                }
            }
            edges
        })
        .collect();
    out.par_sort_unstable();
    out.dedup();
    out
}

/// A tile's rows of the masks' record, in its space order ([`tile_edges`]).
enum TileRecord {
    /// One line per Gaussian (the default slot count).
    Packed(Vec<PackedRow>),
    /// A gathered part of the record (any other slot count).
    Rows(MaskRecord),
}

impl TileRecord {
    /// The rows of the tile's Gaussians at places `near` and `far`.
    fn rows(&self, near: usize, far: usize) -> RecordRows<'_> {
        match self {
            TileRecord::Packed(lines) => RecordRows::Packed(&lines[near], &lines[far]),
            TileRecord::Rows(r) => RecordRows::Rows((r, near), (r, far)),
        }
    }
}

/// The record rows of an edge's two ends, `(near, far)`: rows of a record (the scene's or a
/// gathered part of it), or packed lines.
#[derive(Clone, Copy)]
enum RecordRows<'a> {
    Rows((&'a MaskRecord, usize), (&'a MaskRecord, usize)),
    Packed(&'a PackedRow, &'a PackedRow),
}

impl RecordRows<'_> {
    /// The mask disagreement from the near end to the far one ([`MaskRecord::disagreement`]),
    /// or the other way round; `None` when they share no recorded view.
    fn disagreement(self, far_to_near: bool) -> Option<f32> {
        match (self, far_to_near) {
            (RecordRows::Rows(near, far), false) => MaskRecord::disagreement_between(near, far),
            (RecordRows::Rows(near, far), true) => MaskRecord::disagreement_between(far, near),
            (RecordRows::Packed(near, far), false) => near.disagreement(far),
            (RecordRows::Packed(near, far), true) => far.disagreement(near),
        }
    }
}

/// The weights `(w(i, j), w(j, i))` (bit patterns) of the edge from rank `r` (Gaussian `i`) to
/// its `slot`-th neighbour `j`, with the two ends' rows of the masks' record when there is
/// one; `w(j, i) = w(i, j)` when `j` does not list `i`. `None` when `j` lists `i` and `j < i`:
/// `j`'s own list gives that pair.
fn slot_weights(
    src: &EdgeSource,
    w: &Weigher,
    r: usize,
    slot: usize,
    record: Option<RecordRows>,
) -> Option<(u32, u32)> {
    let k = src.nb.k;
    let ru = src.nb.slots[r * k + slot] as usize;
    let (i, j) = (src.nb.perm[r], src.nb.perm[ru]);
    let back = src.nb.of(ru).position(|x| x as usize == r);
    if back.is_some() && j < i {
        return None;
    }
    let m_ij = record.map(|rows| w.known_or_unknown(rows.disagreement(false)));
    let wij = w.weight_with(src.geometric[r * k + slot], m_ij).to_bits();
    let wji = back.map_or(wij, |b| {
        let m_ji = record.map(|rows| w.known_or_unknown(rows.disagreement(true)));
        w.weight_with(src.geometric[ru * k + b], m_ji).to_bits()
    });
    Some((wij, wji))
}

/// Pushes the edge `(lo, hi)` with weight `wij`, and with `wji` too when that differs.
fn push_edges(out: &mut Vec<Edge>, wij: u32, wji: u32, lo: u32, hi: u32) {
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
