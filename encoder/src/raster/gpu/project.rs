//! Step 1, the `project` kernel (`project.wgsl`: EWA projection of every Gaussian to a splat
//! and its tile rectangle), and step 2 on the CPU: tile binning and the depth sort.

use rayon::prelude::*;
use slag_common::camera::WorldToCamera;
use slag_common::{Error, Resource, Result};

use super::super::project::camera_point;
use super::buffers::{storage, storage_init};
use super::{Binned, GROUPS_X, GpuRasterizer, SEED_SALT, View};

impl GpuRasterizer {
    /// Runs the projection kernel and reads back every Gaussian's packed tile rectangle
    /// (`[x0 | y0 << 16, x1 | y1 << 16]`, empty when culled).
    pub(super) fn project(&self, view: &View) -> Result<Vec<[u32; 2]>> {
        let groups = self.n.div_ceil(256);
        let mut enc = self.device.create_command_encoder(&Default::default());
        if groups > 0 {
            let bg = self.bind(
                &self.pipelines.project,
                &[
                    (0, &view.params_buf),
                    (1, &self.means_opac),
                    (2, &self.scales),
                    (3, &self.quats),
                    (4, &self.splats),
                    (5, &self.isect),
                ],
            );
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipelines.project);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(groups.min(GROUPS_X), groups.div_ceil(GROUPS_X), 1);
        }
        let isect_bytes = self.n as u64 * 8;
        let read = self.submit_and_read(enc, &[(&self.isect, 0, isect_bytes)])?;
        let isect: Vec<[u32; 2]> = bytemuck::pod_collect_to_vec(&read[0]);
        Ok(isect)
    }

    /// Uploads the binned view (tile ranges, sorted ids) and allocates the per-pixel offsets
    /// and the scan's block sums.
    pub(super) fn upload_bins(&self, view: &View, ranges: &[[u32; 2]], ids: &[u32]) -> Binned {
        let b = Binned {
            ranges: storage_init(&self.device, "tile_ranges", bytemuck::cast_slice(ranges)),
            sorted_ids: storage_init(&self.device, "sorted_ids", bytemuck::cast_slice(ids)),
            offsets: storage(&self.device, "offsets", (view.n_pix as u64 + 1) * 4),
            block_sums: storage(&self.device, "block_sums", (view.n_blocks as u64 + 1) * 4),
            dummy: storage(&self.device, "dummy", 16),
            dummy_labels: storage(&self.device, "dummy_labels", 16),
        };
        self.noise(&b.offsets, SEED_SALT + 2);
        self.noise(&b.block_sums, SEED_SALT + 3);
        b
    }
}

/// Tile binning on the CPU: for every Gaussian with a non-empty tile rect (from the GPU
/// projection), one 128-bit key `tile | depth | id` per touched tile, sorted. The depth is the f64
/// camera-frame z of [`camera_point`] (bit-identical to the CPU reference's; positive f64 bit
/// patterns sort like their values), so both rasterizers order every tile identically, exact
/// ties included (by id). Returns per-tile `[start, end)` ranges into the sorted Gaussian ids.
pub(super) fn bin_and_sort(
    isect: &[[u32; 2]],
    means: &[[f32; 3]],
    w2c: &WorldToCamera,
    tiles_x: u32,
    n_tiles: u32,
) -> Result<(Vec<[u32; 2]>, Vec<u32>)> {
    let rect = |r: &[u32; 2]| {
        let (x0, y0, x1, y1) = (r[0] & 0xffff, r[0] >> 16, r[1] & 0xffff, r[1] >> 16);
        (x0, y0, x1.max(x0), y1.max(y0))
    };
    let counts: Vec<u64> = isect
        .par_iter()
        .map(|r| {
            let (x0, y0, x1, y1) = rect(r);
            (x1 - x0) as u64 * (y1 - y0) as u64
        })
        .collect();
    let total: u64 = counts.iter().sum();
    if total > u32::MAX as u64 {
        return Err(Error::limit(
            Resource::RasterEntries,
            format!("{total} tile intersections"),
            "2^32",
        ));
    }
    let mut keys = vec![0u128; total as usize];
    // Fill disjoint chunks in parallel: split `keys` at each Gaussian's start.
    let mut rest: &mut [u128] = &mut keys;
    let mut chunks = Vec::with_capacity(isect.len());
    for c in &counts {
        let (a, b) = rest.split_at_mut(*c as usize);
        chunks.push(a);
        rest = b;
    }
    chunks.into_par_iter().enumerate().for_each(|(id, chunk)| {
        if chunk.is_empty() {
            return;
        }
        let (x0, y0, x1, y1) = rect(&isect[id]);
        let depth = camera_point(means[id].map(f64::from), w2c).z.max(0.0);
        let low = ((depth.to_bits() as u128) << 32) | id as u128;
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
