//! The tiles that bound the edges' memory (module doc, "Bounded memory and parallel passes: tiles").

/// Tiles: median splits on the two world axes of largest extent until each holds at most
/// `cap` Gaussians. Returns the two axes, each Gaussian's tile and each tile's rectangle
/// `(lo, hi)` on those axes (bounds of its Gaussians).
///
/// A split puts the `len / 2` Gaussians that come first by (coordinate, id) on the lower side,
/// so the tiles are the same sets whatever the order of the work; tiles are numbered depth
/// first, lower side first. The two sides of a split are planned in parallel on the current
/// rayon pool. The splits reorder the Gaussians' coordinates on the two axes together with
/// their ids ([`Point`]), so that each split reads its range in order instead of reading the
/// means at random places.
#[allow(clippy::type_complexity)]
pub(super) fn plan_tiles(
    means: &[[f32; 3]],
    cap: usize,
) -> ([usize; 2], Vec<u32>, Vec<([f32; 2], [f32; 2])>) {
    use rayon::prelude::*;
    let ax = largest_axes(means);
    let mut points: Vec<Point> = means
        .par_iter()
        .with_min_len(SEQUENTIAL_BELOW)
        .enumerate()
        .map(|(id, m)| Point {
            c: [m[ax[0]], m[ax[1]]],
            id: id as u32,
        })
        .collect();
    let leaves = split_tiles(cap.max(1), &mut points, 0);
    let mut tile_of = vec![0u32; means.len()];
    let mut rects = Vec::with_capacity(leaves.len());
    for (t, (a, b, rect)) in leaves.into_iter().enumerate() {
        for p in &points[a..b] {
            tile_of[p.id as usize] = t as u32;
        }
        rects.push(rect);
    }
    (ax, tile_of, rects)
}

/// A Gaussian's coordinates on the two split axes and its id: what the splits read and
/// reorder.
#[derive(Clone, Copy)]
struct Point {
    c: [f32; 2],
    id: u32,
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

/// The tiles of `points` (reordered in place so each tile is contiguous), which start at
/// `offset` in the whole array: `(start, end, rect)` per tile, depth first.
fn split_tiles(cap: usize, points: &mut [Point], offset: usize) -> Vec<(usize, usize, Rect)> {
    if points.is_empty() {
        return Vec::new();
    }
    let rect = rect_of(points);
    if points.len() <= cap {
        return vec![(offset, offset + points.len(), rect)];
    }
    let (rlo, rhi) = rect;
    let k = usize::from(rhi[0] - rlo[0] < rhi[1] - rlo[1]);
    let mid = points.len() / 2;
    points.select_nth_unstable_by(mid, |x, y| x.c[k].total_cmp(&y.c[k]).then(x.id.cmp(&y.id)));
    let (lower, upper) = points.split_at_mut(mid);
    let (mut left, right) = if lower.len() + upper.len() >= SEQUENTIAL_BELOW {
        rayon::join(
            || split_tiles(cap, lower, offset),
            || split_tiles(cap, upper, offset + mid),
        )
    } else {
        (
            split_tiles(cap, lower, offset),
            split_tiles(cap, upper, offset + mid),
        )
    };
    left.extend(right);
    left
}

/// The bounds of `points` on the two split axes.
fn rect_of(points: &[Point]) -> Rect {
    use rayon::prelude::*;
    let init = || ([f32::INFINITY; 2], [f32::NEG_INFINITY; 2]);
    let add = |(mut lo, mut hi): Rect, p: &Point| {
        for k in 0..2 {
            lo[k] = lo[k].min(p.c[k]);
            hi[k] = hi[k].max(p.c[k]);
        }
        (lo, hi)
    };
    if points.len() < SEQUENTIAL_BELOW {
        return points.iter().fold(init(), add);
    }
    points
        .par_iter()
        .fold(init, add)
        .reduce(init, |(l0, h0), (l1, h1)| {
            (
                [l0[0].min(l1[0]), l0[1].min(l1[1])],
                [h0[0].max(h1[0]), h0[1].max(h1[1])],
            )
        })
}
