//! The tiles that bound the edges' memory (module doc, "Bounded memory and parallel passes: tiles").

/// Tiles: median splits on the two world axes of largest extent until each holds at most
/// `cap` Gaussians. Returns each Gaussian's tile and each tile's rectangle `(lo, hi)` on those
/// axes (bounds of its Gaussians).
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
