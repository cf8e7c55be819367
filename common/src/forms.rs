//! The two stored forms of the per-Gaussian embeddings and reading either: the dense rows
//! (`embeddings.safetensors`, [`crate::embeddings`], one `E_k` of D values per Gaussian) and the
//! mixture (`mixture.safetensors`, [`crate::mixture`], a shared codebook of mask embeddings plus
//! each Gaussian's strongest `a_kj`).
//!
//! `slag-encoder encode` writes the mixture by default and the dense file only when asked
//! (`--dense`). A command that needs `E_k` rows reads either form with [`read_rows`] (the
//! mixture is expanded row by row, [`expand_mixture`]); one that needs the dense file's own
//! columns (`Σ a_kj`) reads it with [`Embeddings::read`], which says how to get it
//! ([`crate::mixture::dense_file_needed`]) when it is given the mixture or finds only the mixture.

use std::path::Path;

use crate::embeddings::Embeddings;
use crate::mixture::MixtureEmbeddings;
pub use crate::mixture::mixture_beside;
use crate::safetensors_io;
use crate::{Error, Result};

/// Which form an embeddings file holds (its `format` metadata).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EmbeddingsForm {
    /// `slag-embeddings`: dense rows ([`Embeddings`]).
    Dense,
    /// `slag-mixture`: codebook + slots ([`MixtureEmbeddings`]).
    Mixture,
}

/// The form of the file at `path`, from its safetensors header alone (a 31 GB dense file is not
/// read).
///
/// Errors ([`Error::Format`] naming `path`): not a safetensors file, neither slag form;
/// [`Error::Io`]: unreadable.
pub fn form_of(path: &Path) -> Result<EmbeddingsForm> {
    match safetensors_io::metadata_format(path)?.as_deref() {
        Some(crate::embeddings::FORMAT) => Ok(EmbeddingsForm::Dense),
        Some(crate::mixture::FORMAT) => Ok(EmbeddingsForm::Mixture),
        other => Err(Error::format(
            path,
            format!(
                "neither slag embeddings form (metadata format {other:?}): pass the encoder's \
                 mixture.safetensors or embeddings.safetensors"
            ),
        )),
    }
}

/// The dense rows of the mixture `m`: row `i` is [`MixtureEmbeddings::vector`]`(i)` scaled to
/// unit L2 norm (its norm is 1 up to f16 rounding; less for a mixture cut to fewer slots).
/// `total_weights` are 0 (the mixture does not store `Σ a_kj`); `scene_gaussians` 0 and
/// `source_ply` empty (nor those). Memory: `N × D` f32.
pub fn expand_mixture(m: &MixtureEmbeddings) -> Embeddings {
    let mut vectors = m.to_dense();
    if m.dim > 0 {
        for row in vectors.chunks_mut(m.dim) {
            let norm = row.iter().map(|&v| v as f64 * v as f64).sum::<f64>().sqrt();
            if norm > 0.0 {
                row.iter_mut().for_each(|v| *v = (*v as f64 / norm) as f32);
            }
        }
    }
    Embeddings {
        ids: m.gaussian_ids.clone(),
        means: m.means.clone(),
        dim: m.dim,
        vectors,
        total_weights: vec![0.0; m.len()],
        model: m.model_id.clone(),
        scene_gaussians: 0,
        source_ply: String::new(),
    }
}

/// The `E_k` rows of the file at `path`, whichever form it holds: a dense file as it is, a
/// mixture expanded ([`expand_mixture`]). A dense path that does not exist, with
/// `mixture.safetensors` beside it (an encode without the dense file), reads that mixture (and
/// logs so).
///
/// Errors: those of [`form_of`], [`Embeddings::read`] and [`MixtureEmbeddings::read`].
pub fn read_rows(path: &Path) -> Result<Embeddings> {
    let beside = mixture_beside(path);
    let path = if !path.exists() && beside.is_file() {
        tracing::info!(
            "{} does not exist (the encode wrote the mixture form only): reading {}",
            path.display(),
            beside.display()
        );
        beside.as_path()
    } else {
        path
    };
    match form_of(path)? {
        EmbeddingsForm::Dense => Embeddings::read(path),
        EmbeddingsForm::Mixture => Ok(expand_mixture(&MixtureEmbeddings::read(path)?)),
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::embeddings::StoredPrecision;
    use crate::mixture::SparseMixture;

    fn mixture() -> MixtureEmbeddings {
        MixtureEmbeddings::from_sparse(SparseMixture {
            dim: 2,
            model_id: "m".into(),
            codebook: vec![1.0, 0.0, 0.0, 1.0],
            gaussian_ids: vec![3, 7],
            means: vec![[0.0; 3], [1.0, 2.0, 3.0]],
            offsets: vec![0, 1, 3],
            atoms: vec![0, 0, 1],
            weights: vec![2.0, 1.0, 1.0],
        })
        .unwrap()
    }

    #[test]
    fn either_form_reads_as_rows_and_the_dense_readers_name_the_mixture() {
        let dir = tempfile::tempdir().unwrap();
        let mix_path = dir.path().join("mixture.safetensors");
        let m = mixture();
        m.write(&mix_path).unwrap();
        assert_eq!(form_of(&mix_path).unwrap(), EmbeddingsForm::Mixture);
        let rows = read_rows(&mix_path).unwrap();
        assert_eq!(rows.ids, vec![3, 7]);
        assert_eq!(rows.means[1], [1.0, 2.0, 3.0]);
        assert!((rows.vector(0)[0] - 1.0).abs() < 1e-3 && rows.vector(0)[1].abs() < 1e-3);
        let h = std::f32::consts::FRAC_1_SQRT_2;
        assert!((rows.vector(1)[0] - h).abs() < 1e-3 && (rows.vector(1)[1] - h).abs() < 1e-3);

        // The dense file asked for where only the mixture was written: the rows read the
        // mixture beside it; the dense reader says how to get the dense file.
        let dense_path = dir.path().join("embeddings.safetensors");
        assert_eq!(read_rows(&dense_path).unwrap(), rows);
        let e = Embeddings::read(&dense_path).unwrap_err().to_string();
        assert!(
            e.contains("--dense") && e.contains("mixture.safetensors"),
            "{e}"
        );
        let e = Embeddings::read(&mix_path).unwrap_err().to_string();
        assert!(e.contains("mixture form") && e.contains("--dense"), "{e}");

        // A dense file reads as itself.
        rows.write(&dense_path, StoredPrecision::F32).unwrap();
        assert_eq!(form_of(&dense_path).unwrap(), EmbeddingsForm::Dense);
        assert_eq!(read_rows(&dense_path).unwrap().vectors, rows.vectors);

        let junk = dir.path().join("junk.safetensors");
        std::fs::write(&junk, b"not a file").unwrap();
        assert!(matches!(form_of(&junk), Err(Error::Format { .. })));
    }
}
