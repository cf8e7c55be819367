//! The per-Gaussian embeddings file: the encoder's output, readable from Python without slag
//! (`safetensors.numpy.load_file`).
//!
//! Tensors (row `i` describes one *observed* Gaussian; unobserved ones are not stored):
//! - `gaussian_ids`  U32 `[N]` — index of the Gaussian in the source `.ply` (vertex order);
//! - `means`         F32 `[N, 3]` — its centre, world frame of the scene, scene units;
//! - `embeddings`    F16 or F32 `[N, D]` — `E_k` (SLAG eq. for E_k), L2-normalised;
//! - `total_weights` F32 `[N]` — `Σ_i Σ_j a_kj`, the evidence behind `E_k`.
//!
//! Metadata (`__metadata__`, strings): `format = "slag-embeddings"`, `version = "1"`, `model`
//! (CLIP visual model id), `scene_gaussians` (N of the source `.ply`), `source_ply`.

use std::collections::HashMap;
use std::io::Write;
use std::path::Path;

use half::f16;
use safetensors::SafeTensors;
use safetensors::tensor::{Dtype, TensorView};

use crate::{Error, Result};

/// Format identifier stored in the metadata.
pub const FORMAT: &str = "slag-embeddings";
/// Current format version.
pub const VERSION: &str = "1";

/// Precision of the stored embedding vectors.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum StoredPrecision {
    /// IEEE half precision: 2 bytes per component (default; cosine error ~1e-3).
    #[default]
    F16,
    /// IEEE single precision: 4 bytes per component.
    F32,
}

/// Per-Gaussian language embeddings of one scene, held in memory as f32.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Embeddings {
    /// Source-`.ply` indices of the observed Gaussians, ascending. `[N]`.
    pub ids: Vec<u32>,
    /// Centres, world frame, scene units. `[N]`.
    pub means: Vec<[f32; 3]>,
    /// Embedding width D (512 for CLIP ViT-B).
    pub dim: usize,
    /// `[N * dim]` row-major, each row L2-normalised.
    pub vectors: Vec<f32>,
    /// `Σ a_kj` per Gaussian (blend-weight pixels of evidence). `[N]`.
    pub total_weights: Vec<f32>,
    /// CLIP visual model id (file stem of the ONNX export).
    pub model: String,
    /// Number of Gaussians in the source `.ply` (observed or not).
    pub scene_gaussians: u64,
    /// Path of the source `.ply`, as given to the encoder.
    pub source_ply: String,
}

impl Embeddings {
    /// Number of stored (observed) Gaussians.
    pub fn len(&self) -> usize {
        self.ids.len()
    }
    /// True when no Gaussian was observed.
    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }
    /// Row `i` of the embedding matrix.
    pub fn vector(&self, i: usize) -> &[f32] {
        &self.vectors[i * self.dim..(i + 1) * self.dim]
    }

    /// Writes the file atomically: to `<path>.partial`, fsync, then rename, so a killed run never
    /// leaves a file that looks complete.
    ///
    /// f16 rounds to nearest: relative error ≤ 2^-11 for |v| ≥ 6.1e-5, absolute ≤ 2^-25 below
    /// (subnormal halves, then 0).
    ///
    /// Errors: inconsistent lengths, a non-finite component, or with [`StoredPrecision::F16`] a
    /// component beyond the f16 range (±65504) ([`Error::Invalid`], nothing written); I/O.
    pub fn write(&self, path: &Path, precision: StoredPrecision) -> Result<()> {
        let n = self.ids.len();
        if self.means.len() != n
            || self.total_weights.len() != n
            || self.vectors.len() != n * self.dim
        {
            return Err(Error::Invalid(format!(
                "embeddings arrays disagree: {} ids, {} means, {} weights, {} values for dim {}",
                n,
                self.means.len(),
                self.total_weights.len(),
                self.vectors.len(),
                self.dim
            )));
        }
        if let Some(i) = self.vectors.iter().position(|v| !v.is_finite()) {
            return Err(Error::Invalid(format!(
                "embedding of Gaussian {} has a non-finite component ({}); the encoder output is \
                 corrupt, nothing was written",
                self.ids.get(i / self.dim.max(1)).copied().unwrap_or(0),
                self.vectors[i]
            )));
        }
        if precision == StoredPrecision::F16
            && let Some(i) = self
                .vectors
                .iter()
                .position(|&v| !f16::from_f32(v).is_finite())
        {
            return Err(Error::Invalid(format!(
                "embedding of Gaussian {} has the component {}, beyond the f16 range (±65504); \
                 write f32 precision or L2-normalise the rows (they should be unit vectors)",
                self.ids.get(i / self.dim.max(1)).copied().unwrap_or(0),
                self.vectors[i]
            )));
        }
        let ids: &[u8] = bytemuck::cast_slice(&self.ids);
        let means: &[u8] = bytemuck::cast_slice(&self.means);
        let weights: &[u8] = bytemuck::cast_slice(&self.total_weights);
        let halves: Vec<f16>;
        let (emb_dtype, emb): (Dtype, &[u8]) = match precision {
            StoredPrecision::F32 => (Dtype::F32, bytemuck::cast_slice(&self.vectors)),
            StoredPrecision::F16 => {
                halves = self.vectors.iter().map(|&v| f16::from_f32(v)).collect();
                (Dtype::F16, bytemuck::cast_slice(&halves))
            }
        };
        let view = |dtype, shape: Vec<usize>, data| {
            TensorView::new(dtype, shape, data)
                .map_err(|e| Error::Invalid(format!("safetensors: {e}")))
        };
        let tensors = vec![
            ("gaussian_ids", view(Dtype::U32, vec![n], ids)?),
            ("means", view(Dtype::F32, vec![n, 3], means)?),
            ("embeddings", view(emb_dtype, vec![n, self.dim], emb)?),
            ("total_weights", view(Dtype::F32, vec![n], weights)?),
        ];
        let meta: HashMap<String, String> = [
            ("format", FORMAT.to_string()),
            ("version", VERSION.to_string()),
            ("model", self.model.clone()),
            ("scene_gaussians", self.scene_gaussians.to_string()),
            ("source_ply", self.source_ply.clone()),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect();
        let bytes = safetensors::serialize(tensors, Some(meta))
            .map_err(|e| Error::Invalid(format!("safetensors: {e}")))?;
        write_atomic(path, &bytes)
    }

    /// Reads a file written by [`Embeddings::write`] (either precision).
    ///
    /// Errors: not a safetensors file, another format or version, missing tensors, shapes that
    /// disagree; each names the file.
    pub fn read(path: &Path) -> Result<Embeddings> {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        let bad = |m: String| Error::format(path, m);
        let (_, header) = SafeTensors::read_metadata(&bytes).map_err(|e| {
            bad(format!(
                "not a safetensors file ({e}); pass the encoder's embeddings.safetensors"
            ))
        })?;
        let meta = header.metadata().clone().unwrap_or_default();
        if meta.get("format").map(String::as_str) != Some(FORMAT) {
            return Err(bad(format!(
                "not a slag embeddings file (metadata format {:?})",
                meta.get("format")
            )));
        }
        if meta.get("version").map(String::as_str) != Some(VERSION) {
            return Err(bad(format!(
                "embeddings format version {:?}, this slag reads {VERSION}; re-run slag-encoder encode",
                meta.get("version")
            )));
        }
        let st = SafeTensors::deserialize(&bytes).map_err(|e| bad(format!("{e}")))?;
        let get = |name: &str| {
            st.tensor(name)
                .map_err(|e| bad(format!("tensor {name}: {e}")))
        };
        let ids_t = get("gaussian_ids")?;
        let means_t = get("means")?;
        let emb_t = get("embeddings")?;
        let w_t = get("total_weights")?;
        let n = ids_t.shape().first().copied().unwrap_or(0);
        let shape_ok = ids_t.dtype() == Dtype::U32
            && ids_t.shape() == [n]
            && means_t.dtype() == Dtype::F32
            && means_t.shape() == [n, 3]
            && w_t.dtype() == Dtype::F32
            && w_t.shape() == [n]
            && emb_t.shape().len() == 2
            && emb_t.shape()[0] == n;
        if !shape_ok {
            return Err(bad(
                "tensor shapes or dtypes disagree with the slag embeddings layout".into(),
            ));
        }
        let dim = emb_t.shape()[1];
        let vectors: Vec<f32> = match emb_t.dtype() {
            Dtype::F32 => le_f32(emb_t.data()),
            Dtype::F16 => emb_t
                .data()
                .chunks_exact(2)
                .map(|c| f16::from_le_bytes([c[0], c[1]]).to_f32())
                .collect(),
            other => {
                return Err(bad(format!(
                    "embeddings dtype {other:?}; expected F16 or F32"
                )));
            }
        };
        let ids = ids_t
            .data()
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        let flat = le_f32(means_t.data());
        let means = flat.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
        Ok(Embeddings {
            ids,
            means,
            dim,
            vectors,
            total_weights: le_f32(w_t.data()),
            model: meta.get("model").cloned().unwrap_or_default(),
            scene_gaussians: meta
                .get("scene_gaussians")
                .and_then(|s| s.parse().ok())
                .unwrap_or(0),
            source_ply: meta.get("source_ply").cloned().unwrap_or_default(),
        })
    }
}

fn le_f32(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

/// Writes `bytes` to `path` atomically (`<path>.partial`, fsync, rename). Creates parent folders.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    }
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".partial");
    let tmp = std::path::PathBuf::from(tmp);
    let mut f = std::fs::File::create(&tmp).map_err(|e| Error::io(&tmp, e))?;
    f.write_all(bytes)
        .and_then(|_| f.sync_all())
        .map_err(|e| Error::io(&tmp, e))?;
    drop(f);
    std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn sample(n: usize, dim: usize) -> Embeddings {
        let mut vectors = Vec::new();
        for i in 0..n {
            let mut v: Vec<f32> = (0..dim)
                .map(|d| ((i * 7 + d * 3) % 11) as f32 - 5.0)
                .collect();
            let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-6);
            v.iter_mut().for_each(|x| *x /= norm);
            vectors.extend(v);
        }
        Embeddings {
            ids: (0..n as u32).map(|i| i * 3 + 1).collect(),
            means: (0..n).map(|i| [i as f32, -(i as f32), 0.5]).collect(),
            dim,
            vectors,
            total_weights: (0..n).map(|i| i as f32 + 0.25).collect(),
            model: "color-clip-visual".into(),
            scene_gaussians: 3 * n as u64 + 5,
            source_ply: "scene/point_cloud.ply".into(),
        }
    }

    #[test]
    fn round_trip_f32_is_exact_and_f16_is_close() {
        let dir = tempfile::tempdir().unwrap();
        let e = sample(17, 8);
        let p32 = dir.path().join("e32.safetensors");
        e.write(&p32, StoredPrecision::F32).unwrap();
        assert_eq!(Embeddings::read(&p32).unwrap(), e);
        let p16 = dir.path().join("e16.safetensors");
        e.write(&p16, StoredPrecision::F16).unwrap();
        let back = Embeddings::read(&p16).unwrap();
        assert_eq!(back.ids, e.ids);
        assert_eq!(back.means, e.means);
        let max_err = back
            .vectors
            .iter()
            .zip(&e.vectors)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max);
        assert!(max_err < 1e-3, "f16 error {max_err}");
        assert!(!p16.with_extension("safetensors.partial").exists());
    }

    #[test]
    fn rejects_truncated_and_foreign_files() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("e.safetensors");
        sample(4, 4).write(&p, StoredPrecision::F32).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        std::fs::write(&p, &bytes[..bytes.len() - 9]).unwrap();
        assert!(matches!(Embeddings::read(&p), Err(Error::Format { .. })));
        std::fs::write(&p, b"hello world, not safetensors").unwrap();
        assert!(matches!(Embeddings::read(&p), Err(Error::Format { .. })));
        let other = safetensors::serialize(Vec::<(&str, TensorView)>::new(), None).unwrap();
        std::fs::write(&p, other).unwrap();
        assert!(matches!(Embeddings::read(&p), Err(Error::Format { .. })));
    }

    #[test]
    fn rejects_inconsistent_arrays() {
        let mut e = sample(3, 4);
        e.means.pop();
        let dir = tempfile::tempdir().unwrap();
        assert!(matches!(
            e.write(&dir.path().join("x"), StoredPrecision::F32),
            Err(Error::Invalid(_))
        ));
    }
}
