//! The prediction-filtering predictors of a held-out pass, one set per segmentation, scored
//! beside the unfiltered ones (`eval-colors --held-out --prediction-filtering`, `eval-objects --held-out`):
//! `argmax` (the control), `pf-majority`, `pf-mean`, `pf-weighted`, `pf-confident`, `pf-strict`
//! ([`slag_encoder::prediction_filtering`]), and the last three over the mixture's mean form.

use std::path::{Path, PathBuf};

use slag_common::Result;
use slag_common::embeddings::Embeddings;
use slag_common::segments::Segments;
use slag_encoder::prediction_filtering as pf;

use crate::heldout_variants::VariantTable;

/// The prediction-filtering tables of the held-out pass: `argmax` (the control), then per
/// segmentation `pf-majority`, `pf-mean`, `pf-weighted`, `pf-confident` and `pf-strict` over
/// slag's dense scores, and the last three over the mixture's mean form when it is among
/// `variants` (the stored default). The first segmentation's names are bare; the
/// others' get `@<parent folder>/<file stem>`. `emb` gives which of the `n` scene Gaussians
/// are observed and their `Σ_j a_kj`; every table is `[n × c]`.
///
/// Errors: tables whose sizes disagree ([`slag_common::Error::Internal`]).
pub fn pf_tables(
    emb: &Embeddings,
    n: usize,
    slag_scores: &[f32],
    variants: &[crate::heldout_variants::VariantTable],
    segment_sets: &[(PathBuf, Segments)],
    c: usize,
) -> Result<Vec<VariantTable>> {
    let mut observed = vec![false; n];
    let mut sum_a = vec![0.0f32; n];
    for (row, &id) in emb.ids.iter().enumerate() {
        if let Some(o) = observed.get_mut(id as usize) {
            *o = true;
            sum_a[id as usize] = emb.total_weights.get(row).copied().unwrap_or(0.0);
        }
    }
    let table = |name: String, source: &Path, scores: Vec<f32>| VariantTable {
        name,
        source: source.to_path_buf(),
        scores,
        chosen_levels: Vec::new(),
    };
    let own = pf::gaussian_classes(slag_scores, &observed, c)?;
    let mut out = vec![table(
        "argmax".into(),
        &segment_sets[0].0,
        pf::one_hot(&own, c),
    )];
    let mixture = variants
        .iter()
        .find(|v| v.name.starts_with("mixture-mean-S") && v.source.ends_with("mixture.safetensors"))
        .map(|v| (v.name.clone(), v.scores.clone()));
    for (k, (path, s)) in segment_sets.iter().enumerate() {
        let tag = if k == 0 {
            String::new()
        } else {
            let parent = path
                .parent()
                .and_then(|p| p.file_name())
                .map(|p| p.to_string_lossy().into_owned())
                .unwrap_or_default();
            let stem = path
                .file_stem()
                .map(|p| p.to_string_lossy().into_owned())
                .unwrap_or_default();
            format!("@{parent}/{stem}")
        };
        let slag = pf::PfInputs {
            scores: slag_scores,
            observed: &observed,
            segments: &s.segments,
            classes: c,
        };
        out.push(table(
            format!("pf-majority{tag}"),
            path,
            pf::majority_table(&slag)?,
        ));
        out.push(table(format!("pf-mean{tag}"), path, pf::mean_table(&slag)?));
        // `pf-weighted`, `pf-confident` and `pf-strict` of `scores`, their names after `prefix`.
        let mut push_weighted = |prefix: &str, scores: &[f32]| -> Result<()> {
            let t = pf::PfInputs { scores, ..slag };
            let weighted = pf::weighted_table(&t, &sum_a)?;
            out.push(table(format!("{prefix}pf-weighted{tag}"), path, weighted));
            let confident = pf::confident_table(&t, &sum_a)?;
            out.push(table(format!("{prefix}pf-confident{tag}"), path, confident));
            let strict = pf::strict_majority_table(&t)?;
            out.push(table(format!("{prefix}pf-strict{tag}"), path, strict));
            Ok(())
        };
        push_weighted("", slag_scores)?;
        if let Some((name, scores)) = &mixture {
            push_weighted(&format!("{name}+"), scores)?;
        }
    }
    Ok(out)
}
