//! The tiles that bound the edges' memory (module doc, "Bounded memory and parallel passes: tiles").

/// Tiles: median splits on the two world axes of largest extent until each holds at most
/// `cap` Gaussians. Returns the two axes, each Gaussian's tile and each tile's rectangle
/// `(lo, hi)` on those axes (bounds of its Gaussians).
///
/// A split puts the `len / 2` Gaussians that come first by (coordinate, id) on the lower side,
/// so the tiles are the same sets whatever the order of the work; tiles are numbered depth
/// first, lower side first. The two sides of a split are planned in parallel on the current
/// rayon pool, and each split selects its median among contiguous (coordinate, id) keys.
#[allow(clippy::type_complexity)]
pub(super) fn plan_tiles(
    means: &[[f32; 3]],
    cap: usize,
) -> ([usize; 2], Vec<u32>, Vec<([f32; 2], [f32; 2])>) {
    let ax = largest_axes(means);
    let mut perm: Vec<u32> = (0..means.len() as u32).collect();
    let leaves = split_tiles(means, ax, cap.max(1), &mut perm, 0);
    let mut tile_at = vec![0u32; perm.len()];
    let mut rects = Vec::with_capacity(leaves.len());
    for (t, (a, b, rect)) in leaves.into_iter().enumerate() {
        tile_at[a..b].fill(t as u32);
        rects.push(rect);
    }
    let mut tile_of = vec![0u32; means.len()];
    for (&r, &t) in perm.iter().zip(&tile_at) {
        tile_of[r as usize] = t;
    }
    (ax, tile_of, rects)
}

/// The two world axes of largest extent over `means` (ties to the lower axis).
fn largest_axes(means: &[[f32; 3]]) -> [usize; 2] {
    use rayon::prelude::*;
    let (lo, hi) = means
        .par_iter()
        .fold(bounds_init, |(mut lo, mut hi), m| {
            for a in 0..3 {
                lo[a] = lo[a].min(m[a]);
                hi[a] = hi[a].max(m[a]);
            }
            (lo, hi)
        })
        .reduce(bounds_init, |(l0, h0), (l1, h1)| {
            (
                [l0[0].min(l1[0]), l0[1].min(l1[1]), l0[2].min(l1[2])],
                [h0[0].max(h1[0]), h0[1].max(h1[1]), h0[2].max(h1[2])],
            )
        });
    let mut axes = [0usize, 1, 2];
    axes.sort_by(|&a, &b| (hi[b] - lo[b]).total_cmp(&(hi[a] - lo[a])).then(a.cmp(&b)));
    [axes[0], axes[1]]
}

fn bounds_init() -> ([f32; 3], [f32; 3]) {
    ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3])
}

/// A tile's rectangle `(lo, hi)` on the two split axes.
type Rect = ([f32; 2], [f32; 2]);

/// Below this many Gaussians a range is split on the calling thread.
const SEQUENTIAL_BELOW: usize = 1 << 16;

/// The tiles of `rows` (Gaussian ids, reordered in place so each tile is contiguous), which
/// start at `offset` in the whole permutation: `(start, end, rect)` per tile, depth first.
fn split_tiles(
    means: &[[f32; 3]],
    ax: [usize; 2],
    cap: usize,
    rows: &mut [u32],
    offset: usize,
) -> Vec<(usize, usize, Rect)> {
    if rows.is_empty() {
        return Vec::new();
    }
    let rect = rect_of(means, ax, rows);
    if rows.len() <= cap {
        return vec![(offset, offset + rows.len(), rect)];
    }
    let (rlo, rhi) = rect;
    let axis = if rhi[0] - rlo[0] >= rhi[1] - rlo[1] {
        ax[0]
    } else {
        ax[1]
    };
    let mid = rows.len() / 2;
    select_lower_half(means, axis, rows, mid);
    let (lower, upper) = rows.split_at_mut(mid);
    let (mut left, right) = if lower.len() + upper.len() >= SEQUENTIAL_BELOW {
        rayon::join(
            || split_tiles(means, ax, cap, lower, offset),
            || split_tiles(means, ax, cap, upper, offset + mid),
        )
    } else {
        (
            split_tiles(means, ax, cap, lower, offset),
            split_tiles(means, ax, cap, upper, offset + mid),
        )
    };
    left.extend(right);
    left
}

/// The bounds of `rows`' means on the axes `ax`.
fn rect_of(means: &[[f32; 3]], ax: [usize; 2], rows: &[u32]) -> Rect {
    use rayon::prelude::*;
    let init = || ([f32::INFINITY; 2], [f32::NEG_INFINITY; 2]);
    let add = |(mut lo, mut hi): ([f32; 2], [f32; 2]), &r: &u32| {
        for k in 0..2 {
            lo[k] = lo[k].min(means[r as usize][ax[k]]);
            hi[k] = hi[k].max(means[r as usize][ax[k]]);
        }
        (lo, hi)
    };
    if rows.len() < SEQUENTIAL_BELOW {
        return rows.iter().fold(init(), add);
    }
    rows.par_iter()
        .fold(init, add)
        .reduce(init, |(l0, h0), (l1, h1)| {
            (
                [l0[0].min(l1[0]), l0[1].min(l1[1])],
                [h0[0].max(h1[0]), h0[1].max(h1[1])],
            )
        })
}

/// Reorders `rows` so that its first `mid` are the `mid` smallest by (coordinate on `axis`, id).
fn select_lower_half(means: &[[f32; 3]], axis: usize, rows: &mut [u32], mid: usize) {
    use rayon::prelude::*;
    let mut keys: Vec<(f32, u32)> = rows
        .par_iter()
        .with_min_len(SEQUENTIAL_BELOW)
        .map(|&r| (means[r as usize][axis], r))
        .collect();
    keys.select_nth_unstable_by(mid, |x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)));
    rows.par_iter_mut()
        .with_min_len(SEQUENTIAL_BELOW)
        .zip(keys.par_iter())
        .for_each(|(r, k)| *r = k.1);
}
