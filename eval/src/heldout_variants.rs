//! The predictors that `eval-colors --held-out` scores beside the main embeddings, in the same
//! render pass (the aggregation variants):
//!
//! - `--compare FILE`: another embeddings file (e.g. another `--mask-weighting`), scored like
//!   the main one (`cos(E_k, text_c)`).
//! - `embeddings-level{0,1,2}.safetensors` beside the main file (`encode --levels`): one
//!   embedding per SAM granularity level, combined per [`LevelRule`] (each fixed level, LangSplat's
//!   most-relevant level per query, and the per-Gaussian max); a Gaussian without the level falls
//!   back to its mean `E_k`.
//! - `mixture.safetensors` beside the main file (`encode --mixture-keep S`): the mixture's mean
//!   form (`MixtureEmbeddings::scores`), the mean over each Gaussian's top 1, 2, 4, 8 masks only,
//!   the robust mode of [`slag_encoder::aggregate::robust`], and its *max* form, the highest
//!   cosine over a Gaussian's top-`s` mask embeddings (`MixtureEmbeddings::max_atom_scores`), for
//!   `s` in 1, 2, 4, 8, S.

use std::path::{Path, PathBuf};

use slag_common::embeddings::Embeddings;
use slag_common::mixture::MixtureEmbeddings;
use slag_common::{Error, Result};
use slag_encoder::aggregate::levels::{LEVELS, LevelRule, combine_levels};

use crate::heldout::{PixelScore, gaussian_scores};

/// Concentration of the mode variant (`mixture-mode-S*`, [`slag_encoder::aggregate::robust`]).
const MODE_KAPPA: f32 = 10.0;

/// One predictor's `[scene Gaussians × C]` class-score table, before scoring.
#[derive(Debug, Clone, PartialEq)]
pub struct VariantTable {
    /// Short name (`compare`, `level-0`, `levels-select`, `mixture-max-S4`, …).
    pub name: String,
    /// The file it came from.
    pub source: PathBuf,
    /// `[scene Gaussians × C]` scores (0 for Gaussians without a stored form).
    pub scores: Vec<f32>,
    /// For `levels-select`: the level chosen per class (class order); empty otherwise.
    pub chosen_levels: Vec<usize>,
}

/// A variant's held-out score, as `eval-colors --held-out` prints it under `variants`.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct VariantScore {
    /// Short name of the predictor.
    pub name: String,
    /// The file it came from.
    pub source: PathBuf,
    /// For `levels-select`: the level chosen per class (class order).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub chosen_levels: Vec<usize>,
    /// Its held-out score on the same counted pixels as slag.
    pub score: PixelScore,
}

impl VariantTable {
    /// Attaches the tally's score.
    pub fn scored(self, score: PixelScore) -> VariantScore {
        VariantScore {
            name: self.name,
            source: self.source,
            chosen_levels: self.chosen_levels,
            score,
        }
    }
}

/// Reads an embeddings file of the same scene as the main one.
fn read_same_scene(path: &Path, scene_gaussians: usize) -> Result<Embeddings> {
    let e = Embeddings::read(path)?;
    if e.scene_gaussians != scene_gaussians as u64 {
        return Err(Error::mismatch(
            slag_common::Mismatched::Scene,
            format!(
                "{} was made from a scene of {} Gaussians, not {scene_gaussians}: compare only \
                 encodes of the same .ply",
                path.display(),
                e.scene_gaussians
            ),
        ));
    }
    Ok(e)
}

/// Every variant's score table: the `compare` files, then the per-level and mixture forms found
/// beside `embeddings_path`. `mean_scores` is the main embeddings' table (the levels' fallback),
/// `texts` the class text embeddings, `n` the scene's Gaussians.
///
/// Errors: unreadable files (I/O), files of another scene ([`Error::Mismatch`]), and those of
/// [`gaussian_scores`] and [`combine_levels`].
pub fn variant_tables(
    embeddings_path: &Path,
    compare: &[PathBuf],
    mean_scores: &[f32],
    texts: &[Vec<f32>],
    n: usize,
) -> Result<Vec<VariantTable>> {
    let mut out = Vec::new();
    for path in compare {
        let e = read_same_scene(path, n)?;
        out.push(plain(
            "compare".into(),
            path,
            gaussian_scores(&e, texts, n)?,
        ));
    }
    let dir = embeddings_path.parent().unwrap_or(Path::new("."));
    out.extend(level_tables(dir, mean_scores, texts, n)?);
    let mix_path = dir.join("mixture.safetensors");
    if mix_path.exists() {
        out.extend(mixture_tables(&mix_path, texts, n)?);
    }
    Ok(out)
}

/// A variant without chosen levels.
fn plain(name: String, source: &Path, scores: Vec<f32>) -> VariantTable {
    VariantTable {
        name,
        source: source.to_path_buf(),
        scores,
        chosen_levels: Vec::new(),
    }
}

/// The per-level variants (each [`LevelRule`]) when every `embeddings-level{l}.safetensors` is in
/// `dir`; none otherwise.
fn level_tables(
    dir: &Path,
    mean_scores: &[f32],
    texts: &[Vec<f32>],
    n: usize,
) -> Result<Vec<VariantTable>> {
    let level_paths: Vec<PathBuf> = (0..LEVELS)
        .map(|l| dir.join(format!("embeddings-level{l}.safetensors")))
        .collect();
    if !level_paths.iter().all(|p| p.exists()) {
        return Ok(Vec::new());
    }
    let mut tables = Vec::new();
    let mut has = Vec::new();
    for p in &level_paths {
        let e = read_same_scene(p, n)?;
        let mut h = vec![false; n];
        for &id in &e.ids {
            if let Some(slot) = h.get_mut(id as usize) {
                *slot = true;
            }
        }
        tables.push(gaussian_scores(&e, texts, n)?);
        has.push(h);
    }
    let rules = (0..LEVELS)
        .map(LevelRule::Fixed)
        .chain([LevelRule::Select, LevelRule::Max]);
    let mut out = Vec::new();
    for rule in rules {
        let (scores, chosen) = combine_levels(&tables, &has, mean_scores, texts.len(), rule)?;
        out.push(VariantTable {
            name: rule.name(),
            source: dir.to_path_buf(),
            scores,
            chosen_levels: chosen,
        });
    }
    Ok(out)
}

/// The mixture's Gaussians with `vectors` (one row each) as dense embeddings of a scene of `n`.
fn mixture_dense(m: &MixtureEmbeddings, vectors: Vec<f32>, n: usize) -> Embeddings {
    Embeddings {
        ids: m.gaussian_ids.clone(),
        means: m.means.clone(),
        dim: m.dim,
        vectors,
        total_weights: vec![1.0; m.len()],
        scene_gaussians: n as u64,
        ..Embeddings::default()
    }
}

/// The mixture variants of `mix_path`: its mean form, the mean over each Gaussian's `s` strongest
/// masks, its robust mode and its max form over the top `s` masks.
fn mixture_tables(mix_path: &Path, texts: &[Vec<f32>], n: usize) -> Result<Vec<VariantTable>> {
    let c = texts.len();
    let m = MixtureEmbeddings::read(mix_path)?;
    let unit_texts: Vec<&[f32]> = texts.iter().map(Vec::as_slice).collect();
    let spread = |per_class: Vec<Vec<f32>>| -> Result<Vec<f32>> {
        let mut t = vec![0f32; n * c];
        for (cls, col) in per_class.iter().enumerate() {
            for (&id, &v) in m.gaussian_ids.iter().zip(col) {
                let slot = t.get_mut(id as usize * c + cls).ok_or_else(|| {
                    Error::mismatch(
                        slag_common::Mismatched::Scene,
                        format!(
                            "{}: Gaussian {id} outside the scene's {n}",
                            mix_path.display()
                        ),
                    )
                })?;
                *slot = v;
            }
        }
        Ok(t)
    };
    let mut out = vec![plain(
        format!("mixture-mean-S{}", m.keep),
        mix_path,
        spread(m.scores_many(&unit_texts)?)?,
    )];
    // The mean over each Gaussian's `s` strongest masks only (slots are ordered by weight).
    for s in [1usize, 2, 4, 8].into_iter().filter(|&s| s < m.keep) {
        let mut cut = m.clone();
        for (i, (a, w)) in cut.atoms.iter_mut().zip(cut.weights.iter_mut()).enumerate() {
            if i % m.keep >= s {
                *a = slag_common::mixture::UNUSED;
                *w = 0.0;
            }
        }
        let e = mixture_dense(&m, cut.to_dense(), n);
        out.push(plain(
            format!("mixture-mean-S{s}"),
            mix_path,
            gaussian_scores(&e, texts, n)?,
        ));
    }
    let kappa = MODE_KAPPA;
    let modes = slag_encoder::aggregate::robust::mixture_modes(
        &m,
        kappa,
        slag_encoder::aggregate::robust::MODE_ITERATIONS,
    )?;
    let e = mixture_dense(&m, modes, n);
    out.push(plain(
        format!("mixture-mode-S{}-k{kappa}", m.keep),
        mix_path,
        gaussian_scores(&e, texts, n)?,
    ));
    let mut tops: Vec<usize> = [1, 2, 4, 8].into_iter().filter(|&s| s < m.keep).collect();
    tops.push(m.keep);
    for s in tops {
        let per_class = unit_texts
            .iter()
            .map(|t| m.max_atom_scores(t, s))
            .collect::<Result<Vec<_>>>()?;
        out.push(plain(
            format!("mixture-max-S{s}"),
            mix_path,
            spread(per_class)?,
        ));
    }
    Ok(out)
}
