//! The reduction kept in mixture form: a codebook of mask embeddings and each Gaussian's largest
//! `a_kj` (`slag_common::mixture`).

use slag_common::mixture::{MixtureEmbeddings, SparseMixture};
use slag_common::{Error, Result};

use super::reduce::{Pass, accumulate};
use super::*;

/// The same reduction as [`reduce`], kept in mixture form ([`MixtureEmbeddings`]): a shared
/// codebook of every image's mask embeddings `E_j` plus, per observed Gaussian, its `keep`
/// largest `a_kj` over all images, so that `E_k ≈ Σ_{kept} a_kj E_j / ‖Σ_{kept} a_kj E_j‖`.
///
/// Codebook ids: the mask embeddings of the images are concatenated in the order
/// [`ContributionStore::for_each`] visits them (the in-memory images, then the spilled ones, each
/// in push order), so mask `j` of image `i` is row `offset_i + j`; rows no kept atom uses are then
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
    let sparse = reduce_mixture_sparse(store, n_gaussians, dim, params, keep, model_id, means)?;
    MixtureEmbeddings::from_sparse(sparse)
}

/// The part of [`reduce_mixture`] that reads `store`: the codebook (every mask embedding, `[M *
/// D]` f32) and each observed Gaussian's `keep` largest `(atom, a_kj)` as a [`SparseMixture`]
/// (`[N]` ids and means, `[N + 1]` offsets, up to `N × keep` atoms and f64 weights), before
/// [`MixtureEmbeddings::from_sparse`] builds the stored form. The encoder's tail drops the store
/// in between, so that the build's buffers never add to the `a_kj` entries.
///
/// Errors: those of [`reduce_mixture`] but [`MixtureEmbeddings::from_sparse`]'s.
pub fn reduce_mixture_sparse(
    store: &ContributionStore,
    n_gaussians: usize,
    dim: usize,
    params: ReduceParams,
    keep: usize,
    model_id: &str,
    means: &[[f32; 3]],
) -> Result<SparseMixture> {
    if keep == 0 {
        return Err(Error::param(
            "mixture_keep",
            keep,
            "at least 1 mask embedding kept per Gaussian",
        ));
    }
    if means.len() != n_gaussians {
        return Err(Error::internal(format!(
            "reduce_mixture: {} means for {n_gaussians} Gaussians",
            means.len()
        )));
    }
    let slots_estimate = keep.min(64);
    let per_gaussian = (dim + 1) * 8 + std::mem::size_of::<Vec<(f32, u32)>>() + slots_estimate * 8;
    let mut codebook: Vec<f32> = Vec::new();
    let mut image_offsets: Vec<u32> = Vec::new();
    let mut parts = SparseMixture {
        dim,
        model_id: model_id.to_string(),
        offsets: vec![0],
        ..Default::default()
    };
    accumulate(
        Pass::new(store, n_gaussians, dim, params, per_gaussian),
        |first_chunk, image, c| {
            if first_chunk {
                let rows = codebook.len() / dim.max(1);
                if rows + c.mask_embeddings.len() / dim.max(1) >= u32::MAX as usize {
                    return Err(Error::Invalid(format!(
                        "more than {} mask embeddings in all: too many for u32 codebook ids",
                        u32::MAX - 1
                    )));
                }
                image_offsets.push(rows as u32);
                codebook.extend_from_slice(&c.mask_embeddings);
            }
            image_offsets.get(image).copied().ok_or_else(|| {
                Error::internal("the contribution store changed during the reduction")
            })
        },
        |top: &mut Vec<(f32, u32)>, e, offset| push_top(top, keep, e.weight, offset + e.mask),
        // Per run: the observed Gaussians with their kept (a, atom), in id order.
        |sums| {
            sums.observed(params.min_total_weight)
                .map(|(r, _, _, _)| (sums.start + r, sums.extra[r].clone()))
                .collect::<Vec<_>>()
        },
        |runs| {
            for (k, top) in runs.into_iter().flatten() {
                parts.gaussian_ids.push(k as u32);
                parts.means.push(means[k]);
                for (a, atom) in top {
                    parts.atoms.push(atom);
                    parts.weights.push(a as f64);
                }
                parts.offsets.push(parts.atoms.len());
            }
            Ok(())
        },
    )?;
    parts.codebook = codebook;
    Ok(parts)
}

/// Keeps the `keep` largest `(a, atom)` of one Gaussian (ties: the lower atom). Atoms arrive in
/// increasing order, so an equal `a` never displaces a kept one.
fn push_top(top: &mut Vec<(f32, u32)>, keep: usize, a: f32, atom: u32) {
    if top.len() < keep {
        top.push((a, atom));
        return;
    }
    let weakest = top
        .iter()
        .enumerate()
        .min_by(|x, y| x.1.0.total_cmp(&y.1.0).then(y.1.1.cmp(&x.1.1)));
    if let Some((i, &(wa, watom))) = weakest
        && (a > wa || (a == wa && atom < watom))
    {
        top[i] = (a, atom);
    }
}
