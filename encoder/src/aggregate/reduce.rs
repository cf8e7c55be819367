//! The reduction `E_k = Σ_i Σ_j a_kj·E_j / Σ_i Σ_j a_kj` in f64, chunked over Gaussian ids within a
//! memory budget, into memory ([`reduce`]) or streamed to the embeddings file ([`reduce_to_writer`]).

use std::ops::Range;

use rayon::prelude::*;
use slag_common::embeddings::EmbeddingsWriter;
use slag_common::{Error, Result};

use super::*;

/// Knobs of the reduction.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct ReduceParams {
    /// A Gaussian whose `Σ a_kj` is below this is *unobserved* and gets no embedding.
    pub min_total_weight: f64,
    /// Upper bound on the f64 accumulator, bytes; the Gaussians are processed in chunks that fit.
    pub accumulator_budget_bytes: usize,
    /// Use the image-major loop (the spilled path's) even when every contribution is in memory.
    /// Same values bit for bit, only slower; kept so that benchmarks can measure the two orders
    /// against each other in one run (`slag-bench reduce`).
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub image_major: bool,
}

impl Default for ReduceParams {
    fn default() -> Self {
        Self {
            min_total_weight: 1e-6,
            accumulator_budget_bytes: 2 << 30,
            image_major: false,
        }
    }
}

/// Result of the reduction: the observed Gaussians with their `E_k`.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Reduced {
    /// Observed Gaussian indices, ascending.
    pub ids: Vec<u32>,
    /// `[ids.len() * dim]`, rows L2-normalised `E_k`.
    pub vectors: Vec<f32>,
    /// `Σ_i Σ_j a_kj` per observed Gaussian.
    pub total_weights: Vec<f32>,
    /// Number of chunks the reduction used.
    pub chunks: usize,
}

impl Reduced {
    /// Runs in ascending id order joined into one (`chunks` summed).
    pub fn concat(parts: Vec<Reduced>) -> Reduced {
        let rows: usize = parts.iter().map(|p| p.ids.len()).sum();
        let values: usize = parts.iter().map(|p| p.vectors.len()).sum();
        let mut out = Reduced {
            ids: Vec::with_capacity(rows),
            vectors: Vec::with_capacity(values),
            total_weights: Vec::with_capacity(rows),
            chunks: 0,
        };
        for p in parts {
            out.ids.extend_from_slice(&p.ids);
            out.vectors.extend_from_slice(&p.vectors);
            out.total_weights.extend_from_slice(&p.total_weights);
            out.chunks += p.chunks;
        }
        out
    }
}

/// `E_k = Σ a_kj E_j / Σ a_kj` over every stored contribution, for Gaussians `0..n_gaussians`,
/// normalised to unit length (cosine queries). f64 accumulation; chunked over Gaussian ids.
/// Unobserved: `Σ a < min_total_weight`, or the weighted mean's norm below 1e-9 of `Σ a`
/// (mask embeddings that cancel out carry no direction).
pub fn reduce(
    store: &ContributionStore,
    n_gaussians: usize,
    dim: usize,
    params: ReduceParams,
) -> Result<Reduced> {
    let mut out = Reduced::default();
    out.chunks = reduce_each(store, n_gaussians, dim, params, |parts| {
        let part = Reduced::concat(parts);
        out.ids.extend_from_slice(&part.ids);
        out.vectors.extend_from_slice(&part.vectors);
        out.total_weights.extend_from_slice(&part.total_weights);
        Ok(())
    })?;
    Ok(out)
}

/// [`reduce`] without collecting: for each chunk of Gaussian ids (ascending), hands `sink` the
/// chunk's observed rows as consecutive [`Reduced`] runs in ascending id order (observed ids
/// `[B]`, unit vectors `[B * dim]`, `Σ a_kj` `[B]`, `chunks` 0; one run per block of Gaussians), owned, so
/// that a sink may pass them to a writer thread and overlap the write with the next chunk's
/// accumulation. Memory: the f64 accumulators (one chunk's, ≤ `params.accumulator_budget_bytes`,
/// on the image-major path; one block's per thread otherwise) plus one chunk's output (at most
/// [`OUTPUT_CHUNK_BYTES`] on the block-major path, [`output_chunk_rows`] Gaussians; about half the
/// accumulator budget on the image-major path), whatever the scene size. Returns the number of
/// chunks.
///
/// Errors: a contribution of another width ([`Error::Mismatch`]); spill-file I/O; `sink`'s errors.
pub fn reduce_each(
    store: &ContributionStore,
    n_gaussians: usize,
    dim: usize,
    params: ReduceParams,
    mut sink: impl FnMut(Vec<Reduced>) -> Result<()>,
) -> Result<usize> {
    accumulate(
        Pass::new(store, n_gaussians, dim, params, (dim + 1) * 8).streamed(),
        |_, _, _| Ok(0),
        |_: &mut (), _, _| {},
        |sums| sums.reduced(params.min_total_weight),
        &mut sink,
    )
}

/// Bytes of output rows (unit vectors in f32, ids, total weights) of one chunk of the
/// Gaussian-block-major reduction ([`reduce_each`]).
pub const OUTPUT_CHUNK_BYTES: usize = 64 << 20;

/// Gaussians per chunk of the Gaussian-block-major reduction at width `dim`: as many whole blocks
/// of 128 Gaussians as [`OUTPUT_CHUNK_BYTES`] holds rows of `4 · dim + 8` bytes (32,640 at
/// D = 512), at least one block. The chunk size changes no value: each Gaussian's sums run in the
/// same order whatever the chunking.
pub fn output_chunk_rows(dim: usize) -> usize {
    let rows = OUTPUT_CHUNK_BYTES / (4 * dim + 8);
    (rows / REDUCE_BLOCK).max(1) * REDUCE_BLOCK
}

/// What [`reduce_to_writer`] leaves: the writer with every observed row pushed (call
/// [`EmbeddingsWriter::finish`]), the number of chunks, and the reduction's wall time in seconds
/// until its last chunk was handed to the writer thread.
pub struct Streamed {
    /// The writer, all rows pushed, not yet finished.
    pub writer: EmbeddingsWriter,
    /// Chunks the reduction used.
    pub chunks: usize,
    /// Seconds from the start until the last chunk was handed on (the rest of the call's time
    /// is the writer finishing its last chunk).
    pub reduce_s: f64,
}

/// [`reduce_each`] streamed into `writer` (the encoder's tail): a writer thread converts and
/// writes the runs of chunk c while chunk c + 1 is accumulated; at most one chunk waits in
/// between, so memory stays at the accumulators plus three chunks' output (being written,
/// waiting, being accumulated: 3 × [`OUTPUT_CHUNK_BYTES`] on the block-major path). `means` are all
/// Gaussian centres (`[N]`, world frame, `.ply` order), written beside each row.
///
/// Errors: those of [`reduce_each`]; the writer's (I/O, non-finite rows), which take precedence
/// over the reduction's "writer stopped" error they cause.
pub fn reduce_to_writer(
    store: &ContributionStore,
    means: &[[f32; 3]],
    dim: usize,
    params: ReduceParams,
    writer: EmbeddingsWriter,
) -> Result<Streamed> {
    stream_to_writer(
        Pass::new(store, means.len(), dim, params, (dim + 1) * 8).streamed(),
        params.min_total_weight,
        means,
        writer,
        |_, _, _| Ok(0),
        |_: &mut (), _, _| {},
        |_, _| (),
        |_| Ok(()),
    )
}

/// The body of [`reduce_to_writer`], with a side product: one [`accumulate`] pass whose every
/// run of final sums is turned into the observed rows ([`ChunkSums::reduced`], sent to the writer
/// thread) and into a side part by `side_part(sums, rows)` (in parallel, as `accumulate`'s
/// `finish`; `rows` are the run's observed rows, so the side sees exactly the Gaussians written);
/// `side(parts)` then receives the chunk's side parts in ascending id order on the calling thread,
/// after the chunk's rows were handed to the writer. `on_image` and `on_entry` are
/// [`accumulate`]'s hooks. The mixture rides on this ([`super::reduce_to_writer_with_mixture`]):
/// one f64 reduction feeds both outputs.
///
/// Errors: those of [`accumulate`], `side`'s, and the writer's (I/O, non-finite rows, means
/// missing), which take precedence over the reduction's "writer stopped" error they cause.
#[allow(clippy::too_many_arguments)]
pub(super) fn stream_to_writer<T: Clone + Default + Send, S: Send>(
    pass: Pass<'_>,
    min_total_weight: f64,
    means: &[[f32; 3]],
    writer: EmbeddingsWriter,
    on_image: impl FnMut(bool, usize, &StoredImage) -> Result<u32>,
    on_entry: impl Fn(&mut T, &Entry, u32) + Sync,
    side_part: impl Fn(&mut ChunkSums<T>, &Reduced) -> S + Sync,
    mut side: impl FnMut(Vec<S>) -> Result<()>,
) -> Result<Streamed> {
    let t0 = std::time::Instant::now();
    std::thread::scope(|s| {
        let (tx, rx) = std::sync::mpsc::sync_channel::<Vec<Reduced>>(1);
        let handle = s.spawn(move || -> Result<EmbeddingsWriter> {
            let mut writer = writer;
            let mut run_means: Vec<[f32; 3]> = Vec::new();
            for run in rx.into_iter().flatten() {
                run_means.clear();
                for &k in &run.ids {
                    run_means.push(*means.get(k as usize).ok_or_else(|| {
                        Error::internal(format!("Gaussian {k} has no mean ({} given)", means.len()))
                    })?);
                }
                writer.push(&run.ids, &run_means, &run.vectors, &run.total_weights)?;
            }
            Ok(writer)
        });
        let reduced = accumulate(
            pass,
            on_image,
            on_entry,
            |sums| {
                let rows = sums.reduced(min_total_weight);
                let part = side_part(sums, &rows);
                (rows, part)
            },
            |parts| {
                let (runs, sides): (Vec<Reduced>, Vec<S>) = parts.into_iter().unzip();
                tx.send(runs)
                    .map_err(|_| Error::internal("the embeddings writer stopped early"))?;
                side(sides)
            },
        );
        let reduce_s = t0.elapsed().as_secs_f64();
        drop(tx);
        let writer = handle
            .join()
            .map_err(|_| Error::internal("the embeddings writer thread panicked"))??;
        Ok(Streamed {
            writer,
            chunks: reduced?,
            reduce_s,
        })
    })
}

/// One run of Gaussian ids (a chunk, or a block of one) after every contribution was added:
/// `Σ_i Σ_j a_kj E_j` and `Σ_i Σ_j a_kj` in f64 for Gaussians `start..start + den.len()`, plus a
/// per-Gaussian extra (`T`) that the entry hook of [`accumulate`] filled.
pub(super) struct ChunkSums<T> {
    /// First Gaussian id of the chunk.
    pub(super) start: usize,
    /// Embedding width D.
    pub(super) dim: usize,
    /// `[B * D]` weighted sums `Σ a_kj E_j`.
    pub(super) num: Vec<f64>,
    /// `[B]` total weights `Σ a_kj`.
    pub(super) den: Vec<f64>,
    /// `[B]` per-Gaussian extras.
    pub(super) extra: Vec<T>,
}

impl<T: Clone + Default> ChunkSums<T> {
    /// Sums of width `dim` for no Gaussians yet ([`ChunkSums::reset`] sizes them).
    fn empty(dim: usize) -> Self {
        ChunkSums {
            start: 0,
            dim,
            num: Vec::new(),
            den: Vec::new(),
            extra: Vec::new(),
        }
    }

    /// Zeroed sums for Gaussians `start..start + len`, reusing the buffers.
    fn reset(&mut self, start: usize, len: usize) {
        self.start = start;
        self.num.clear();
        self.num.resize(len * self.dim, 0.0);
        self.den.clear();
        self.den.resize(len, 0.0);
        self.extra.clear();
        self.extra.resize(len, T::default());
    }

    /// The observed rows of the run ([`ChunkSums::observed`]) as a [`Reduced`]: ids `[B]`, the
    /// unit vectors `Σ a E / ‖Σ a E‖` rounded to f32 `[B * D]`, `Σ a` rounded to f32 `[B]`,
    /// `chunks` 0.
    pub(super) fn reduced(&self, min_total_weight: f64) -> Reduced {
        reduced_rows(self.start, self.dim, &self.num, &self.den, min_total_weight)
    }

    /// The observed Gaussians of the chunk, ascending: `(row r, Σ a E [D], its L2 norm, Σ a)`
    /// ([`observed_rows`]).
    pub(super) fn observed(
        &self,
        min_total_weight: f64,
    ) -> impl Iterator<Item = (usize, &[f64], f64, f64)> {
        observed_rows(self.dim, &self.num, &self.den, min_total_weight)
    }
}

/// The observed rows of Gaussians `start..start + den.len()` from their final sums (`num`
/// `[B * dim]` `Σ a E`, `den` `[B]` `Σ a`, f64) as a [`Reduced`]: ids `[B']`, the unit vectors
/// `Σ a E / ‖Σ a E‖` rounded to f32 `[B' * dim]`, `Σ a` rounded to f32 `[B']`, `chunks` 0.
/// Every reduction (kept views, or the host's dense fold) turns its sums into rows here, so
/// equal sums give equal bytes.
pub(super) fn reduced_rows(
    start: usize,
    dim: usize,
    num: &[f64],
    den: &[f64],
    min_total_weight: f64,
) -> Reduced {
    let mut out = Reduced::default();
    for (r, row, norm, d) in observed_rows(dim, num, den, min_total_weight) {
        out.ids.push((start + r) as u32);
        out.vectors.extend(row.iter().map(|v| (v / norm) as f32));
        out.total_weights.push(d as f32);
    }
    out
}

/// The observed Gaussians among sums `num` `[B * dim]` and `den` `[B]`, ascending: `(row r,
/// Σ a E [D], its L2 norm, Σ a)`. Unobserved (skipped): `Σ a` NaN or below
/// `min_total_weight`, or the norm not finite or at most `1e-9 · Σ a` (mask embeddings that
/// cancel out carry no direction).
pub(super) fn observed_rows<'s>(
    dim: usize,
    num: &'s [f64],
    den: &'s [f64],
    min_total_weight: f64,
) -> impl Iterator<Item = (usize, &'s [f64], f64, f64)> {
    den.iter().enumerate().filter_map(move |(r, &d)| {
        // NaN sums count as unobserved too.
        if d.is_nan() || d < min_total_weight {
            return None;
        }
        let row = &num[r * dim..(r + 1) * dim];
        let norm = row.iter().map(|v| v * v).sum::<f64>().sqrt();
        if !norm.is_finite() || norm <= 1e-9 * d {
            return None;
        }
        Some((r, row, norm, d))
    })
}

/// What one [`accumulate`] pass reduces: every contribution of `store` over Gaussian ids
/// `0..n_gaussians` of width `dim`, `chunk` ids at a time, in the loop order `image_major`
/// ([`ReduceParams::image_major`]).
#[derive(Clone, Copy)]
pub(super) struct Pass<'a> {
    pub(super) store: &'a ContributionStore,
    pub(super) n_gaussians: usize,
    pub(super) dim: usize,
    pub(super) chunk: usize,
    pub(super) image_major: bool,
}

impl<'a> Pass<'a> {
    /// A pass whose chunk holds as many Gaussians as `params.accumulator_budget_bytes` allows at
    /// `per_gaussian` accumulator bytes each (at least 1024, at most the scene rounded up to
    /// 1024).
    pub(super) fn new(
        store: &'a ContributionStore,
        n_gaussians: usize,
        dim: usize,
        params: ReduceParams,
        per_gaussian: usize,
    ) -> Self {
        Pass {
            store,
            n_gaussians,
            dim,
            chunk: (params.accumulator_budget_bytes / per_gaussian)
                .clamp(1024, n_gaussians.max(1024)),
            image_major: params.image_major,
        }
    }

    /// This pass ([`Pass::new`]) for output streamed chunk by chunk ([`reduce_each`],
    /// [`reduce_to_writer`]): on the block-major path (no spilled contribution, not
    /// [`ReduceParams::image_major`]) there is no chunk-wide accumulator, so the chunk is sized by
    /// its output instead, at most [`output_chunk_rows`] Gaussians: a chunk's rows are what a
    /// sink holds while the next chunks are accumulated (the streamed tail holds up to three).
    pub(super) fn streamed(mut self) -> Self {
        if self.store.spilled() == 0 && !self.image_major {
            self.chunk = self.chunk.min(output_chunk_rows(self.dim));
        }
        self
    }
}

/// The f64 accumulation shared by [`reduce_each`], [`reduce_mixture`] and the fused tail
/// ([`super::reduce_to_writer_with_mixture`]): for each chunk of `chunk` Gaussian ids, visits every
/// contribution ([`ContributionStore::for_each`] order) and adds `a_kj` to `Σ a` and `a_kj · E_j`
/// to `Σ a E` of its Gaussian; `finish` turns each run of final sums into a part (in parallel; it
/// may take the extras out, the sums are reset before their next use), and `done` receives the
/// chunk's parts in ascending id order.
/// Within a Gaussian the sums always run in contribution, then entry order, so every caller and
/// both loop orders below get bit-identical f64 values.
///
/// Loop order ([`ReduceParams::image_major`]):
/// - *Gaussian-block-major* (default when no contribution is spilled): rayon over blocks of
///   [`REDUCE_BLOCK`] Gaussians, each block visiting every image's entries of its id range into
///   its thread's accumulator (`REDUCE_BLOCK × D` f64, 512 KiB at D = 512, reused from block to
///   block), which stays in the core's cache while all images are added; `finish` runs per
///   block. The memory traffic is one read of the entries and mask embeddings.
/// - *Image-major* (spilled contributions, streamed from disk one at a time): a chunk-sized
///   accumulator; for each image, rayon over blocks of 1024 Gaussians; every entry reads and
///   writes its Gaussian's f64 row in memory; `finish` runs once on the whole chunk.
///
/// Hooks: `on_image(first_chunk, image, c)` runs once per contribution and chunk, in visit order,
/// before its entries are added (after the width check; `image` counts the contributions of this
/// chunk's visit from 0) and returns a tag passed to `on_entry` (the mixture's codebook offset);
/// `on_entry(extra, entry, tag)` sees every entry with its Gaussian's extra, in the per-Gaussian
/// order above. The first error of a width mismatch or `on_image` is returned and no part of
/// that chunk is handed on (spill-file I/O errors come first). Returns the number of chunks.
pub(super) fn accumulate<T: Clone + Default + Send, B: Send>(
    pass: Pass<'_>,
    mut on_image: impl FnMut(bool, usize, &StoredImage) -> Result<u32>,
    on_entry: impl Fn(&mut T, &Entry, u32) + Sync,
    finish: impl Fn(&mut ChunkSums<T>) -> B + Sync,
    mut done: impl FnMut(Vec<B>) -> Result<()>,
) -> Result<usize> {
    let Pass {
        store,
        n_gaussians,
        dim,
        chunk,
        image_major,
    } = pass;
    if store.is_folding() {
        return Err(Error::internal(
            "the views were folded into the mixture: no reduction can read them again",
        ));
    }
    let mut chunks = 0;
    for start in (0..n_gaussians).step_by(chunk) {
        chunks += 1;
        let ids = start..(start + chunk).min(n_gaussians);
        let parts = if store.spilled() == 0 && !image_major {
            let images = &store.in_memory;
            block_major_chunk(images, ids, dim, &mut on_image, &on_entry, &finish)?
        } else {
            let part = image_major_chunk(store, ids, dim, &mut on_image, &on_entry, &finish)?;
            vec![part]
        };
        done(parts)?;
    }
    Ok(chunks)
}

/// Refuses a contribution whose mask embeddings are not `dim` wide (another CLIP model's).
fn check_width(c: &StoredImage, dim: usize) -> Result<()> {
    if c.dim != dim {
        return Err(Error::mismatch(
            slag_common::Mismatched::EmbeddingWidth,
            format!(
                "contribution of dim {}, expected {dim}: reduce contributions of one CLIP model",
                c.dim
            ),
        ));
    }
    Ok(())
}

/// One chunk (Gaussian ids `ids`) of the Gaussian-block-major loop of [`accumulate`]: checks and
/// tags every in-memory contribution in order, then rayon over runs of [`BLOCKS_PER_TASK`]
/// consecutive blocks of [`REDUCE_BLOCK`] Gaussians, each block's sums in its thread's reused
/// accumulator. Within a run each image's entries are walked forward: a block's first entry is
/// where the previous block's ended, so only the run's first block searches the whole image.
/// Returns the blocks' parts in ascending id order.
fn block_major_chunk<T: Clone + Default + Send, B: Send>(
    images: &[StoredImage],
    ids: Range<usize>,
    dim: usize,
    on_image: &mut impl FnMut(bool, usize, &StoredImage) -> Result<u32>,
    on_entry: &(impl Fn(&mut T, &Entry, u32) + Sync),
    finish: &(impl Fn(&mut ChunkSums<T>) -> B + Sync),
) -> Result<Vec<B>> {
    let mut tags = Vec::with_capacity(images.len());
    for (image, c) in images.iter().enumerate() {
        check_width(c, dim)?;
        tags.push(on_image(ids.start == 0, image, c)?);
    }
    let end = ids.end;
    let span = REDUCE_BLOCK * BLOCKS_PER_TASK;
    let runs: Vec<Vec<B>> = ids
        .step_by(span)
        .collect::<Vec<_>>()
        .into_par_iter()
        .map_init(
            || (ChunkSums::empty(dim), Vec::new()),
            |(sums, cursors), t0| {
                // Each image's first entry of Gaussian `t0` or later.
                cursors.clear();
                cursors.extend(images.iter().map(|c| first_entry_of(c, t0 as u32)));
                (t0..(t0 + span).min(end))
                    .step_by(REDUCE_BLOCK)
                    .map(|g0| {
                        sums.reset(g0, REDUCE_BLOCK.min(end - g0));
                        for ((c, &tag), lo) in images.iter().zip(&tags).zip(cursors.iter_mut()) {
                            let (num, den, extra) = (&mut sums.num, &mut sums.den, &mut sums.extra);
                            *lo =
                                add_entries(c, *lo, g0 as u32, dim, num, den, extra, tag, on_entry);
                        }
                        finish(sums)
                    })
                    .collect()
            },
        )
        .collect();
    Ok(runs.into_iter().flatten().collect())
}

/// One chunk (Gaussian ids `ids`) of the image-major loop of [`accumulate`]: a chunk-sized
/// accumulator; every contribution, streamed in [`ContributionStore::for_each`] order, is checked,
/// tagged and added by rayon over blocks of 1024 Gaussians. Returns the chunk's one part; the
/// first error (spill-file I/O first, then width or `on_image`) stops the adding.
fn image_major_chunk<T: Clone + Default + Send, B>(
    store: &ContributionStore,
    ids: Range<usize>,
    dim: usize,
    on_image: &mut impl FnMut(bool, usize, &StoredImage) -> Result<u32>,
    on_entry: &(impl Fn(&mut T, &Entry, u32) + Sync),
    finish: &impl Fn(&mut ChunkSums<T>) -> B,
) -> Result<B> {
    const BLOCK: usize = 1024;
    let start = ids.start;
    let mut sums = ChunkSums::empty(dim);
    sums.reset(start, ids.len());
    let mut failure: Option<Error> = None;
    let mut image = 0usize;
    store.for_each(|c| {
        if failure.is_some() {
            return;
        }
        let tag = match check_width(c, dim).and_then(|()| on_image(start == 0, image, c)) {
            Ok(tag) => tag,
            Err(e) => {
                failure = Some(e);
                return;
            }
        };
        image += 1;
        sums.num
            .par_chunks_mut(BLOCK * dim)
            .zip(sums.den.par_chunks_mut(BLOCK))
            .zip(sums.extra.par_chunks_mut(BLOCK))
            .enumerate()
            .for_each(|(b, ((num, den), extra))| {
                let g0 = (start + b * BLOCK) as u32;
                let lo = first_entry_of(c, g0);
                add_entries(c, lo, g0, dim, num, den, extra, tag, on_entry);
            });
    })?;
    if let Some(e) = failure {
        return Err(e);
    }
    Ok(finish(&mut sums))
}

/// Gaussians per block of the Gaussian-block-major reduction ([`accumulate`]).
const REDUCE_BLOCK: usize = 128;

/// Consecutive blocks per rayon task of the block-major reduction: enough that the binary
/// search of each image's entries (one cache miss per step over arrays of millions) is paid
/// once per run, few enough that a chunk still splits into hundreds of tasks.
const BLOCKS_PER_TASK: usize = 8;

/// The index of `c`'s first entry whose Gaussian is `g0` or later (its entries are sorted by
/// Gaussian): a binary search over the whole image.
pub(super) fn first_entry_of(c: &StoredImage, g0: u32) -> usize {
    c.gaussians.partition_point(|&g| g < g0)
}

/// The number of leading `ids` (ascending) below `bound`: an exponential search from the front,
/// then a binary search within the last step, so a short run costs a few reads near its start
/// instead of a search over the whole slice.
fn leading_below(ids: &[u32], bound: u32) -> usize {
    let (mut lo, mut step) = (0, 1);
    // Invariant: every id of `ids[..lo]` is below `bound`.
    while lo + step <= ids.len() && ids[lo + step - 1] < bound {
        lo += step;
        step *= 2;
    }
    let hi = (lo + step).min(ids.len());
    lo + ids[lo..hi].partition_point(|&g| g < bound)
}

/// Adds one image's entries for Gaussians `g0..g0 + db.len()` (its entries are sorted by
/// Gaussian; `lo` is its first entry of Gaussian `g0` or later) to that block's sums: `db[r] +=
/// a`, `nb[r·D..(r+1)·D] += a · E_j`, in entry order. Returns the index of the first entry after
/// the block, where the next block's entries start.
#[allow(clippy::too_many_arguments)]
#[inline]
pub(super) fn add_entries<T>(
    c: &StoredImage,
    lo: usize,
    g0: u32,
    dim: usize,
    nb: &mut [f64],
    db: &mut [f64],
    xb: &mut [T],
    tag: u32,
    on_entry: &(impl Fn(&mut T, &Entry, u32) + Sync),
) -> usize {
    let g1 = g0 + db.len() as u32;
    let hi = lo + leading_below(&c.gaussians[lo..], g1);
    let run = Run {
        gaussians: &c.gaussians[lo..hi],
        weights: &c.weights[lo..hi],
        mask_embeddings: &c.mask_embeddings,
        g0,
        dim,
    };
    match &c.masks {
        MaskColumn::U8(m) => run.add(&m[lo..hi], nb, db, xb, tag, on_entry),
        MaskColumn::U16(m) => run.add(&m[lo..hi], nb, db, xb, tag, on_entry),
        MaskColumn::U32(m) => run.add(&m[lo..hi], nb, db, xb, tag, on_entry),
    }
    hi
}

/// The entries of one image that fall in one block of Gaussians ([`add_entries`]).
struct Run<'a> {
    gaussians: &'a [u32],
    weights: &'a [f32],
    mask_embeddings: &'a [f32],
    g0: u32,
    dim: usize,
}

impl Run<'_> {
    /// Adds the run's entries, `masks` being their mask indices, in entry order.
    #[inline]
    fn add<M: Copy + Into<u32>, T>(
        &self,
        masks: &[M],
        nb: &mut [f64],
        db: &mut [f64],
        xb: &mut [T],
        tag: u32,
        on_entry: &(impl Fn(&mut T, &Entry, u32) + Sync),
    ) {
        let dim = self.dim;
        for ((&gaussian, &mask), &weight) in self.gaussians.iter().zip(masks).zip(self.weights) {
            let mask: u32 = mask.into();
            let r = (gaussian - self.g0) as usize;
            let a = weight as f64;
            db[r] += a;
            let ej = &self.mask_embeddings[mask as usize * dim..(mask as usize + 1) * dim];
            add_scaled(&mut nb[r * dim..(r + 1) * dim], a, ej);
            let e = Entry {
                gaussian,
                mask,
                weight,
            };
            on_entry(&mut xb[r], &e, tag);
        }
    }
}

/// `acc[i] += a · e[i]` in f64 for every `i` (`acc` and `e` of one length): the reduction's inner
/// loop, 512 multiply-adds per `a_kj` entry. A portable build targets x86-64's baseline (SSE2: two
/// f64 per instruction); where the CPU has AVX-512 or AVX2 (checked at run time, cached by std)
/// the same loop is compiled for eight or four. Each element is still one rounded product then
/// one rounded sum (Rust never fuses them into an FMA), so every path gives the same bits.
#[inline]
pub(super) fn add_scaled(acc: &mut [f64], a: f64, e: &[f32]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU has AVX-512F (checked just above).
            #[allow(unsafe_code)]
            unsafe {
                add_scaled_avx512(acc, a, e)
            };
            return;
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU has AVX2 (checked just above).
            #[allow(unsafe_code)]
            unsafe {
                add_scaled_avx2(acc, a, e)
            };
            return;
        }
    }
    add_scaled_portable(acc, a, e);
}

/// [`add_scaled`] for the build's baseline target.
#[inline]
fn add_scaled_portable(acc: &mut [f64], a: f64, e: &[f32]) {
    for (x, &v) in acc.iter_mut().zip(e) {
        *x += a * f64::from(v);
    }
}

/// [`add_scaled`] compiled for AVX-512F (the vectoriser widens the portable loop).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
fn add_scaled_avx512(acc: &mut [f64], a: f64, e: &[f32]) {
    add_scaled_portable(acc, a, e);
}

/// [`add_scaled`] compiled for AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn add_scaled_avx2(acc: &mut [f64], a: f64, e: &[f32]) {
    add_scaled_portable(acc, a, e);
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod simd_tests {
    use super::*;

    /// Every path the CPU offers gives the portable loop's bits, for lengths around the vector
    /// widths and values across f32's range (subnormal, huge, signed zeros).
    #[test]
    fn every_instruction_set_adds_the_same_bits() {
        let mut rng = slag_common::rng::SplitMix64::new(7);
        let specials = [0.0f32, -0.0, 1e-40, -3.4e38, 3.4e38, 1.0, -1.0, 6.1e-5];
        for len in [0usize, 1, 3, 4, 7, 8, 9, 15, 16, 17, 63, 512, 513] {
            for scale in [1e-300f64, 1e-3, 0.37, 1.0, 1e30, -2.5] {
                let e: Vec<f32> = (0..len)
                    .map(|i| {
                        if i % 5 == 0 {
                            specials[i / 5 % specials.len()]
                        } else {
                            (rng.next_f64() as f32 - 0.5) * 8.0
                        }
                    })
                    .collect();
                let start: Vec<f64> = (0..len).map(|_| rng.next_f64() * 1e3 - 5e2).collect();
                let mut want = start.clone();
                add_scaled_portable(&mut want, scale, &e);
                let mut got = start.clone();
                add_scaled(&mut got, scale, &e);
                let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&got), bits(&want), "len {len}, a {scale}");
                #[cfg(target_arch = "x86_64")]
                {
                    #[allow(unsafe_code)]
                    if std::arch::is_x86_feature_detected!("avx2") {
                        let mut v = start.clone();
                        // SAFETY: checked just above.
                        unsafe { add_scaled_avx2(&mut v, scale, &e) };
                        assert_eq!(bits(&v), bits(&want), "avx2, len {len}, a {scale}");
                    }
                    #[allow(unsafe_code)]
                    if std::arch::is_x86_feature_detected!("avx512f") {
                        let mut v = start;
                        // SAFETY: checked just above.
                        unsafe { add_scaled_avx512(&mut v, scale, &e) };
                        assert_eq!(bits(&v), bits(&want), "avx512, len {len}, a {scale}");
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod walk_tests {
    use super::*;

    /// The galloping search finds what a binary search over the whole slice finds, for every
    /// bound around and between the ids, on runs of repeated ids and gaps.
    #[test]
    fn leading_below_equals_partition_point() {
        let mut rng = slag_common::rng::SplitMix64::new(3);
        for len in [0usize, 1, 2, 3, 7, 8, 9, 100, 1000] {
            let mut ids: Vec<u32> = (0..len).map(|_| (rng.next_f64() * 300.0) as u32).collect();
            ids.sort_unstable();
            for bound in 0..=301u32 {
                let want = ids.partition_point(|&g| g < bound);
                assert_eq!(leading_below(&ids, bound), want, "len {len}, bound {bound}");
            }
        }
    }
}
