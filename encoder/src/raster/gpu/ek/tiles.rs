//! The reduction of the kept records, tile by tile: runs of whole blocks of Gaussians whose
//! records and outputs fit one buffer, each sorted by (Gaussian, label) and reduced by
//! `ek.wgsl`, its outputs staged and read back into the host's kept pairs.

use slag_common::{Error, Resource, Result};

use super::{BLOCK_GAUSSIANS, EkParams, Kept, KeptPart, MAX_KEEP, TILE_BYTES};
use crate::raster::gpu::buffers::{storage, storage_init};
use crate::raster::gpu::reduce::record_radix_shifts;
use crate::raster::gpu::sort::{SortBuffers, groups_2d};
use crate::raster::gpu::{GROUPS_X, GpuRasterizer, Params};
use crate::raster::{DeviceReduce, KeptReduced, KeptTile};

/// A tile of the reduction: blocks `[b0, b1)` and, per part, its records there.
pub(in crate::raster::gpu) struct Tile {
    pub(in crate::raster::gpu) g0: u32,
    pub(in crate::raster::gpu) n_tile: u32,
    /// Per part with records: (part, first record, count).
    pub(in crate::raster::gpu) ranges: Vec<(usize, u32, u32)>,
    pub(in crate::raster::gpu) records: u64,
}

impl GpuRasterizer {
    pub(in crate::raster::gpu) fn ek_uniform(&self, p: &EkParams) -> wgpu::Buffer {
        crate::raster::gpu::buffers::uniform_init(&self.device, "ek_params", p)
    }

    /// The tiles of the reduction: runs of whole blocks whose records fit one tile buffer and
    /// whose outputs (`out_per_gaussian` bytes each) fit `tile_bytes` (at least one block).
    ///
    /// Errors: one block holds more records than a tile can ([`Error::Limit`] `GpuBinding`).
    pub(in crate::raster::gpu) fn kept_tiles(
        &self,
        parts: &[KeptPart],
        blocks: std::ops::Range<usize>,
        out_per_gaussian: u64,
        tile_bytes: u64,
    ) -> Result<Vec<Tile>> {
        self.kept_tiles_within(parts, blocks, out_per_gaussian, tile_bytes, usize::MAX)
    }

    /// [`Self::kept_tiles`] with no tile across a multiple of `chunk_blocks` blocks (the chunks
    /// of the streamed reduction's state, [`crate::raster::gpu::fold`]).
    ///
    /// Errors: as [`Self::kept_tiles`].
    pub(in crate::raster::gpu) fn kept_tiles_within(
        &self,
        parts: &[KeptPart],
        blocks: std::ops::Range<usize>,
        out_per_gaussian: u64,
        tile_bytes: u64,
        chunk_blocks: usize,
    ) -> Result<Vec<Tile>> {
        let record_cap = (self.max_binding().min(tile_bytes) / 16).saturating_sub(1);
        let gaussian_cap = (self.max_binding().min(tile_bytes) / out_per_gaussian.max(1))
            .max(u64::from(BLOCK_GAUSSIANS));
        let block_records = |b: usize| -> u64 {
            parts
                .iter()
                .map(|p| u64::from(p.starts[b + 1] - p.starts[b]))
                .sum()
        };
        let mut tiles = Vec::new();
        let mut b0 = blocks.start;
        while b0 < blocks.end {
            let mut b1 = b0;
            let mut records = 0u64;
            while b1 < blocks.end {
                let more = block_records(b1);
                let gaussians = (b1 + 1 - b0) as u64 * u64::from(BLOCK_GAUSSIANS);
                let chunk_end = b1 > b0 && b1.is_multiple_of(chunk_blocks.max(1));
                if b1 > b0 && (records + more > record_cap || gaussians > gaussian_cap || chunk_end)
                {
                    break;
                }
                if more > record_cap {
                    return Err(Error::limit(
                        Resource::GpuBinding,
                        format!("{more} kept label sums for {BLOCK_GAUSSIANS} Gaussians"),
                        format!("{record_cap} per tile of the device reduction"),
                    ));
                }
                records += more;
                b1 += 1;
            }
            let g0 = b0 as u32 * BLOCK_GAUSSIANS;
            let g1 = (b1 as u32 * BLOCK_GAUSSIANS).min(self.n);
            let ranges = parts
                .iter()
                .enumerate()
                .filter_map(|(i, p)| {
                    let (s, e) = (p.starts[b0], p.starts[b1]);
                    (e > s).then_some((i, s, e - s))
                })
                .collect();
            tiles.push(Tile {
                g0,
                n_tile: g1 - g0,
                ranges,
                records,
            });
            b0 = b1;
        }
        Ok(tiles)
    }

    /// Reduces every kept view (see the module docs), tile by tile of Gaussian ids ascending
    /// (those of [`DeviceReduce::gaussians`] only, when given), handing each tile's observed
    /// Gaussians to `sink`; keeping stops, and the kept records are freed with the rasterizer
    /// (or when keeping starts again). Returns the number of tiles and the codebook.
    ///
    /// Errors: nothing kept ([`Error::Internal`]); `p.keep` above [`MAX_KEEP`] ([`Error::Param`]);
    /// a range of Gaussians not on block bounds ([`Error::Internal`]); device failures; `sink`'s.
    pub(in crate::raster::gpu) fn reduce_kept_tiles(
        &mut self,
        p: &DeviceReduce,
        sink: &mut dyn FnMut(KeptTile) -> Result<()>,
    ) -> Result<KeptReduced> {
        let Some(mut kept) = self.kept.take() else {
            return Err(Error::internal("the device reduction has no kept views"));
        };
        if p.keep == 0 || p.keep > MAX_KEEP {
            return Err(Error::param(
                "mixture_keep",
                p.keep,
                format!("1 to {MAX_KEEP} for the device reduction (or --reduce host)"),
            ));
        }
        let blocks = self.blocks_of(p.gaussians.map_or(0..self.n, |(a, b)| a..b))?;
        kept.sort_by_view();
        let dim = kept.dim;
        let tile_bytes = self.reduce_tile_bytes.unwrap_or(TILE_BYTES);
        let out_per_gaussian = 8 + p.keep as u64 * 8 + if p.dense { dim as u64 * 4 } else { 0 };
        let tiles = self.kept_tiles(&kept.parts, blocks, out_per_gaussian, tile_bytes)?;
        let tables = storage_init(
            &self.device,
            "ek_tables",
            bytemuck::cast_slice(&kept.tables),
        );
        let codebook = storage_init(
            &self.device,
            "ek_codebook",
            bytemuck::cast_slice(&kept.codebook),
        );
        let shared = TileShared {
            kept: &kept,
            tables: &tables,
            codebook: &codebook,
            p,
        };
        let mut sort: Option<SortBuffers> = None;
        let largest = tiles.iter().map(|t| u64::from(t.n_tile)).max().unwrap_or(0);
        let staging = TileStaging::new(&self.device, largest, p, dim);
        let (mut device_s, mut sink_s) = (0.0, 0.0);
        for tile in &tiles {
            let t0 = std::time::Instant::now();
            let out = self.reduce_tile(&shared, tile, &mut sort, &staging)?;
            let t1 = std::time::Instant::now();
            sink(out)?;
            device_s += (t1 - t0).as_secs_f64();
            sink_s += t1.elapsed().as_secs_f64();
        }
        // Where the reduction's time goes: the tiles on the device (with their readback), and
        // the host's sink (the mixture's rows, the dense rows) after each.
        tracing::info!(
            target: "slag_encoder::pipeline",
            tiles = tiles.len(),
            device_s = format!("{device_s:.2}"),
            sink_s = format!("{sink_s:.2}"),
            "device reduction"
        );
        let codebook = std::mem::take(&mut kept.codebook);
        let (peak_kept_bytes, records_bytes) = (kept.peak_bytes, kept.total_bytes);
        self.spent_kept = Some(kept);
        Ok(KeptReduced {
            tiles: tiles.len(),
            codebook,
            waves: 1,
            state_bytes: 0,
            peak_kept_bytes,
            records_bytes,
        })
    }

    /// One tile: its records gathered view by view, sorted by Gaussian, reduced, read back.
    fn reduce_tile(
        &self,
        s: &TileShared<'_>,
        tile: &Tile,
        sort: &mut Option<SortBuffers>,
        staging: &TileStaging,
    ) -> Result<KeptTile> {
        let (p, dim) = (s.p, s.kept.dim);
        let n = tile.records as u32;
        let mut phases = TilePhases::new();
        // The tile's records after a 4-word header (the layout record_keys reads).
        let recs = storage(&self.device, "ek_tile_records", 16 + tile.records * 16);
        let mut enc = self.device.create_command_encoder(&Default::default());
        let views = &s.kept.views;
        let segs = gather_tile_records(&mut enc, &s.kept.parts, tile, &recs, |part| {
            let [base, row, _] = views[part.view as usize];
            [base, row]
        });
        let segs_buf = storage_init(&self.device, "ek_segments", bytemuck::cast_slice(&segs));
        let out = TileOutputs::new(&self.device, tile, p, dim);
        for b in [&out.meta, &out.kept, &out.rows, &out.run_start] {
            enc.clear_buffer(b, 0, None);
        }
        enc = self.phase_end(enc, &mut phases)?;
        let order = if n > 0 {
            Some(self.sort_tile(&mut enc, &recs, n, sort)?)
        } else {
            None
        };
        enc = self.phase_end(enc, &mut phases)?;
        if let Some(order) = &order {
            let inputs = [&recs, order, &segs_buf];
            self.encode_ek_reduce(&mut enc, s, tile, segs.len() as u32, inputs, &out);
        }
        enc = self.phase_end(enc, &mut phases)?;
        let sizes = output_bytes(u64::from(tile.n_tile), p, dim);
        let staged: Vec<(&wgpu::Buffer, u64)> = staging.buffers.iter().zip(sizes).collect();
        for (src, &(dst, size)) in [&out.meta, &out.kept, &out.rows].into_iter().zip(&staged) {
            enc.copy_buffer_to_buffer(src, 0, dst, 0, size);
        }
        let output = self.submit_and_map_all(enc, &staged, |read| {
            phases.mark();
            tile_output(tile, p, dim, read)
        })??;
        phases.mark();
        phases.log(tile);
        Ok(output)
    }

    /// With the reduction's debug log on, ends a phase of [`Self::reduce_tile`]: submits `enc`,
    /// waits for the device and marks the time, returning a new encoder; otherwise returns `enc`
    /// as it is (one submission per tile).
    ///
    /// Errors: waiting for the device fails.
    fn phase_end(
        &self,
        enc: wgpu::CommandEncoder,
        phases: &mut TilePhases,
    ) -> Result<wgpu::CommandEncoder> {
        if phases.marks.is_none() {
            return Ok(enc);
        }
        self.queue.submit([enc.finish()]);
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| {
                crate::raster::gpu::gpu_err("waiting for the device reduction failed", e)
            })?;
        phases.mark();
        Ok(self.device.create_command_encoder(&Default::default()))
    }

    /// Dispatch step of [`Self::reduce_tile`]: `run_starts` over the tile's sorted records, then
    /// `ek_reduce` over the tile's Gaussians, reading `[records, sorted order, segments]` and
    /// writing its outputs.
    fn encode_ek_reduce(
        &self,
        enc: &mut wgpu::CommandEncoder,
        s: &TileShared<'_>,
        tile: &Tile,
        n_segments: u32,
        [recs, order, segs]: [&wgpu::Buffer; 3],
        out: &TileOutputs,
    ) {
        let (kept, p) = (s.kept, s.p);
        let n = tile.records as u32;
        let params = self.ek_uniform(&EkParams {
            min_total_weight: p.min_total_weight,
            n_records: n,
            g0: tile.g0,
            n_tile: tile.n_tile,
            dim: kept.dim as u32,
            keep: p.keep as u32,
            n_segments,
            groups_x: GROUPS_X,
            dense: u32::from(p.dense),
            n_blocks: 0,
            pad0: 0,
        });
        let starts = self.bind(
            &kept.run_starts,
            &[(0, &params), (1, recs), (2, order), (11, &out.run_start)],
        );
        let bg = self.bind(
            &kept.ek_reduce,
            &[
                (0, &params),
                (1, recs),
                (2, order),
                (3, segs),
                (4, s.tables),
                (5, s.codebook),
                (6, &out.meta),
                (7, &out.kept),
                (8, &out.rows),
                (11, &out.run_start),
            ],
        );
        let mut pass = enc.begin_compute_pass(&Default::default());
        pass.set_pipeline(&kept.run_starts);
        pass.set_bind_group(0, &starts, &[]);
        let (x, y) = groups_2d(n.div_ceil(256));
        pass.dispatch_workgroups(x, y, 1);
        pass.set_pipeline(&kept.ek_reduce);
        pass.set_bind_group(0, &bg, &[]);
        let (x, y) = groups_2d(tile.n_tile);
        pass.dispatch_workgroups(x, y, 1);
    }

    /// Records the stable sort of the tile's `n` records by Gaussian (the raster module's
    /// `record_keys` and radix passes over the Gaussian-id bits only) and returns the buffer of
    /// sorted record indices.
    pub(in crate::raster::gpu) fn sort_tile(
        &self,
        enc: &mut wgpu::CommandEncoder,
        recs: &wgpu::Buffer,
        n: u32,
        kept: &mut Option<SortBuffers>,
    ) -> Result<wgpu::Buffer> {
        let sb = self.sort_buffers(kept.take(), u64::from(n));
        let shifts = record_radix_shifts(0, self.n);
        let base = Params {
            n_keys: n,
            n_pixels: n,
            groups_x: GROUPS_X,
            ..bytemuck::Zeroable::zeroed()
        };
        let radix = self.radix_params(n, &shifts, &base);
        let params = self.uniform(&base);
        let (x, y) = groups_2d(n.div_ceil(256));
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            let p = &self.pipelines;
            let bg = self.bind(
                &p.record_keys,
                &[
                    (0, &params),
                    (13, recs),
                    (16, &sb.keys[0]),
                    (17, &sb.vals[0]),
                ],
            );
            pass.set_pipeline(&p.record_keys);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(x, y, 1);
            self.encode_radix_passes(&mut pass, &sb, n, &radix);
        }
        let order = sb.vals[shifts.len() % 2].clone();
        *kept = Some(sb);
        Ok(order)
    }
}

/// Gather step of [`GpuRasterizer::reduce_tile`]: records the copies of every part's records
/// in the tile into `recs` (after its 4-word header) and returns per part its segment: first
/// record, view, table base, codebook row (one zero segment when the tile has none).
pub(in crate::raster::gpu) fn gather_tile_records(
    enc: &mut wgpu::CommandEncoder,
    parts: &[KeptPart],
    tile: &Tile,
    recs: &wgpu::Buffer,
    table_and_row: impl Fn(&KeptPart) -> [u32; 2],
) -> Vec<[u32; 4]> {
    let mut segs: Vec<[u32; 4]> = Vec::with_capacity(tile.ranges.len().max(1));
    let mut at = 0u32;
    for &(i, first, count) in &tile.ranges {
        let part = &parts[i];
        let [base, row] = table_and_row(part);
        segs.push([at, part.view, base, row]);
        enc.copy_buffer_to_buffer(
            &part.records,
            u64::from(first) * 16,
            recs,
            16 + u64::from(at) * 16,
            u64::from(count) * 16,
        );
        at += count;
    }
    if segs.is_empty() {
        segs.push([0; 4]);
    }
    segs
}

/// The outputs of one tile of the reduction: per Gaussian its meta (observed, total weight)
/// and kept pairs, and with `p.dense` its row (a placeholder without); and per Gaussian where
/// its sorted records start (`run_starts`, read by `ek_reduce`).
struct TileOutputs {
    meta: wgpu::Buffer,
    kept: wgpu::Buffer,
    rows: wgpu::Buffer,
    run_start: wgpu::Buffer,
}

impl TileOutputs {
    /// Allocation step of [`GpuRasterizer::reduce_tile`]: the tile's output buffers.
    fn new(device: &wgpu::Device, tile: &Tile, p: &DeviceReduce, dim: usize) -> Self {
        let n_tile = u64::from(tile.n_tile);
        let bytes = output_bytes(n_tile, p, dim);
        TileOutputs {
            meta: storage(device, "ek_meta", bytes[0]),
            kept: storage(device, "ek_kept", bytes[1]),
            // A placeholder without the dense rows.
            rows: storage(device, "ek_rows", bytes.get(2).copied().unwrap_or(4)),
            run_start: storage(device, "ek_run_start", n_tile * 4),
        }
    }
}

/// Where one tile's time goes, kept only while the reduction's debug log is on (target
/// `slag_encoder::pipeline`): the device is then waited for after each phase (gather and
/// clear, sort, reduce, readback), and the host's conversion of the outputs is timed.
struct TilePhases {
    /// The start, then one instant per phase end.
    marks: Option<Vec<std::time::Instant>>,
}

impl TilePhases {
    const NAMES: [&str; 5] = ["gather_s", "sort_s", "reduce_s", "read_s", "output_s"];

    fn new() -> Self {
        let on = tracing::enabled!(target: "slag_encoder::pipeline", tracing::Level::DEBUG);
        TilePhases {
            marks: on.then(|| vec![std::time::Instant::now()]),
        }
    }

    fn mark(&mut self) {
        if let Some(m) = &mut self.marks {
            m.push(std::time::Instant::now());
        }
    }

    /// The debug line of one tile: its Gaussians, records and seconds per phase.
    fn log(&self, tile: &Tile) {
        let Some(m) = &self.marks else { return };
        let phases: Vec<String> = Self::NAMES
            .iter()
            .zip(m.windows(2))
            .map(|(name, w)| format!("{name}={:.3}", (w[1] - w[0]).as_secs_f64()))
            .collect();
        tracing::debug!(
            target: "slag_encoder::pipeline",
            g0 = tile.g0,
            gaussians = tile.n_tile,
            records = tile.records,
            phases = phases.join(" "),
            "device reduction tile"
        );
    }
}

/// The host-visible buffers each tile's outputs are copied to and read from (meta, kept pairs,
/// and with `p.dense` the rows), made once for the largest tile: a new mapping per tile of
/// hundreds of MB costs more than the copy.
pub(in crate::raster::gpu) struct TileStaging {
    pub(in crate::raster::gpu) buffers: Vec<wgpu::Buffer>,
}

impl TileStaging {
    pub(in crate::raster::gpu) fn new(
        device: &wgpu::Device,
        largest: u64,
        p: &DeviceReduce,
        dim: usize,
    ) -> Self {
        let buffers = output_bytes(largest, p, dim)
            .into_iter()
            .map(|size| {
                device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("ek_staging"),
                    size: size.max(4).next_multiple_of(4),
                    usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                })
            })
            .collect();
        TileStaging { buffers }
    }
}

/// Bytes of the outputs read back for `n` Gaussians: meta, kept pairs, and with `p.dense`
/// the rows.
pub(in crate::raster::gpu) fn output_bytes(n: u64, p: &DeviceReduce, dim: usize) -> Vec<u64> {
    let mut sizes = vec![n * 8, n * p.keep as u64 * 8];
    if p.dense {
        sizes.push(n * dim as u64 * 4);
    }
    sizes
}

/// What every tile of one reduction shares.
struct TileShared<'a> {
    kept: &'a Kept,
    tables: &'a wgpu::Buffer,
    codebook: &'a wgpu::Buffer,
    p: &'a DeviceReduce,
}

/// The observed Gaussians of a tile from its read-back outputs (`read`: meta, kept pairs, and
/// with `p.dense` the rows), converted on every thread in chunks of Gaussians, then joined in
/// order (millions of Gaussians per tile).
///
/// Errors: the driver cut a Gaussian's reduction short ([`Error::Gpu`], see [`cut_short`]).
pub(in crate::raster::gpu) fn tile_output(
    tile: &Tile,
    p: &DeviceReduce,
    dim: usize,
    read: &[&[u8]],
) -> Result<KeptTile> {
    use rayon::prelude::*;
    const CHUNK: usize = 1 << 16;
    let n_tile = tile.n_tile as usize;
    cut_short(tile, read[0])?;
    let parts: Vec<KeptTile> = (0..n_tile.div_ceil(CHUNK))
        .into_par_iter()
        .map(|c| tile_output_range(tile, p, dim, read, c * CHUNK..((c + 1) * CHUNK).min(n_tile)))
        .collect();
    let mut out = KeptTile {
        kept_starts: vec![0],
        ..KeptTile::default()
    };
    for part in parts {
        let base = out.kept.len() as u32;
        out.ids.extend_from_slice(&part.ids);
        out.total_weights.extend_from_slice(&part.total_weights);
        out.kept_starts
            .extend(part.kept_starts[1..].iter().map(|&e| base + e));
        out.kept.extend_from_slice(&part.kept);
        out.rows.extend_from_slice(&part.rows);
    }
    Ok(out)
}

/// `gmeta`'s first word for a Gaussian whose reduction the driver cut short (`ek.wgsl`
/// `CUT_SHORT`).
const CUT_SHORT: u32 = 2;

/// Check step of [`tile_output`]: no Gaussian of the tile's meta (`[observed, Σ a bits]` per
/// Gaussian) is marked cut short. Some drivers (lavapipe) end every loop of a shader
/// invocation once they ran a fixed number of iterations in all; `ek_reduce` (or, streamed,
/// `ek_fold` through `ek_finish`) sees it and marks the Gaussian, whose terms would otherwise be
/// reduced in part without a word.
///
/// Errors: a marked Gaussian ([`Error::Gpu`], naming it and `--reduce host`).
fn cut_short(tile: &Tile, meta: &[u8]) -> Result<()> {
    let first = meta
        .chunks_exact(8)
        .take(tile.n_tile as usize)
        .position(|m| bytemuck::pod_read_unaligned::<u32>(&m[..4]) == CUT_SHORT);
    match first {
        None => Ok(()),
        Some(i) => Err(Error::Gpu(format!(
            "the device reduction of Gaussian {} was cut short: this driver stops a shader's \
             loops after a fixed number of iterations (lavapipe: 65,535), fewer than the \
             Gaussian's kept label sums need; reduce with --reduce host, or on a GPU",
            tile.g0 + i as u32
        ))),
    }
}

/// [`tile_output`] of the tile's Gaussians `range` (tile indices). Read-back bytes carry no
/// alignment: each value is read, not cast in place.
fn tile_output_range(
    tile: &Tile,
    p: &DeviceReduce,
    dim: usize,
    read: &[&[u8]],
    range: std::ops::Range<usize>,
) -> KeptTile {
    let pair = |bytes: &[u8], i: usize| -> [u32; 2] {
        bytemuck::pod_read_unaligned(&bytes[i * 8..i * 8 + 8])
    };
    let mut out = KeptTile {
        kept_starts: vec![0],
        ..KeptTile::default()
    };
    // One flat list of pairs, not a list per Gaussian: tens of millions of Gaussians per
    // reduction.
    for i in range {
        let m = pair(read[0], i);
        if m[0] != 1 {
            continue;
        }
        out.ids.push(tile.g0 + i as u32);
        out.total_weights.push(f32::from_bits(m[1]));
        let used = (i * p.keep..(i + 1) * p.keep)
            .map(|s| pair(read[1], s))
            .filter(|s| s[0] != u32::MAX);
        out.kept.extend(used.map(|s| (f32::from_bits(s[1]), s[0])));
        out.kept_starts.push(out.kept.len() as u32);
        if p.dense {
            let row = &read[2][i * dim * 4..(i + 1) * dim * 4];
            out.rows.extend(
                row.chunks_exact(4)
                    .map(|b| f32::from_ne_bytes([b[0], b[1], b[2], b[3]])),
            );
        }
    }
    out
}
