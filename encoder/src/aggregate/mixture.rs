//! The reduction kept in mixture form: a codebook of mask embeddings and each Gaussian's largest
//! `a_kj` (`slag_common::mixture`).

use slag_common::embeddings::EmbeddingsWriter;
use slag_common::mixture::{MixtureEmbeddings, SparseMixture};
use slag_common::{Error, Result};

use super::reduce::{Pass, accumulate, stream_to_writer};
use super::top::replace_weakest;
use super::*;

/// The same reduction as [`reduce`], kept in mixture form ([`MixtureEmbeddings`]): a shared
/// codebook of every image's mask embeddings `E_j` plus, per observed Gaussian, its `keep`
/// largest `a_kj` over all images, so that `E_k ≈ Σ_{kept} a_kj E_j / ‖Σ_{kept} a_kj E_j‖`.
///
/// Codebook ids: the mask embeddings of the images are concatenated in the order
/// [`ContributionStore::for_each`] visits them (by view index, whatever the order they arrived
/// in), so mask `j` of image `i` is row `offset_i + j`; rows no kept atom uses are then
/// dropped and the rest renumbered in that order ([`MixtureEmbeddings::from_sparse`]).
///
/// The observed Gaussians are exactly those of [`reduce`] with the same `params` (same f64
/// sums in the same order, same unobserved rule on the full `Σ a_kj` and `‖Σ a_kj E_j‖`); with
/// `keep` at least a Gaussian's number of non-zero `a_kj` its reconstruction equals [`reduce`]'s
/// `E_k` up to f16 rounding of the codebook and weights. Ties between equal `a_kj` keep the lower
/// codebook row. Memory: the f64 accumulator of [`reduce`] plus up to `keep` `(a, row)` pairs per
/// Gaussian of a chunk, chunked over Gaussian ids within `params.accumulator_budget_bytes`, plus
/// the whole `M × D` f32 codebook; the result holds `N × S` slots with
/// `S = min(keep, most non-zero a_kj of any observed Gaussian)` (the `[N, S]` layout pays `S`
/// slots for every Gaussian, so a heavy tail of atom counts makes a large `keep` expensive).
///
/// `means` are all `n_gaussians` centres (world frame, source `.ply` order); `model_id` is the
/// CLIP visual model id recorded in the output.
///
/// Errors: `keep == 0` ([`Error::Param`] `mixture_keep`), `means.len() != n_gaussians`
/// ([`Error::Internal`]), a contribution of another width than `dim` ([`Error::Mismatch`]), more
/// than `u32::MAX - 1` mask embeddings in all ([`Error::Invalid`]), a kept mixture that
/// [`MixtureEmbeddings::from_sparse`] cannot store (mask embeddings that nearly cancel); I/O
/// errors of spilled contributions.
pub fn reduce_mixture(
    store: &ContributionStore,
    n_gaussians: usize,
    dim: usize,
    params: ReduceParams,
    keep: usize,
    model_id: &str,
    means: &[[f32; 3]],
) -> Result<MixtureEmbeddings> {
    check_keep(keep)?;
    if means.len() != n_gaussians {
        return Err(Error::internal(format!(
            "reduce_mixture: {} means for {n_gaussians} Gaussians",
            means.len()
        )));
    }
    let (sparse, _) = reduce_mixture_chunks(store, means, dim, params, keep, model_id)?;
    MixtureEmbeddings::from_sparse(sparse)
}

/// The part of [`reduce_mixture`] that reads `store`, over all `means` (`[N]`, world frame,
/// `.ply` order): the codebook (every mask embedding, `[M * D]` f32) and each observed
/// Gaussian's `keep` largest `(atom, a_kj)` as a [`SparseMixture`] (`[N]` ids and means,
/// `[N + 1]` offsets, up to `N × keep` atoms and f64 weights), before
/// [`MixtureEmbeddings::from_sparse`] builds the stored form; also the number of Gaussian-id
/// chunks the pass took. The encoder's tail when only the mixture is written: no dense `E_k`
/// row is made, and the store is dropped before the build, so that the build's buffers never
/// add to the `a_kj` entries.
///
/// Errors: those of [`reduce_mixture`] but [`MixtureEmbeddings::from_sparse`]'s.
pub fn reduce_mixture_chunks(
    store: &ContributionStore,
    means: &[[f32; 3]],
    dim: usize,
    params: ReduceParams,
    keep: usize,
    model_id: &str,
) -> Result<(SparseMixture, usize)> {
    let n_gaussians = means.len();
    let (mut codebook, mut gather) = Gather::new(dim, keep, model_id, means)?;
    let (min_total_weight, per_gaussian) =
        (params.min_total_weight, Gather::per_gaussian(dim, keep));
    let chunks = accumulate(
        Pass::new(store, n_gaussians, dim, params, per_gaussian),
        |first_chunk, image, c| codebook.on_image(first_chunk, image, c),
        |top: &mut Vec<(f32, u32)>, e, offset| push_top(top, keep, e.weight, offset + e.mask),
        // Per run: the observed Gaussians with their kept (a, atom), in id order.
        |sums| {
            let observed: Vec<usize> = sums.observed(min_total_weight).map(|o| o.0).collect();
            observed
                .into_iter()
                .map(|r| (sums.start + r, std::mem::take(&mut sums.extra[r])))
                .collect::<Vec<Kept>>()
        },
        |runs| {
            gather.push(runs);
            Ok(())
        },
    )?;
    Ok((gather.finish(codebook), chunks))
}

/// What [`reduce_to_writer_with_mixture`] leaves: the embeddings as [`reduce_to_writer`] leaves
/// them and the mixture's sparse parts as [`reduce_mixture_chunks`] returns them.
pub struct StreamedMixture {
    /// The embeddings writer (all rows pushed, not yet finished), chunks, and the wall time of
    /// the shared reduction ([`Streamed::reduce_s`], which includes `gather_s`).
    pub streamed: Streamed,
    /// The codebook and each observed Gaussian's kept `(atom, a_kj)`, for
    /// [`MixtureEmbeddings::from_sparse`].
    pub sparse: SparseMixture,
    /// Seconds of the reduction's wall time spent only on the mixture: moving each chunk's kept
    /// atoms into `sparse` on the reducing thread, between chunks. (The per-entry top-`keep`
    /// selection runs inside the shared accumulation, on every core, and is not in it.)
    pub gather_s: f64,
}

/// [`reduce_to_writer`] and [`reduce_mixture_chunks`] in ONE pass over `store` (the encoder's
/// tail when the mixture is asked for): each chunk's f64 sums give both the embeddings rows,
/// streamed to `writer`, and the mixture's sparse parts, so the mixture costs its top-`keep`
/// bookkeeping and codebook, not a second reduction. The results are exactly those of the two
/// functions with the same arguments (same sums in the same order, same observed rule, same
/// ties, same codebook order; the chunking changes no value): the written rows bit for bit, the
/// [`SparseMixture`] equal.
///
/// Memory: that of [`reduce_to_writer`] with the accumulator of [`reduce_mixture_chunks`] (the
/// per-Gaussian kept pairs beside the f64 sums, chunked within
/// `params.accumulator_budget_bytes` on the image-major path, one block per thread on the
/// block-major path), plus the growing result: the `M × D` f32 codebook and up to `keep`
/// `(atom, a)` per observed Gaussian. `means` are all Gaussian centres (`[N]`, world frame,
/// `.ply` order); `model_id` is the CLIP visual model id recorded in the mixture.
///
/// Errors: those of [`reduce_to_writer`] and [`reduce_mixture_chunks`] (`keep == 0` is refused
/// before anything is read).
pub fn reduce_to_writer_with_mixture(
    store: &ContributionStore,
    means: &[[f32; 3]],
    dim: usize,
    params: ReduceParams,
    writer: EmbeddingsWriter,
    keep: usize,
    model_id: &str,
) -> Result<StreamedMixture> {
    let n_gaussians = means.len();
    let (mut codebook, mut gather) = Gather::new(dim, keep, model_id, means)?;
    let mut gather_s = 0.0;
    let per_gaussian = Gather::per_gaussian(dim, keep);
    let streamed = stream_to_writer(
        Pass::new(store, n_gaussians, dim, params, per_gaussian).streamed(),
        params.min_total_weight,
        means,
        writer,
        |first_chunk, image, c| codebook.on_image(first_chunk, image, c),
        |top: &mut Vec<(f32, u32)>, e, offset| push_top(top, keep, e.weight, offset + e.mask),
        // Per run: the kept (a, atom) of exactly the rows written, in id order.
        |sums, rows| {
            rows.ids
                .iter()
                .map(|&k| {
                    let k = k as usize;
                    (k, std::mem::take(&mut sums.extra[k - sums.start]))
                })
                .collect::<Vec<Kept>>()
        },
        |runs| {
            let t = std::time::Instant::now();
            gather.push(runs);
            gather_s += t.elapsed().as_secs_f64();
            Ok(())
        },
    )?;
    Ok(StreamedMixture {
        streamed,
        sparse: gather.finish(codebook),
        gather_s,
    })
}

/// The mixture's codebook, built from the first chunk's visit of the images (a pass's
/// `on_image` hook).
struct Codebook {
    dim: usize,
    /// `[M * D]` every image's mask embeddings, in visit order.
    rows: Vec<f32>,
    /// First codebook row of each image, in visit order.
    image_offsets: Vec<u32>,
}

impl Codebook {
    /// [`accumulate`]'s `on_image`: appends the image's mask embeddings to the codebook on the
    /// first chunk's visit, and returns its first codebook row (the tag that turns its mask
    /// indices into atoms).
    ///
    /// Errors: more than `u32::MAX - 1` mask embeddings in all ([`Error::Invalid`]); an image
    /// a later chunk visits that the first did not ([`Error::Internal`]).
    fn on_image(&mut self, first_chunk: bool, image: usize, c: &StoredImage) -> Result<u32> {
        let dim = self.dim.max(1);
        if first_chunk {
            let rows = self.rows.len() / dim;
            if rows + c.mask_embeddings.len() / dim >= u32::MAX as usize {
                return Err(Error::Invalid(format!(
                    "more than {} mask embeddings in all: too many for u32 codebook ids",
                    u32::MAX - 1
                )));
            }
            self.image_offsets.push(rows as u32);
            self.rows.extend_from_slice(&c.mask_embeddings);
        }
        self.image_offsets
            .get(image)
            .copied()
            .ok_or_else(|| Error::internal("the contribution store changed during the reduction"))
    }
}

/// One observed Gaussian of a run: its id and its kept `(a_kj, atom)` pairs (at most `keep`).
type Kept = (usize, Vec<(f32, u32)>);

/// The mixture's rows: the observed Gaussians' kept `(a, atom)`, gathered chunk by chunk into a
/// [`SparseMixture`] (a pass's `done` side).
struct Gather<'m> {
    means: &'m [[f32; 3]],
    parts: SparseMixture,
}

/// Refuses `keep == 0` ([`Error::Param`] `mixture_keep`): a mixture keeps at least one atom.
fn check_keep(keep: usize) -> Result<()> {
    if keep == 0 {
        return Err(Error::param(
            "mixture_keep",
            keep,
            "at least 1 mask embedding kept per Gaussian",
        ));
    }
    Ok(())
}

impl<'m> Gather<'m> {
    /// An empty codebook and gather for the Gaussians of `means`.
    ///
    /// Errors: `keep == 0` ([`Error::Param`] `mixture_keep`).
    fn new(
        dim: usize,
        keep: usize,
        model_id: &str,
        means: &'m [[f32; 3]],
    ) -> Result<(Codebook, Self)> {
        check_keep(keep)?;
        let codebook = Codebook {
            dim,
            rows: Vec::new(),
            image_offsets: Vec::new(),
        };
        let gather = Gather {
            means,
            parts: SparseMixture {
                dim,
                model_id: model_id.to_string(),
                offsets: vec![0],
                ..Default::default()
            },
        };
        Ok((codebook, gather))
    }

    /// Accumulator bytes per Gaussian of a pass that keeps `keep` pairs: the f64 sums plus the
    /// kept pairs' vector (its capacity estimated at 64 pairs at most).
    fn per_gaussian(dim: usize, keep: usize) -> usize {
        (dim + 1) * 8 + std::mem::size_of::<Vec<(f32, u32)>>() + keep.min(64) * 8
    }

    /// Appends one chunk's observed Gaussians (`(id, kept (a, atom))`, runs in ascending id
    /// order) to the sparse rows.
    fn push(&mut self, runs: Vec<Vec<Kept>>) {
        let parts = &mut self.parts;
        for (k, top) in runs.into_iter().flatten() {
            parts.gaussian_ids.push(k as u32);
            parts.means.push(self.means[k]);
            for (a, atom) in top {
                parts.atoms.push(atom);
                parts.weights.push(a);
            }
            parts.offsets.push(parts.atoms.len());
        }
    }

    /// The gathered [`SparseMixture`] with `codebook`'s rows.
    fn finish(self, codebook: Codebook) -> SparseMixture {
        SparseMixture {
            codebook: codebook.rows,
            ..self.parts
        }
    }
}

/// Keeps the `keep` largest `(a, atom)` of one Gaussian (ties: the lower atom). Atoms arrive in
/// increasing order, so an equal `a` never displaces a kept one.
fn push_top(top: &mut Vec<(f32, u32)>, keep: usize, a: f32, atom: u32) {
    if top.len() < keep {
        top.push((a, atom));
        return;
    }
    replace_weakest(top, a, atom);
}
