//! The exact k-nearest-neighbour search of the means over a uniform grid of cubic cells
//! (module doc, "Graph and weights"): every Gaussian's `k` nearest other means within
//! `max_edge`, in ascending `(d², id)` order, `d²` computed as `(dx² + dy²) + dz²` in `f32`
//! with `dx = m_j − m_i` (the R*-tree search this replaces computed it so; the same `d²` gives
//! the same neighbours, ties included).
//!
//! The means are sorted by cell (cells of side `c`, by default `max_edge / 4`, smaller where
//! that would put many means in a cell); a search scans the 3 × 3 × 3 cells around its own,
//! then further shells of cells, until the `k`-th distance found is shorter than the distance
//! to any cell not yet scanned (or that distance exceeds `max_edge`). Memory: 24 bytes per
//! Gaussian while it runs (cell order, the means in that order, the cell keys) plus the cells'
//! index, besides the result.

use rayon::prelude::*;
use rustc_hash::FxHashMap;

use super::SegmentControl;
use super::neighbours::{NO_NEIGHBOUR, Ranked};

/// Cells per axis at most: a cell's coordinates fit 21 bits of its 63-bit key.
const AXIS_CELLS: f64 = (1u64 << 21) as f64 - 2.0;

/// Means per occupied cell above which the cells are made smaller.
const CROWDED: f64 = 32.0;

/// Cell key → cell index.
type CellIndex = FxHashMap<u64, u32>;

/// The means sorted by cell.
struct Grid {
    /// Cell side, scene units.
    side: f64,
    /// Corner of cell (0, 0, 0).
    origin: [f64; 3],
    /// Gaussian ids in cell order (ascending id within a cell).
    order: Vec<u32>,
    /// The means in cell order.
    points: Vec<[f32; 3]>,
    /// Cell `c` holds `order[starts[c]..starts[c + 1]]`.
    starts: Vec<u32>,
    /// Each occupied cell's integer coordinates.
    cells: Vec<[i64; 3]>,
    /// The largest cell coordinate on each axis.
    last: [i64; 3],
    index: CellIndex,
}

fn cell_of(m: &[f32; 3], origin: &[f64; 3], side: f64) -> [i64; 3] {
    std::array::from_fn(|a| ((f64::from(m[a]) - origin[a]) / side).floor() as i64)
}

/// A cell's key: its three 21-bit coordinates interleaved bit by bit (a Morton, or Z-order,
/// code), so that the cells sorted by key keep cells near in space near in the order: the
/// means in cell order are the segmentation's space order ([`super::neighbours::Ranked`]).
fn key(c: [i64; 3]) -> u64 {
    (0..3).fold(0, |k, a| k | (spread(c[a] as u64) << a))
}

/// The low 21 bits of `v` spread to every third bit (bit `b` to bit `3b`).
fn spread(v: u64) -> u64 {
    let mut v = v & 0x1f_ffff;
    v = (v | (v << 32)) & 0x001f_0000_0000_ffff;
    v = (v | (v << 16)) & 0x001f_0000_ff00_00ff;
    v = (v | (v << 8)) & 0x100f_00f0_0f00_f00f;
    v = (v | (v << 4)) & 0x10c3_0c30_c30c_30c3;
    v = (v | (v << 2)) & 0x1249_2492_4924_9249;
    v
}

/// The means' bounding box.
fn bounds(means: &[[f32; 3]]) -> ([f64; 3], [f64; 3]) {
    let (lo, hi) = means
        .par_iter()
        .fold(
            || ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]),
            |(mut lo, mut hi), m| {
                for a in 0..3 {
                    lo[a] = lo[a].min(m[a]);
                    hi[a] = hi[a].max(m[a]);
                }
                (lo, hi)
            },
        )
        .reduce(
            || ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]),
            |(l1, h1), (l2, h2)| {
                (
                    std::array::from_fn(|a| l1[a].min(l2[a])),
                    std::array::from_fn(|a| h1[a].max(h2[a])),
                )
            },
        );
    (lo.map(f64::from), hi.map(f64::from))
}

impl Grid {
    /// The means binned into cells of side `max_edge / 4`, halved (down to `max_edge / 16`)
    /// while an occupied cell holds more than [`CROWDED`] means on average; never more than
    /// [`AXIS_CELLS`] cells per axis.
    fn build(means: &[[f32; 3]], max_edge: f32) -> Grid {
        let (lo, hi) = bounds(means);
        let extent = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max);
        let floor = (extent / AXIS_CELLS).max(f64::MIN_POSITIVE);
        let mut side = (f64::from(max_edge) / 4.0).max(floor);
        let mut keyed = Self::keyed(means, &lo, side);
        for _ in 0..2 {
            let occupied = 1 + keyed.par_windows(2).filter(|w| w[0].0 != w[1].0).count();
            let finer = (side / 2.0).max(floor);
            if (means.len() as f64) <= CROWDED * occupied as f64 || finer >= side {
                break;
            }
            side = finer;
            keyed = Self::keyed(means, &lo, side);
        }
        Self::from_keyed(means, lo, side, keyed)
    }

    /// Every mean's cell key and id, sorted.
    fn keyed(means: &[[f32; 3]], origin: &[f64; 3], side: f64) -> Vec<(u64, u32)> {
        let mut keyed: Vec<(u64, u32)> = means
            .par_iter()
            .enumerate()
            .map(|(i, m)| (key(cell_of(m, origin, side)), i as u32))
            .collect();
        keyed.par_sort_unstable();
        keyed
    }

    fn from_keyed(means: &[[f32; 3]], origin: [f64; 3], side: f64, keyed: Vec<(u64, u32)>) -> Grid {
        // Where each cell starts: the positions whose key differs from the one before (in
        // order, found in parallel).
        let mut starts: Vec<u32> = (0..keyed.len())
            .into_par_iter()
            .filter(|&pos| pos == 0 || keyed[pos - 1].0 != keyed[pos].0)
            .map(|pos| pos as u32)
            .collect();
        let cells: Vec<[i64; 3]> = starts
            .par_iter()
            .map(|&pos| cell_of(&means[keyed[pos as usize].1 as usize], &origin, side))
            .collect();
        let mut index = CellIndex::with_capacity_and_hasher(starts.len(), Default::default());
        for (c, &pos) in starts.iter().enumerate() {
            index.insert(keyed[pos as usize].0, c as u32);
        }
        starts.push(keyed.len() as u32);
        let last = std::array::from_fn(|a| cells.iter().map(|c| c[a]).max().unwrap_or(0));
        let order: Vec<u32> = keyed.into_par_iter().map(|(_, i)| i).collect();
        let points = order.par_iter().map(|&i| means[i as usize]).collect();
        Grid {
            side,
            origin,
            order,
            points,
            starts,
            cells,
            last,
            index,
        }
    }

    /// The positions (in cell order) of the means of the cell at `c`; empty when unoccupied.
    fn span(&self, c: [i64; 3]) -> std::ops::Range<usize> {
        if c.iter().any(|&v| !(0..1 << 21).contains(&v)) {
            return 0..0;
        }
        match self.index.get(&key(c)) {
            Some(&k) => self.starts[k as usize] as usize..self.starts[k as usize + 1] as usize,
            None => 0..0,
        }
    }
}

/// The `(d², id)` keys of the means offered, cut back to the `k` smallest whenever the `k`-th
/// is asked for (a selection over the batch, instead of an insertion per mean).
struct Nearest {
    k: usize,
    keys: Vec<u64>,
}

impl Nearest {
    fn offer(&mut self, d2: f32, j: u32) {
        self.keys
            .push((u64::from(d2.to_bits()) << 32) | u64::from(j));
    }
    /// The `k`-th smallest `d²` so far, when `k` were seen; the keys are cut back to the `k`
    /// smallest (unordered).
    fn kth(&mut self) -> Option<f32> {
        if self.keys.len() < self.k {
            return None;
        }
        let (_, kth, _) = self.keys.select_nth_unstable(self.k - 1);
        let kth = *kth;
        self.keys.truncate(self.k);
        Some(f32::from_bits((kth >> 32) as u32))
    }
    /// The `k` smallest keys (or all, when fewer), ascending.
    fn best(&mut self) -> &[u64] {
        if self.keys.len() > self.k {
            self.keys.select_nth_unstable(self.k - 1);
            self.keys.truncate(self.k);
        }
        self.keys.sort_unstable();
        &self.keys
    }
}

/// `d²` exactly as the module doc says.
fn distance_2(a: &[f32; 3], b: &[f32; 3]) -> f32 {
    let (dx, dy, dz) = (b[0] - a[0], b[1] - a[1], b[2] - a[2]);
    dx * dx + dy * dy + dz * dz
}

/// Rounds the cells' searches are cut into: each round runs on `ctl`'s pool of its moment, so
/// a segmentation widened while it searches ([`SegmentControl::set_pool`]) searches its
/// remaining cells on all the threads it was given.
const SEARCH_ROUNDS: usize = 32;

/// Every Gaussian's `k` nearest other means within `max_edge` (module doc), the cells searched
/// in [`SEARCH_ROUNDS`] rounds on `ctl`'s pool. Once `ctl` is stopped the remaining Gaussians
/// get none: the caller discards such a partial result.
pub(super) fn neighbours(
    means: &[[f32; 3]],
    k: usize,
    max_edge: f32,
    ctl: &SegmentControl,
) -> Ranked {
    let t0 = std::time::Instant::now();
    let grid = ctl.run(|| Grid::build(means, max_edge));
    let build_s = t0.elapsed().as_secs_f64();
    let h2 = max_edge * max_edge;
    // Filled on every thread: 40 bytes per Gaussian at k = 10.
    let mut ids = Vec::with_capacity(means.len() * k);
    ids.par_extend(rayon::iter::repeat_n(NO_NEIGHBOUR, means.len() * k));
    let mut parts: Vec<(usize, &mut [u32])> = Vec::with_capacity(grid.cells.len());
    let mut rest: &mut [u32] = &mut ids;
    for c in 0..grid.cells.len() {
        let len = (grid.starts[c + 1] - grid.starts[c]) as usize * k;
        let (head, tail) = std::mem::take(&mut rest).split_at_mut(len);
        parts.push((c, head));
        rest = tail;
    }
    let per_round = parts.len().div_ceil(SEARCH_ROUNDS).max(1);
    let mut parts = parts.into_iter();
    let t1 = std::time::Instant::now();
    while !ctl.is_stopped() {
        let round: Vec<(usize, &mut [u32])> = parts.by_ref().take(per_round).collect();
        if round.is_empty() {
            break;
        }
        ctl.run(|| {
            round.into_par_iter().for_each(|(c, out)| {
                if !ctl.is_stopped() {
                    search_cell(&grid, c, k, h2, out);
                }
            });
        });
    }
    let search_s = t1.elapsed().as_secs_f64();
    let nb = Ranked::from_cell_order(k, ids, grid.order);
    tracing::debug!(
        target: "slag_encoder::segments",
        cells = grid.cells.len(),
        build_s = format!("{build_s:.2}"),
        search_s = format!("{search_s:.2}"),
        total_s = format!("{:.2}", t0.elapsed().as_secs_f64()),
        "neighbour search"
    );
    nb
}

/// The neighbours of every mean of cell `c` into `out`, `k` slots each, in cell order.
fn search_cell(grid: &Grid, c: usize, k: usize, h2: f32, out: &mut [u32]) {
    let at = grid.cells[c];
    let mut block = Vec::with_capacity(27);
    for dx in -1..=1 {
        for dy in -1..=1 {
            for dz in -1..=1 {
                let s = grid.span([at[0] + dx, at[1] + dy, at[2] + dz]);
                if !s.is_empty() {
                    block.push(s);
                }
            }
        }
    }
    let own = grid.starts[c] as usize..grid.starts[c + 1] as usize;
    let mut near = Nearest {
        k,
        keys: Vec::with_capacity(64),
    };
    for (pos, slots) in own.zip(out.chunks_mut(k)) {
        let (i, p) = (grid.order[pos], grid.points[pos]);
        near.keys.clear();
        for s in &block {
            offer_span(grid, s.clone(), i, &p, h2, &mut near);
        }
        let mut shell = 1;
        while !settled(grid, &p, at, shell, &mut near, h2) {
            shell += 1;
            for cell in shell_cells(at, shell) {
                offer_span(grid, grid.span(cell), i, &p, h2, &mut near);
            }
        }
        for (slot, &b) in slots.iter_mut().zip(near.best()) {
            *slot = b as u32;
        }
    }
}

/// Offers the means at positions `s` to `near`, but `i` itself and those beyond `h2`.
fn offer_span(
    grid: &Grid,
    s: std::ops::Range<usize>,
    i: u32,
    p: &[f32; 3],
    h2: f32,
    near: &mut Nearest,
) {
    for pos in s {
        let j = grid.order[pos];
        if j == i {
            continue;
        }
        let d2 = distance_2(p, &grid.points[pos]);
        if d2 <= h2 {
            near.offer(d2, j);
        }
    }
}

/// Whether no mean outside the cube of cells within `shell` of `at` can enter `near`: the
/// cube holds every cell, or the `k`-th distance found is shorter than the distance from `p` to
/// outside the cube, or that distance exceeds `max_edge` (both with a margin for rounding).
fn settled(
    grid: &Grid,
    p: &[f32; 3],
    at: [i64; 3],
    shell: i64,
    near: &mut Nearest,
    h2: f32,
) -> bool {
    if (0..3).all(|a| at[a] - shell <= 0 && at[a] + shell >= grid.last[a]) {
        return true;
    }
    let side = grid.side;
    let mut gap = f64::INFINITY;
    for a in 0..3 {
        let x = f64::from(p[a]) - grid.origin[a];
        let lo = (at[a] - shell) as f64 * side;
        let hi = (at[a] + shell + 1) as f64 * side;
        gap = gap.min(x - lo).min(hi - x);
    }
    let gap = (gap - 1e-6 * side).max(0.0);
    let reach = gap * gap * (1.0 - 1e-5);
    if reach > f64::from(h2) {
        return true;
    }
    near.kth().is_some_and(|d2| f64::from(d2) < reach)
}

/// The cells at Chebyshev distance exactly `shell` from `at`.
fn shell_cells(at: [i64; 3], shell: i64) -> impl Iterator<Item = [i64; 3]> {
    let r = shell;
    (-r..=r).flat_map(move |dx| {
        (-r..=r).flat_map(move |dy| {
            let edge = dx.abs() == r || dy.abs() == r;
            let dzs: Vec<i64> = if edge {
                (-r..=r).collect()
            } else {
                vec![-r, r]
            };
            dzs.into_iter()
                .map(move |dz| [at[0] + dx, at[1] + dy, at[2] + dz])
        })
    })
}

#[cfg(test)]
mod tests {
    use super::key;

    #[test]
    fn cell_keys_interleave_the_coordinates_bit_by_bit() {
        let slow = |c: [i64; 3]| {
            (0..21).fold(0u64, |k, b| {
                (0..3).fold(k, |k, a| k | ((c[a] as u64 >> b) & 1) << (3 * b + a))
            })
        };
        let last = (1i64 << 21) - 1;
        let corners = [
            [0, 0, 0],
            [1, 0, 0],
            [0, 1, 0],
            [0, 0, 1],
            [last; 3],
            [5, 77, 1 << 20],
        ];
        let mut s = 7u64;
        let random = (0..1000).map(|_| {
            std::array::from_fn(|_| {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (s >> 43) as i64
            })
        });
        for c in corners.into_iter().chain(random) {
            assert_eq!(key(c), slow(c), "{c:?}");
        }
        // Cells next to each other share a long key prefix: a 2×2×2 block is 8 keys in a row.
        let block: Vec<u64> = (0..8).map(|b| key([b & 1, (b >> 1) & 1, b >> 2])).collect();
        assert_eq!(block, (0..8).collect::<Vec<u64>>());
    }
}
