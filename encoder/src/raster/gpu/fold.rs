//! The streamed device reduction: the kept views folded a wave at a time into a running state
//! per Gaussian (`ek.wgsl` `ek_fold`, `ek_finish`), so that the device holds the views of one
//! wave, not every view of the encode.
//!
//! The mixture (the default output) needs, per Gaussian, only `Σ_i Σ_j a_kj` and its `S`
//! largest `(a_kj, codebook row)` pairs, and each `a_kj` is final once its view is done (a mask
//! belongs to one view). The state is therefore `Σ a` in f64 and `S` slots: `N × (8 + 8·S)`
//! bytes whatever the number of views. A wave folds only views that come before every view not
//! yet folded, in the encode's view order (the caller says which: [`GpuRasterizer::fold_kept_due`]'s
//! `below`), so each Gaussian's terms are added in the order the all-kept reduction
//! ([`super::ek`]) adds them, the codebook rows are numbered as it numbers them, and the result
//! is the same bytes.
//!
//! One difference, by construction: the all-kept reduction also marks unobserved a Gaussian
//! whose full `‖Σ a_kj E_j‖` is at most `1e-9 · Σ a_kj` (mask embeddings that cancel out),
//! which needs the whole `D`-wide sum per Gaussian; the streamed one keeps only `Σ a_kj`, and
//! marks unobserved a Gaussian whose `Σ a_kj` is below the threshold, not positive, or not
//! finite. Such a Gaussian's kept pairs still face the mixture's own check
//! (`MixtureEmbeddings::from_sparse`: kept embeddings that nearly cancel are refused).
//!
//! On several devices ([`GpuRasterizer::start_streaming_share`]) each device's state covers one
//! share of the Gaussians (consecutive whole blocks). As each of its views is kept, its records
//! of the other shares go to their devices ([`super::ek::KeptInbox`]) and only its own share's
//! stay; a device takes in what the others sent before each wave, and the caller's `below` is
//! the lowest view not yet kept and sent on any device. Each device so folds every view's terms
//! of its Gaussians in view order, and numbers the codebook rows over every view, as one device
//! alone does: the shares joined are the same bytes.
//!
//! Memory on the device: the state (its share), in chunks of whole blocks that each fit one
//! binding; the kept records of the views not folded yet (at most the budget left beside the
//! state: a wave starts when they pass half of it; on several devices the records the others
//! sent count too); during a wave, one tile of records with the sort's buffers. `--dense`
//! needs the whole `D`-wide sum per Gaussian and is not streamed.

use slag_common::{Error, Result};

use super::buffers::{storage, storage_init};
use super::ek::{
    BLOCK_GAUSSIANS, EkParams, Kept, KeptInbox, KeptPart, MAX_KEEP, TILE_BYTES, Tile, TileStaging,
    gather_tile_records, output_bytes, share_gaussians, tile_output,
};
use super::sort::{SortBuffers, groups_2d};
use super::{GROUPS_X, GpuRasterizer};
use crate::raster::{DeviceReduce, KeptReduced, KeptTile};

/// One chunk of the running state: the Gaussians `[g0, g0 + n)` (whole blocks), their `Σ a`
/// (f64) and their `keep` slots of (codebook row + 1, a bits), 0 where unused.
struct StateChunk {
    g0: u32,
    n: u32,
    den: wgpu::Buffer,
    kept: wgpu::Buffer,
}

/// The streamed reduction's state and progress (the rasterizer's `stream`).
pub(super) struct Stream {
    keep: u32,
    fold: wgpu::ComputePipeline,
    finish: wgpu::ComputePipeline,
    run_starts: wgpu::ComputePipeline,
    chunk_blocks: usize,
    /// The Gaussian ids `[first, end)` the state covers: every Gaussian, or on several devices
    /// this device's share ([`Stream::share`]).
    gaussians: std::ops::Range<u32>,
    chunks: Vec<StateChunk>,
    /// On several devices: where the other devices' views of this device's share come in, and
    /// the other devices' inboxes its own views go to ([`super::ek::KeptInbox`]).
    share: Option<StreamShare>,
    /// The highest index in the encode's view list of a view folded so far: a view below it
    /// that comes later would be added out of order ([`wave_parts`] refuses it).
    folded_up_to: Option<u32>,
    /// Bytes of the state on the device.
    state_bytes: u64,
    /// Kept records past which a wave starts ([`GpuRasterizer::fold_kept_due`]).
    wave_bytes: u64,
    /// Codebook rows of the views folded so far.
    rows: u32,
    /// Per kept view (an index into [`Kept::views`]), whether a wave folded it.
    folded: Vec<bool>,
    /// Waves so far.
    waves: usize,
}

/// A streamed reduction shared between devices ([`GpuRasterizer::start_streaming_share`]).
struct StreamShare {
    /// Where the other devices leave this device's share of their views.
    inbox: KeptInbox,
    /// The other devices' inboxes, once every device streams
    /// ([`GpuRasterizer::share_stream_with`]).
    peers: Vec<KeptInbox>,
}

/// What the streamed reduction reports beside its tiles ([`crate::raster::KeptReduced`]).
#[derive(Debug, Clone, Copy, Default)]
struct StreamStats {
    waves: usize,
    state_bytes: u64,
}

impl GpuRasterizer {
    /// Makes the kept views stream ([`Self::fold_kept_due`]) into a state of `keep` pairs per
    /// Gaussian (1 to [`MAX_KEEP`]). Returns whether they do: keeping must have started
    /// ([`Self::start_keeping`]) with nothing kept yet, and the state must fit the keeping
    /// budget. The budget the records of the views not folded yet may take shrinks by the
    /// state's bytes; a wave starts when they pass half of what is left.
    pub(super) fn start_streaming(&mut self, keep: usize) -> bool {
        self.start_streaming_over(keep, 0..self.n)
    }

    /// [`Self::start_streaming`] of share `share` of `shares` devices (from 0) that stream
    /// together: the state covers that share of the Gaussians ([`share_gaussians`]) only, and
    /// the other devices' views of it come in through the returned inbox. Streaming starts
    /// once every device streams ([`Self::share_stream_with`]). `None`: it does not stream.
    pub(super) fn start_streaming_share(
        &mut self,
        keep: usize,
        share: usize,
        shares: usize,
    ) -> Option<KeptInbox> {
        let gaussians = share_gaussians(self.n, share, shares);
        if !self.start_streaming_over(keep, gaussians.clone()) {
            return None;
        }
        let inbox = KeptInbox::new(&self.device, gaussians);
        let stream = self.stream.as_mut()?;
        stream.share = Some(StreamShare {
            inbox: inbox.clone(),
            peers: Vec::new(),
        });
        Some(inbox)
    }

    /// After [`Self::start_streaming_share`]: `peers`, the other devices' inboxes, when every
    /// device streams, from here each view kept is sent to them
    /// ([`Self::share_kept_view`]); `None` when one does not, and this one stops streaming too
    /// (every view is kept to the end, its budget whole again). Nothing may be kept yet.
    pub(super) fn share_stream_with(&mut self, peers: Option<Vec<KeptInbox>>) {
        match (peers, self.stream.as_mut()) {
            (Some(peers), Some(stream)) => {
                if let Some(share) = stream.share.as_mut() {
                    share.peers = peers;
                }
            }
            (None, Some(stream)) => {
                if let Some(kept) = self.kept.as_mut() {
                    kept.budget += stream.state_bytes;
                }
                self.stream = None;
            }
            (_, None) => {}
        }
    }

    /// The Gaussian ids a streamed reduction shared between devices folds here
    /// ([`Self::start_streaming_share`]); `None` without one.
    pub(super) fn streamed_share(&self) -> Option<std::ops::Range<u32>> {
        let stream = self.stream.as_ref()?;
        stream.share.as_ref().map(|_| stream.gaussians.clone())
    }

    /// After kept view `id` was kept whole: with a streamed reduction shared between devices,
    /// it goes to the others ([`Self::share_kept_view`]); otherwise nothing.
    ///
    /// Errors: as [`Self::share_kept_view`].
    pub(super) fn kept_view_done(&mut self, id: u32) -> Result<()> {
        let Some(stream) = self.stream.as_ref() else {
            return Ok(());
        };
        let Some(share) = stream.share.as_ref().filter(|s| !s.peers.is_empty()) else {
            return Ok(());
        };
        let (own, peers) = (stream.gaussians.clone(), share.peers.clone());
        self.share_kept_view(id, &own, &peers)
    }

    /// [`Self::start_streaming`] over the Gaussian ids `gaussians` (whole blocks).
    fn start_streaming_over(&mut self, keep: usize, gaussians: std::ops::Range<u32>) -> bool {
        let max_binding = self.max_binding();
        let Some(kept) = self.kept.as_ref() else {
            return false;
        };
        if keep == 0 || keep > MAX_KEEP || !kept.views.is_empty() || self.stream.is_some() {
            return false;
        }
        let per_gaussian = 8 + 8 * keep as u64;
        let state_bytes = u64::from(gaussians.end - gaussians.start) * per_gaussian;
        if state_bytes >= kept.budget {
            tracing::info!(
                state_mib = state_bytes >> 20,
                budget_mib = kept.budget >> 20,
                "the streamed reduction's state does not fit the device budget: every view is \
                 kept to the end instead"
            );
            return false;
        }
        let Some([fold, finish, run_starts]) = self.fold_pipelines() else {
            return false;
        };
        let block_state = u64::from(BLOCK_GAUSSIANS) * 8 * keep as u64;
        let chunk_blocks = (max_binding / block_state).max(1) as usize;
        let chunks = state_chunks(&self.device, &gaussians, chunk_blocks, keep);
        let Some(kept) = self.kept.as_mut() else {
            return false;
        };
        kept.budget -= state_bytes;
        let wave_bytes = kept.budget / 2;
        self.stream = Some(Stream {
            keep: keep as u32,
            fold,
            finish,
            run_starts,
            chunk_blocks,
            gaussians,
            chunks,
            share: None,
            folded_up_to: None,
            state_bytes,
            wave_bytes,
            rows: 0,
            folded: Vec::new(),
            waves: 0,
        });
        true
    }

    /// The streamed reduction's kernels (`ek_fold`, `ek_finish`, `run_starts`); `None` where
    /// they do not build.
    fn fold_pipelines(&self) -> Option<[wgpu::ComputePipeline; 3]> {
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = self
            .device
            .create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some("slag-ek fold kernels"),
                source: wgpu::ShaderSource::Wgsl(include_str!("ek.wgsl").into()),
            });
        let pipe = |entry: &str| super::compute_pipeline(&self.device, &module, entry);
        let pipelines = [pipe("ek_fold"), pipe("ek_finish"), pipe("run_starts")];
        if let Some(e) = pollster::block_on(scope.pop()) {
            tracing::warn!(error = %e, "the streamed reduction's kernels do not build here");
            return None;
        }
        Some(pipelines)
    }

    /// Folds the kept views whose index in the encode's view list is below `below` into the
    /// running state and frees their records, when the kept records passed the wave size
    /// (half the budget beside the state); `below` must be such that no view below it is
    /// still to come. Returns whether a wave ran. Without streaming, does nothing.
    ///
    /// Errors: device failures; a tile's records past a binding ([`Error::Limit`]).
    pub(super) fn fold_kept_due(&mut self, below: usize) -> Result<bool> {
        self.take_own_inbox()?;
        let due = match (&self.kept, &self.stream) {
            (Some(k), Some(s)) => k.bytes >= s.wave_bytes.max(1),
            _ => false,
        };
        if !due {
            return Ok(false);
        }
        self.fold_below(below)
    }

    /// With a streamed reduction shared between devices, takes in what the others sent
    /// ([`Self::take_inbox`]); otherwise nothing. A caller that folds the views below `below`
    /// takes them in after it learnt `below`: a view counts as done only once it was sent.
    ///
    /// Errors: as [`Self::take_inbox`].
    fn take_own_inbox(&mut self) -> Result<()> {
        let inbox = self
            .stream
            .as_ref()
            .and_then(|s| s.share.as_ref())
            .map(|s| s.inbox.clone());
        match inbox {
            Some(inbox) => self.take_inbox(&inbox),
            None => Ok(()),
        }
    }

    /// One wave ([`Self::fold_kept_due`]) whatever the records kept: every kept view below
    /// `below` not folded yet. Returns whether there was one to fold.
    ///
    /// Errors: as [`Self::fold_kept_due`].
    pub(super) fn fold_below(&mut self, below: usize) -> Result<bool> {
        let (Some(mut kept), Some(mut stream)) = (self.kept.take(), self.stream.take()) else {
            return Ok(false);
        };
        let out = self.fold_wave(&mut kept, &mut stream, below);
        self.kept = Some(kept);
        self.stream = Some(stream);
        out
    }

    /// The wave of [`Self::fold_below`] on `kept` (taken out of the rasterizer meanwhile).
    fn fold_wave(&self, kept: &mut Kept, stream: &mut Stream, below: usize) -> Result<bool> {
        let Some((wave, rows)) = wave_parts(kept, stream, below)? else {
            return Ok(false);
        };
        let blocks = self.blocks_of(stream.gaussians.clone())?;
        let tile_bytes = self.reduce_tile_bytes.unwrap_or(TILE_BYTES);
        let tiles = self.kept_tiles_within(&wave, blocks, 4, tile_bytes, stream.chunk_blocks)?;
        let tables = storage_init(
            &self.device,
            "ek_tables",
            bytemuck::cast_slice(&kept.tables),
        );
        let mut sort: Option<SortBuffers> = None;
        for tile in &tiles {
            let base_of = |part: &KeptPart| {
                let v = part.view as usize;
                [kept.views[v][0], rows[v]]
            };
            self.fold_tile(stream, &wave, tile, &tables, &mut sort, base_of)?;
        }
        kept.bytes -= wave.iter().map(|p| u64::from(p.n) * 16).sum::<u64>();
        stream.waves += 1;
        tracing::debug!(
            target: "slag_encoder::pipeline",
            wave = stream.waves,
            bands = wave.len(),
            tiles = tiles.len(),
            "device reduction wave"
        );
        Ok(true)
    }

    /// One tile of a wave: its records gathered band by band (`base_of`: a band's view's
    /// label-table base and first codebook row), sorted by Gaussian, folded into the state
    /// chunk that holds the tile; waits for the device, so that the tile's buffers go before
    /// the next tile's come.
    fn fold_tile(
        &self,
        stream: &Stream,
        wave: &[KeptPart],
        tile: &Tile,
        tables: &wgpu::Buffer,
        sort: &mut Option<SortBuffers>,
        base_of: impl Fn(&KeptPart) -> [u32; 2],
    ) -> Result<()> {
        let n = tile.records as u32;
        if n == 0 {
            return Ok(());
        }
        let chunk = chunk_of(stream, tile)?;
        let recs = storage(&self.device, "ek_tile_records", 16 + tile.records * 16);
        let mut enc = self.device.create_command_encoder(&Default::default());
        let segs = gather_tile_records(&mut enc, wave, tile, &recs, base_of);
        let segs_buf = storage_init(&self.device, "ek_segments", bytemuck::cast_slice(&segs));
        let run_start = storage(&self.device, "ek_run_start", u64::from(tile.n_tile) * 4);
        enc.clear_buffer(&run_start, 0, None);
        let order = self.sort_tile(&mut enc, &recs, n, sort)?;
        let params = self.ek_uniform(&EkParams {
            min_total_weight: 0.0,
            n_records: n,
            g0: tile.g0,
            n_tile: tile.n_tile,
            dim: 0,
            keep: stream.keep,
            n_segments: segs.len() as u32,
            groups_x: GROUPS_X,
            dense: 0,
            n_blocks: 0,
            pad0: chunk.g0,
        });
        let starts = self.bind(
            &stream.run_starts,
            &[(0, &params), (1, &recs), (2, &order), (11, &run_start)],
        );
        let fold = self.bind(
            &stream.fold,
            &[
                (0, &params),
                (1, &recs),
                (2, &order),
                (3, &segs_buf),
                (4, tables),
                (11, &run_start),
                (12, &chunk.den),
                (13, &chunk.kept),
            ],
        );
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(&stream.run_starts);
            pass.set_bind_group(0, &starts, &[]);
            let (x, y) = groups_2d(n.div_ceil(256));
            pass.dispatch_workgroups(x, y, 1);
            pass.set_pipeline(&stream.fold);
            pass.set_bind_group(0, &fold, &[]);
            let (x, y) = groups_2d(tile.n_tile.div_ceil(64));
            pass.dispatch_workgroups(x, y, 1);
        }
        self.queue.submit([enc.finish()]);
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| super::gpu_err("waiting for a wave of the device reduction failed", e))?;
        Ok(())
    }

    /// [`crate::raster::WeightRasterizer::reduce_kept`] of the streamed reduction
    /// ([`Self::finish_stream`]): the codebook in view order, as the all-kept reduction's; the
    /// kept views and the state are freed with the rasterizer (or when keeping starts again).
    ///
    /// Errors: nothing kept ([`Error::Internal`]); as [`Self::finish_stream`].
    pub(super) fn reduce_streamed(
        &mut self,
        p: &DeviceReduce,
        sink: &mut dyn FnMut(KeptTile) -> Result<()>,
    ) -> Result<KeptReduced> {
        self.take_own_inbox()?;
        let (Some(mut kept), Some(mut stream)) = (self.kept.take(), self.stream.take()) else {
            return Err(Error::internal("the streamed reduction has no kept views"));
        };
        let (tiles, stats) = self.finish_stream(&mut kept, &mut stream, p, sink)?;
        kept.sort_by_view();
        let codebook = std::mem::take(&mut kept.codebook);
        let (peak_kept_bytes, records_bytes) = (kept.peak_bytes, kept.total_bytes);
        self.spent_kept = Some(kept);
        Ok(KeptReduced {
            tiles,
            codebook,
            waves: stats.waves,
            state_bytes: stats.state_bytes,
            peak_kept_bytes,
            records_bytes,
        })
    }

    /// The end of the streamed reduction: the views not folded yet folded, then every
    /// Gaussian's state turned into the all-kept reduction's outputs (`ek_finish`), tile by
    /// tile of Gaussian ids ascending, handed to `sink`. Returns the tiles and the stream's
    /// figures.
    ///
    /// Errors: `p` asking for the dense rows, other Gaussians than the stream's (all, or its
    /// share: [`DeviceReduce::gaussians`]), or another `keep` than the stream's
    /// ([`Error::Internal`]: the encoder streams only without them); device failures; `sink`'s.
    fn finish_stream(
        &self,
        kept: &mut Kept,
        stream: &mut Stream,
        p: &DeviceReduce,
        sink: &mut dyn FnMut(KeptTile) -> Result<()>,
    ) -> Result<(usize, StreamStats)> {
        let keep = stream.keep as usize;
        let gaussians = p.gaussians.map_or(0..self.n, |(a, b)| a..b);
        if p.dense || gaussians != stream.gaussians || p.keep != keep {
            return Err(Error::internal(
                "the streamed reduction writes the mixture of its own Gaussians, with its own keep",
            ));
        }
        self.fold_wave(kept, stream, usize::MAX)?;
        let tile_bytes = self.reduce_tile_bytes.unwrap_or(TILE_BYTES);
        let per_gaussian = 8 + 8 * keep as u64;
        let tile_gaussians = (tile_bytes / per_gaussian).max(u64::from(BLOCK_GAUSSIANS)) as u32;
        let tile_gaussians = tile_gaussians / BLOCK_GAUSSIANS * BLOCK_GAUSSIANS;
        let largest = stream
            .chunks
            .iter()
            .map(|c| c.n.min(tile_gaussians))
            .max()
            .unwrap_or(0);
        let staging = TileStaging::new(&self.device, u64::from(largest), p, kept.dim);
        let mut tiles = 0;
        for chunk in &stream.chunks {
            let mut g0 = chunk.g0;
            while g0 < chunk.g0 + chunk.n {
                let n_tile = tile_gaussians.min(chunk.g0 + chunk.n - g0);
                let tile = Tile {
                    g0,
                    n_tile,
                    ranges: Vec::new(),
                    records: 0,
                };
                sink(self.finish_tile(stream, chunk, &tile, p, kept.dim, &staging)?)?;
                tiles += 1;
                g0 += n_tile;
            }
        }
        let stats = StreamStats {
            waves: stream.waves,
            state_bytes: stream.state_bytes,
        };
        Ok((tiles, stats))
    }

    /// One tile of [`Self::finish_stream`]: `ek_finish` over its Gaussians, its meta and kept
    /// pairs read back through `staging` and converted as the all-kept reduction's.
    fn finish_tile(
        &self,
        stream: &Stream,
        chunk: &StateChunk,
        tile: &Tile,
        p: &DeviceReduce,
        dim: usize,
        staging: &TileStaging,
    ) -> Result<KeptTile> {
        let sizes = output_bytes(u64::from(tile.n_tile), p, dim);
        let meta = storage(&self.device, "ek_meta", sizes[0]);
        let kept_out = storage(&self.device, "ek_kept", sizes[1]);
        let mut enc = self.device.create_command_encoder(&Default::default());
        enc.clear_buffer(&meta, 0, None);
        enc.clear_buffer(&kept_out, 0, None);
        let params = self.ek_uniform(&EkParams {
            min_total_weight: p.min_total_weight,
            n_records: 0,
            g0: tile.g0,
            n_tile: tile.n_tile,
            dim: dim as u32,
            keep: stream.keep,
            n_segments: 0,
            groups_x: GROUPS_X,
            dense: 0,
            n_blocks: 0,
            pad0: chunk.g0,
        });
        let bg = self.bind(
            &stream.finish,
            &[
                (0, &params),
                (6, &meta),
                (7, &kept_out),
                (12, &chunk.den),
                (13, &chunk.kept),
            ],
        );
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(&stream.finish);
            pass.set_bind_group(0, &bg, &[]);
            let (x, y) = groups_2d(tile.n_tile.div_ceil(64));
            pass.dispatch_workgroups(x, y, 1);
        }
        let staged: Vec<(&wgpu::Buffer, u64)> = staging.buffers.iter().zip(sizes).collect();
        for (src, &(dst, size)) in [&meta, &kept_out].into_iter().zip(&staged) {
            enc.copy_buffer_to_buffer(src, 0, dst, 0, size);
        }
        self.submit_and_map_all(enc, &staged, |read| tile_output(tile, p, dim, read))?
    }
}

/// The state's chunks for the Gaussians `gaussians` (whole blocks): runs of whole blocks that
/// end at multiples of `chunk_blocks` blocks (the tiles of a wave end there too,
/// [`GpuRasterizer::kept_tiles_within`]), each a `Σ a` buffer and a slots buffer (wgpu zeroes
/// new buffers: the empty state).
fn state_chunks(
    device: &wgpu::Device,
    gaussians: &std::ops::Range<u32>,
    chunk_blocks: usize,
    keep: usize,
) -> Vec<StateChunk> {
    let chunk_gaussians =
        (chunk_blocks as u64 * u64::from(BLOCK_GAUSSIANS)).min(u64::from(u32::MAX));
    let end = u64::from(gaussians.end);
    let mut chunks = Vec::new();
    let mut g0 = u64::from(gaussians.start);
    while g0 < end {
        let len = ((g0 / chunk_gaussians + 1) * chunk_gaussians).min(end) - g0;
        chunks.push(StateChunk {
            g0: g0 as u32,
            n: len as u32,
            den: storage(device, "ek_state_den", len * 8),
            kept: storage(device, "ek_state_kept", len * 8 * keep as u64),
        });
        g0 += len;
    }
    chunks
}

/// The state chunk that holds `tile` (tiles never cross a chunk).
///
/// Errors: none does ([`Error::Internal`]).
fn chunk_of<'a>(stream: &'a Stream, tile: &Tile) -> Result<&'a StateChunk> {
    stream
        .chunks
        .iter()
        .find(|c| c.g0 <= tile.g0 && tile.g0 + tile.n_tile <= c.g0 + c.n)
        .ok_or_else(|| {
            Error::internal(format!(
                "a tile of Gaussians {}..{} across the streamed state's chunks",
                tile.g0,
                tile.g0 + tile.n_tile
            ))
        })
}

/// The bands of the next wave, taken out of `kept`: those of every kept view below `below` in
/// the encode's view list not folded yet, ordered by view index (a view's bands in keeping
/// order), with each kept view's first codebook row (numbered on from the views folded
/// before, in view order; unused for the others). `None` when no view is due.
///
/// Errors: a due view below one an earlier wave folded ([`Error::Internal`]: its terms would
/// be added out of the encode's view order).
fn wave_parts(
    kept: &mut Kept,
    stream: &mut Stream,
    below: usize,
) -> Result<Option<(Vec<KeptPart>, Vec<u32>)>> {
    let dim = kept.dim;
    let n_views = kept.views.len();
    stream.folded.resize(n_views, false);
    let mut due: Vec<usize> = (0..n_views)
        .filter(|&v| !stream.folded[v] && (kept.views[v][2] as usize) < below)
        .collect();
    if due.is_empty() {
        return Ok(None);
    }
    due.sort_by_key(|&v| (kept.views[v][2], v));
    let (first, last) = (kept.views[due[0]][2], kept.views[due[due.len() - 1]][2]);
    if let Some(up_to) = stream.folded_up_to.filter(|&u| first < u) {
        return Err(Error::internal(format!(
            "view {first} came to the streamed reduction after view {up_to} was folded"
        )));
    }
    stream.folded_up_to = Some(last);
    let mut rows = vec![u32::MAX; n_views];
    let mut rank = vec![usize::MAX; n_views];
    for (r, &v) in due.iter().enumerate() {
        let row_end = kept
            .views
            .get(v + 1)
            .map_or(kept.codebook.len() / dim.max(1), |next| next[1] as usize);
        let n_rows = row_end - kept.views[v][1] as usize;
        rows[v] = stream.rows;
        rank[v] = r;
        stream.rows += n_rows as u32;
        stream.folded[v] = true;
    }
    let parts = std::mem::take(&mut kept.parts);
    let (mut wave, rest): (Vec<KeptPart>, Vec<KeptPart>) = parts
        .into_iter()
        .partition(|p| rank[p.view as usize] != usize::MAX);
    kept.parts = rest;
    wave.sort_by_key(|p| rank[p.view as usize]);
    Ok(Some((wave, rows)))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use slag_common::rng::SplitMix64;

    /// The sort of a tile's records (`sort_tile`) orders them by Gaussian and keeps the order
    /// of equal Gaussians (the views' order, which the reduction adds in), at many records.
    #[test]
    fn tile_sort_is_stable_at_many_records() {
        let n_gaussians = 8_000usize;
        let mut g = slag_common::scene::Gaussians::default();
        for i in 0..n_gaussians {
            g.means.push([i as f32 * 1e-3, 0.0, 5.0]);
            g.scales.push([0.01; 3]);
            g.rotations.push([1.0, 0.0, 0.0, 0.0]);
            g.opacities.push(0.5);
        }
        let Some(r) = crate::raster::testdata::gpu_unless_skipped(|| GpuRasterizer::new(&g)) else {
            return;
        };
        let mut rng = SplitMix64::new(3);
        for n in [10_000u32, 20_000, 60_000] {
            // Records: Gaussian, label (its position, to check stability), 0, 0.
            let mut words = vec![0u32; 4];
            for i in 0..n {
                words.extend([(rng.next_u64() % n_gaussians as u64) as u32, i, 0, 0]);
            }
            let recs = storage_init(&r.device, "recs", bytemuck::cast_slice(&words));
            let mut enc = r.device.create_command_encoder(&Default::default());
            let mut sort = None;
            let order = r.sort_tile(&mut enc, &recs, n, &mut sort).unwrap();
            let out = r
                .submit_and_read(enc, &[(&order, 0, u64::from(n) * 4)])
                .unwrap();
            let order: Vec<u32> = bytemuck::pod_collect_to_vec(&out[0]);
            let key = |i: u32| (words[4 + 4 * i as usize], words[4 + 4 * i as usize + 1]);
            let bad = order.windows(2).filter(|w| key(w[0]) >= key(w[1])).count();
            assert_eq!(bad, 0, "{n} records: {bad} out of order");
        }
    }
}
