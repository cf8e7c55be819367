//! The host reference of step 2: tile binning and the depth sort on the CPU, in f64 depths
//! ([`bin_and_sort`]), the order the GPU's binning and radix sort (`sort.rs`, `sort.wgsl`)
//! reproduces with f32 depths; the tests compare the two, and `cargo bench --bench binsort`
//! times it.

use rayon::prelude::*;
use slag_common::camera::WorldToCamera;
use slag_common::{Error, Resource, Result};

use super::super::project::camera_point;

/// Tile binning on the CPU: every (tile, Gaussian) intersection of the Gaussians' tile rects
/// (as the GPU projection computes them; `isect[k]` packed `[x0 | y0 << 16, x1 | y1 << 16]`, empty when culled)
/// ordered by `(tile, depth, id)`. The depth is the f64 camera-frame z of [`camera_point`]
/// rounded to f32 (the key of the CPU rasterizer and of the GPU's radix sort; positive f32 bit
/// patterns sort like their values), so all order every tile identically, equal f32 depths by id. Returns per-tile
/// `[start, end)` ranges into the sorted Gaussian ids (`n_tiles` ranges, tiles row-major with
/// `tiles_x` per row).
///
/// A counting sort by tile, then a sort of each tile's `(depth, id)` keys, in parallel: the
/// Gaussians are cut into chunks, each chunk counts its intersections per tile, the counts give
/// every (chunk, tile) its own slots, the chunks fill them, and the tiles are sorted one by one.
/// The same order as one sort of all `(tile, depth, id)` keys ([`bin_and_sort_reference`]), at a
/// fraction of its cost: the per-tile sorts are small and independent. Where the tile grid is so
/// large that the per-chunk counts would outweigh the intersections, the reference is used.
///
/// Errors: more than 2^32 intersections ([`Error::Limit`]); a rect outside the grid
/// ([`Error::Internal`]).
pub fn bin_and_sort(
    isect: &[[u32; 2]],
    means: &[[f32; 3]],
    w2c: &WorldToCamera,
    tiles_x: u32,
    n_tiles: u32,
) -> Result<(Vec<[u32; 2]>, Vec<u32>)> {
    let total = checked_total(isect.par_iter().map(area).sum())?;
    let n_t = n_tiles as usize;
    let n_chunks = (rayon::current_num_threads() * 4).clamp(1, isect.len().max(1));
    if (n_chunks as u64).saturating_mul(n_t as u64) > 4 * total.max(1 << 16) {
        return bin_and_sort_reference(isect, means, w2c, tiles_x, n_tiles);
    }
    let chunks = Chunks {
        isect,
        per_chunk: isect.len().div_ceil(n_chunks).max(1),
        tiles_x,
        n_tiles,
    };
    // 1. Intersections per (chunk, tile).
    let counts = chunks.tile_counts()?;
    // 2. Every chunk sorts its own keys by tile (a local counting sort: id order within a tile).
    let local = chunks.keys_by_tile(&counts, means, w2c);
    // 3. Tile ranges; each tile gathers its keys from every chunk (chunk order) and sorts them by
    //    (depth, id).
    let mut ranges = tile_ranges(&counts, n_t);
    let keys = gather_tiles(&local, &ranges, total);
    drop(local);
    let ids = keys.into_par_iter().map(|k| k as u32).collect();
    // Empty tiles read [0, 0), as in the reference.
    for r in ranges.iter_mut().filter(|r| r[0] == r[1]) {
        *r = [0, 0];
    }
    Ok((ranges, ids))
}

/// The Gaussians' tile rects cut into chunks of `per_chunk` for [`bin_and_sort`], on a grid of
/// `n_tiles` tiles, `tiles_x` per row.
struct Chunks<'a> {
    isect: &'a [[u32; 2]],
    per_chunk: usize,
    tiles_x: u32,
    n_tiles: u32,
}

/// One chunk's keys sorted by tile (id order within a tile) and, per tile, where its keys start
/// (`n_tiles + 1` offsets, the total last).
type ChunkKeys = (Vec<u128>, Vec<u32>);

impl Chunks<'_> {
    /// Counting step: per chunk, its intersections per tile.
    ///
    /// Errors: a rect outside the grid ([`Error::Internal`]).
    fn tile_counts(&self) -> Result<Vec<Vec<u32>>> {
        let (n_tiles, tiles_x) = (self.n_tiles, self.tiles_x);
        let outside = || {
            Error::internal(format!(
                "projection produced a tile outside the {n_tiles}-tile grid"
            ))
        };
        self.isect
            .par_chunks(self.per_chunk)
            .map(|chunk| {
                let mut h = vec![0u32; n_tiles as usize];
                for r in chunk {
                    let (x0, y0, x1, y1) = rect(r);
                    for y in y0..y1 {
                        for x in x0..x1 {
                            *h.get_mut((y * tiles_x + x) as usize).ok_or_else(outside)? += 1;
                        }
                    }
                }
                Ok(h)
            })
            .collect()
    }

    /// Local sort step: every chunk places its `(depth, id)` keys by tile, from its `counts`.
    fn keys_by_tile(
        &self,
        counts: &[Vec<u32>],
        means: &[[f32; 3]],
        w2c: &WorldToCamera,
    ) -> Vec<ChunkKeys> {
        self.isect
            .par_chunks(self.per_chunk)
            .zip(counts.par_iter())
            .enumerate()
            .map(|(c, (chunk, h))| {
                let mut starts = Vec::with_capacity(h.len() + 1);
                let mut next = 0u32;
                for &k in h {
                    starts.push(next);
                    next += k;
                }
                starts.push(next);
                let mut cursor = starts.clone();
                let mut keys = vec![0u128; next as usize];
                for (j, r) in chunk.iter().enumerate() {
                    let (x0, y0, x1, y1) = rect(r);
                    if x0 == x1 || y0 == y1 {
                        continue;
                    }
                    let key = depth_key(c * self.per_chunk + j, means, w2c);
                    for y in y0..y1 {
                        for x in x0..x1 {
                            let t = (y * self.tiles_x + x) as usize;
                            keys[cursor[t] as usize] = key;
                            cursor[t] += 1;
                        }
                    }
                }
                (keys, starts)
            })
            .collect()
    }
}

/// Range step: every tile's `[start, end)` in the sorted keys, tiles in order, from the chunks'
/// counts.
fn tile_ranges(counts: &[Vec<u32>], n_t: usize) -> Vec<[u32; 2]> {
    let mut ranges = vec![[0u32; 2]; n_t];
    let mut next = 0u32;
    for (t, r) in ranges.iter_mut().enumerate() {
        let len: u32 = counts.iter().map(|h| h[t]).sum();
        *r = [next, next + len];
        next += len;
    }
    ranges
}

/// Gather step: each tile's keys from every chunk (chunk order) into its range of the `total`
/// keys, then sorted by `(depth, id)`, tiles in parallel.
fn gather_tiles(local: &[ChunkKeys], ranges: &[[u32; 2]], total: u64) -> Vec<u128> {
    let mut keys = vec![0u128; total as usize];
    let segments = split_lengths(&mut keys, ranges.iter().map(|r| (r[1] - r[0]) as usize));
    segments.into_par_iter().enumerate().for_each(|(t, seg)| {
        let mut at = 0;
        for (chunk_keys, starts) in local {
            let part = &chunk_keys[starts[t] as usize..starts[t + 1] as usize];
            seg[at..at + part.len()].copy_from_slice(part);
            at += part.len();
        }
        seg.sort_unstable();
    });
    keys
}

/// A Gaussian's packed tile rect as `(x0, y0, x1, y1)`, end-exclusive, empty when `x1 <= x0` or
/// `y1 <= y0`.
fn rect(r: &[u32; 2]) -> (u32, u32, u32, u32) {
    let (x0, y0, x1, y1) = (r[0] & 0xffff, r[0] >> 16, r[1] & 0xffff, r[1] >> 16);
    (x0, y0, x1.max(x0), y1.max(y0))
}

/// The number of tiles a Gaussian's packed rect covers.
fn area(r: &[u32; 2]) -> u64 {
    let (x0, y0, x1, y1) = rect(r);
    (x1 - x0) as u64 * (y1 - y0) as u64
}

/// `total` (tile, Gaussian) intersections, checked against the u32 offsets of the kernels.
fn checked_total(total: u64) -> Result<u64> {
    if total > u32::MAX as u64 {
        return Err(Error::limit(
            Resource::RasterEntries,
            format!("{total} tile intersections"),
            "2^32",
        ));
    }
    Ok(total)
}

/// Gaussian `id`'s sort key within a tile: the bits of its f64 camera-frame depth (clamped at 0)
/// rounded to f32, above its id, so keys order by depth, equal f32 depths by id (the GPU's radix
/// sort uses the same f32 depths).
fn depth_key(id: usize, means: &[[f32; 3]], w2c: &WorldToCamera) -> u128 {
    let depth = camera_point(means[id].map(f64::from), w2c).z.max(0.0) as f32;
    ((depth.to_bits() as u128) << 32) | id as u128
}

/// `keys` cut into consecutive disjoint slices of the given lengths (their sum must not exceed
/// `keys.len()`), for filling or sorting in parallel.
fn split_lengths(keys: &mut [u128], lens: impl Iterator<Item = usize>) -> Vec<&mut [u128]> {
    let mut parts = Vec::with_capacity(lens.size_hint().0);
    let mut rest = keys;
    for len in lens {
        let (a, b) = rest.split_at_mut(len);
        parts.push(a);
        rest = b;
    }
    parts
}

/// [`bin_and_sort`] as one sort of all 128-bit `tile | depth | id` keys: the straightforward form,
/// kept as the test oracle, the benchmark baseline (`cargo bench --bench binsort`) and the
/// fallback for very large tile grids. Same inputs, outputs and errors.
pub fn bin_and_sort_reference(
    isect: &[[u32; 2]],
    means: &[[f32; 3]],
    w2c: &WorldToCamera,
    tiles_x: u32,
    n_tiles: u32,
) -> Result<(Vec<[u32; 2]>, Vec<u32>)> {
    let counts: Vec<u64> = isect.par_iter().map(area).collect();
    let total = checked_total(counts.iter().sum())?;
    let mut keys = vec![0u128; total as usize];
    // Fill disjoint chunks in parallel: split `keys` at each Gaussian's start.
    let chunks = split_lengths(&mut keys, counts.iter().map(|&c| c as usize));
    chunks.into_par_iter().enumerate().for_each(|(id, chunk)| {
        if chunk.is_empty() {
            return;
        }
        let (x0, y0, x1, y1) = rect(&isect[id]);
        let low = depth_key(id, means, w2c);
        let mut e = 0;
        for y in y0..y1 {
            for x in x0..x1 {
                chunk[e] = (((y * tiles_x + x) as u128) << 96) | low;
                e += 1;
            }
        }
    });
    keys.par_sort_unstable();
    let mut ranges = vec![[0u32; 2]; n_tiles as usize];
    let mut i = 0usize;
    while i < keys.len() {
        let tile = (keys[i] >> 96) as usize;
        let mut j = i;
        while j < keys.len() && (keys[j] >> 96) as usize == tile {
            j += 1;
        }
        if tile >= ranges.len() {
            return Err(Error::internal(format!(
                "projection produced tile {tile} outside the grid"
            )));
        }
        ranges[tile] = [i as u32, j as u32];
        i = j;
    }
    let ids = keys.into_iter().map(|k| k as u32).collect();
    Ok((ranges, ids))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use glam::{DMat3, DVec3};
    use proptest::prelude::*;

    fn pack(x0: u32, y0: u32, x1: u32, y1: u32) -> [u32; 2] {
        [x0 | y0 << 16, x1 | y1 << 16]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]

        /// The chunked counting sort gives exactly the reference's ranges and ids: random rects
        /// (empty, culled, single-tile, large), depths with exact ties (repeated means), any
        /// number of Gaussians relative to the chunks.
        #[test]
        fn counting_sort_equals_the_global_sort(
            tiles_x in 1u32..12,
            tiles_y in 1u32..9,
            gaussians in prop::collection::vec((0u32..12, 0u32..9, 0u32..5, 0u32..5, 0u8..6), 0..400),
        ) {
            let w2c = WorldToCamera { rotation: DMat3::IDENTITY, translation: DVec3::new(0.0, 0.0, 1.0) };
            let isect: Vec<[u32; 2]> = gaussians
                .iter()
                .map(|&(x, y, w, h, _)| {
                    let (x0, y0) = (x.min(tiles_x - 1), y.min(tiles_y - 1));
                    pack(x0, y0, (x0 + w).min(tiles_x), (y0 + h).min(tiles_y))
                })
                .collect();
            // Six depths only: many exact ties, broken by id.
            let means: Vec<[f32; 3]> = gaussians.iter().map(|g| [0.0, 0.0, g.4 as f32 * 0.5]).collect();
            let n_tiles = tiles_x * tiles_y;
            let fast = bin_and_sort(&isect, &means, &w2c, tiles_x, n_tiles).unwrap();
            let reference = bin_and_sort_reference(&isect, &means, &w2c, tiles_x, n_tiles).unwrap();
            prop_assert_eq!(fast, reference);
        }
    }

    #[test]
    fn a_rect_outside_the_grid_is_an_internal_error_in_both() {
        let w2c = WorldToCamera {
            rotation: DMat3::IDENTITY,
            translation: DVec3::ZERO,
        };
        let isect = vec![pack(0, 0, 1, 1), pack(2, 3, 3, 5)];
        let means = vec![[0.0, 0.0, 1.0]; 2];
        for r in [
            bin_and_sort(&isect, &means, &w2c, 4, 16),
            bin_and_sort_reference(&isect, &means, &w2c, 4, 16),
        ] {
            assert!(matches!(r, Err(Error::Internal(_))), "{r:?}");
        }
    }
}
