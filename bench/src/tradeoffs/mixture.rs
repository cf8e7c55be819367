//! Mixture storage points: the baseline's embeddings as a shared codebook of mask embeddings with
//! `S` sparse weights per Gaussian (`slag_common::mixture::MixtureEmbeddings`).

use std::time::Instant;

use slag_common::embeddings::Embeddings;
use slag_common::mixture::{MixtureEmbeddings, SparseMixture, UNUSED};

use super::storage::FootprintRow;
use super::{EvalContext, Row, sets};

/// `mix` cut to each Gaussian's `keep` largest weights (its slots are ordered by decreasing
/// weight), rebuilt with [`MixtureEmbeddings::from_sparse`] (unused codebook rows dropped, weights
/// renormalised). Equal to `reduce_mixture` with `keep` up to the f16 rounding of the weights
/// the order is taken from, when `mix` kept at least `keep` atoms.
///
/// Errors: as [`MixtureEmbeddings::from_sparse`].
pub fn truncate(mix: &MixtureEmbeddings, keep: usize) -> anyhow::Result<MixtureEmbeddings> {
    let n = mix.len();
    let s = mix.keep.max(1);
    let mut offsets = Vec::with_capacity(n + 1);
    let (mut atoms, mut weights) = (Vec::new(), Vec::new());
    offsets.push(0);
    for i in 0..n {
        let slots = i * s..(i + 1) * s;
        for (&a, &w) in mix.atoms[slots.clone()]
            .iter()
            .zip(&mix.weights[slots])
            .filter(|(a, w)| **a != UNUSED && **w != 0.0)
            .take(keep)
        {
            atoms.push(a);
            weights.push(w);
        }
        offsets.push(atoms.len());
    }
    Ok(MixtureEmbeddings::from_sparse(SparseMixture {
        dim: mix.dim,
        model_id: mix.model_id.clone(),
        codebook: mix.codebook.clone(),
        gaussian_ids: mix.gaussian_ids.clone(),
        means: mix.means.clone(),
        offsets,
        atoms,
        weights,
    })?)
}

/// Mixture points: `mix` (the baseline run's mixture, all atoms kept) cut to each of `keeps`, and
/// `mix` itself (point `mixture-Sall`), scored with [`MixtureEmbeddings::scores`] (codebook projections, then `S` multiply-adds per
/// Gaussian) against the exact f32 answer of the dense embeddings `emb` of the same run.
///
/// Also returns one footprint line per point (bytes as written to disk).
///
/// Errors: a mixture of other Gaussians than `emb`, scoring errors.
pub fn mixture_rows(
    ctx: &EvalContext,
    emb: &Embeddings,
    mix: &MixtureEmbeddings,
    keeps: &[usize],
    template: &Row,
    repeats: usize,
) -> anyhow::Result<(Vec<Row>, Vec<FootprintRow>)> {
    if mix.gaussian_ids != emb.ids {
        anyhow::bail!(
            "the mixture holds {} Gaussians, the dense embeddings {}: they come from different runs",
            mix.len(),
            emb.len()
        );
    }
    let exact = sets::threshold_sets(emb, &ctx.prompts, ctx.threshold)?;
    let mut rows = Vec::new();
    let mut footprint = Vec::new();
    let all = keeps.iter().map(|&k| Some(k)).chain([None]);
    for keep in all {
        let t = Instant::now();
        let m = match keep {
            Some(k) => truncate(mix, k)?,
            None => mix.clone(),
        };
        let build_s = t.elapsed().as_secs_f64();
        let name = keep.map_or_else(|| "all".to_string(), |k| k.to_string());
        let mut times = Vec::new();
        let mut answers = Vec::new();
        for q in &ctx.prompts {
            let pick = |scores: &[f32]| -> Vec<u32> {
                scores
                    .iter()
                    .zip(&m.gaussian_ids)
                    .filter(|(s, _)| **s >= ctx.threshold)
                    .map(|(_, &id)| id)
                    .collect()
            };
            answers.push(pick(&m.scores(q)?));
            for _ in 0..repeats {
                let t = Instant::now();
                std::hint::black_box(pick(&m.scores(q)?));
                times.push(t.elapsed().as_secs_f64() * 1e3);
            }
        }
        let dense = Embeddings {
            vectors: m.to_dense(),
            ..emb.clone()
        };
        let miou = ctx.colour_miou(&dense)?;
        let agreement = sets::mean_iou(&answers, &exact);
        eprintln!(
            "mixture S={name} (stored S {}): {:.1} B/Gaussian, IoU {:.4}",
            m.keep,
            m.bytes_per_gaussian(),
            agreement.0
        );
        footprint.push(FootprintRow {
            form: format!("mixture, S = {name} (codebook f16 + S × (u32 atom, f16 weight))"),
            gaussians: m.len(),
            bytes: m.stored_bytes() as u64,
            detail: format!("{} codebook rows, S = {}", m.codebook_len(), m.keep),
        });
        let row = Row {
            point: format!("mixture-S{name}"),
            knob: "mixture".into(),
            storage: format!("mixture-S{name}"),
            build_s,
            bytes_per_gaussian: m.bytes_per_gaussian(),
            query_ms: super::storage::median(times),
            ..template.clone()
        };
        rows.push(row.scanned_storage(ctx, miou, agreement));
    }
    Ok((rows, footprint))
}
