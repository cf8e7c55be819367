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
//! (CLIP model id: the image tower's `slag.clip_pair_id` metadata, else its file stem without
//! `-visual`; older files hold the full visual file stem, which pairs the same way),
//! `scene_gaussians` (N of the source `.ply`), `source_ply`.

use std::io::Write;
use std::path::Path;

use half::f16;
use half::slice::HalfFloatSliceExt;
use rayon::prelude::*;
use safetensors::tensor::Dtype;

use crate::safetensors_io::{self, FileKind, le_f16, le_f32, le_u32, tensor, triples};
use crate::{Error, Result};

/// Format identifier stored in the metadata.
pub const FORMAT: &str = "slag-embeddings";
/// Current format version.
pub const VERSION: &str = "1";

/// The metadata and message words of this file for [`safetensors_io`].
const KIND: FileKind = FileKind {
    format: FORMAT,
    version: VERSION,
    noun: "embeddings",
    file_name: "embeddings.safetensors",
    rewrite_with: "slag-encoder encode",
};

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
    /// CLIP model id (`slag_common::onnx::clip_pair_id` of the image tower; older files: the
    /// visual file stem). The text side checks it with `slag_common::onnx::check_clip_pair`.
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
    /// Errors (nothing written): inconsistent lengths ([`Error::Internal`]), a non-finite
    /// component ([`Error::Invalid`]), with [`StoredPrecision::F16`] a component beyond the f16
    /// range (±65504) ([`Error::Param`] `precision`); I/O.
    pub fn write(&self, path: &Path, precision: StoredPrecision) -> Result<()> {
        let n = self.ids.len();
        if self.means.len() != n
            || self.total_weights.len() != n
            || self.vectors.len() != n * self.dim
        {
            return Err(Error::internal(format!(
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
            return Err(Error::param(
                "precision",
                "f16",
                format!(
                    "f32 for the embedding of Gaussian {}, whose component {} is beyond the f16 \
                     range (±65504), or L2-normalised rows (they should be unit vectors)",
                    self.ids.get(i / self.dim.max(1)).copied().unwrap_or(0),
                    self.vectors[i]
                ),
            ));
        }
        let halves: Vec<f16>;
        let shape = vec![n, self.dim];
        let emb = match precision {
            StoredPrecision::F32 => tensor("embeddings", shape, &self.vectors),
            StoredPrecision::F16 => {
                halves = self.vectors.iter().map(|&v| f16::from_f32(v)).collect();
                tensor("embeddings", shape, &halves)
            }
        };
        let tensors = vec![
            tensor("gaussian_ids", vec![n], &self.ids),
            tensor("means", vec![n, 3], &self.means),
            emb,
            tensor("total_weights", vec![n], &self.total_weights),
        ];
        let meta = [
            ("model", self.model.clone()),
            ("scene_gaussians", self.scene_gaussians.to_string()),
            ("source_ply", self.source_ply.clone()),
        ];
        safetensors_io::write(path, &KIND, tensors, &meta)
    }

    /// Reads a file written by [`Embeddings::write`] (either precision). To read the rows of
    /// either stored form (this or the mixture), use [`crate::forms::read_rows`].
    ///
    /// Errors: not a safetensors file, another format or version, missing tensors, shapes that
    /// disagree; the mixture file given, or a missing file with the mixture beside it
    /// ([`crate::mixture::dense_file_needed`]); each names the file.
    pub fn read(path: &Path) -> Result<Embeddings> {
        // The mixture given, or only the mixture written: say how to get the dense file.
        if let Some(e) = crate::mixture::dense_file_needed(path) {
            return Err(e);
        }
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        let bad = |m: String| Error::format(path, m);
        let file = safetensors_io::open(path, &bytes, &KIND)?;
        let meta = &file.meta;
        let ids_t = file.tensor(path, "gaussian_ids")?;
        let means_t = file.tensor(path, "means")?;
        let emb_t = file.tensor(path, "embeddings")?;
        let w_t = file.tensor(path, "total_weights")?;
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
            Dtype::F16 => le_f16(emb_t.data()),
            other => {
                return Err(bad(format!(
                    "embeddings dtype {other:?}; expected F16 or F32"
                )));
            }
        };
        Ok(Embeddings {
            ids: le_u32(ids_t.data()),
            means: triples(&le_f32(means_t.data())),
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

/// Writes an embeddings file (the tensors of [`Embeddings::write`]) whose rows arrive in blocks,
/// so that a scene with tens of millions of observed Gaussians never holds its `[N, D]` matrix in
/// memory: each block's vectors are converted to the stored precision and appended to
/// `<path>.partial` behind a reserved header region ([`HEADER_RESERVE`] bytes); only ids, means
/// and total weights (20 bytes a row) stay in memory. [`EmbeddingsWriter::finish`] appends the
/// small tensors, writes the safetensors header into the reserved region (space-padded, as the
/// format allows), fsyncs and renames the file to `path`, so the vectors are written once. In this
/// layout `embeddings` comes first in the data section (safetensors readers go by each tensor's
/// `data_offsets`). A header longer than the reserve (a very long `source_ply`) falls back to
/// copying the data behind a header of its own size. Dropped unfinished (an error, a panic), the
/// writer removes its partial file: nothing that looks complete is left.
#[derive(Debug)]
pub struct EmbeddingsWriter {
    path: std::path::PathBuf,
    partial: std::path::PathBuf,
    file: Option<std::io::BufWriter<std::fs::File>>,
    dim: usize,
    precision: StoredPrecision,
    ids: Vec<u32>,
    means: Vec<[f32; 3]>,
    total_weights: Vec<f32>,
}

/// Bytes reserved at the start of an [`EmbeddingsWriter`] file for the 8-byte header length and
/// the JSON header; the data section starts at this (page-aligned) offset.
pub const HEADER_RESERVE: u64 = 8192;

impl EmbeddingsWriter {
    /// Starts a file at `path` for rows of width `dim` stored at `precision` (creates parent
    /// folders; an existing file at `path` stays until [`EmbeddingsWriter::finish`] replaces it).
    ///
    /// Errors: `dim == 0` ([`Error::Param`]); I/O.
    pub fn create(path: &Path, dim: usize, precision: StoredPrecision) -> Result<Self> {
        use std::io::{Seek, SeekFrom};
        if dim == 0 {
            return Err(Error::param("dim", dim, "an embedding width of at least 1"));
        }
        let (partial, mut f) = crate::io::create_partial(path)?;
        // The header region stays a hole until finish; a crash leaves only `<path>.partial`.
        f.seek(SeekFrom::Start(HEADER_RESERVE))
            .map_err(|e| Error::io(&partial, e))?;
        Ok(Self {
            path: path.to_path_buf(),
            partial,
            file: Some(std::io::BufWriter::with_capacity(1 << 22, f)),
            dim,
            precision,
            ids: Vec::new(),
            means: Vec::new(),
            total_weights: Vec::new(),
        })
    }

    /// Rows written so far.
    pub fn len(&self) -> usize {
        self.ids.len()
    }

    /// True before the first row.
    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }

    /// Appends a block of rows: `ids [B]` (ascending, above every id already written), `means
    /// [B]` (world frame), `vectors [B * dim]` (L2-normalised rows), `total_weights [B]`.
    ///
    /// Errors: lengths that disagree or ids out of order ([`Error::Internal`]: the caller's
    /// contract), non-finite or beyond-f16 values ([`Error::Invalid`]); I/O.
    pub fn push(
        &mut self,
        ids: &[u32],
        means: &[[f32; 3]],
        vectors: &[f32],
        total_weights: &[f32],
    ) -> Result<()> {
        let b = ids.len();
        if means.len() != b || total_weights.len() != b || vectors.len() != b * self.dim {
            return Err(Error::internal(format!(
                "embeddings block disagrees: {b} ids, {} means, {} weights, {} values for dim {}",
                means.len(),
                total_weights.len(),
                vectors.len(),
                self.dim
            )));
        }
        let mut last = self.ids.last().copied();
        for &id in ids {
            if last.is_some_and(|l| id <= l) {
                return Err(Error::internal(format!(
                    "embeddings rows must come in ascending Gaussian id order (got {id} after {last:?})"
                )));
            }
            last = Some(id);
        }
        // Large blocks are checked and converted in parallel; small runs (a block of the
        // reduction: 128 rows) serially, where rayon's fork would cost more than the work.
        const PAR: usize = 1 << 20;
        let bad_value = |v: &f32| !v.is_finite() || v.abs() > 65504.0;
        let bad = if vectors.len() >= PAR {
            vectors.par_iter().position_first(bad_value)
        } else {
            vectors.iter().position(bad_value)
        };
        if let Some(bad) = bad {
            return Err(Error::Invalid(format!(
                "embedding component {} of the block is {} (rows must be finite unit vectors)",
                bad, vectors[bad]
            )));
        }
        let w = self
            .file
            .as_mut()
            .ok_or_else(|| Error::internal("embeddings writer already finished"))?;
        let io = |e| Error::io(&self.partial, e);
        match self.precision {
            StoredPrecision::F32 => w.write_all(bytemuck::cast_slice(vectors)).map_err(io)?,
            StoredPrecision::F16 => {
                // Bulk conversion (F16C where the CPU has it), in parallel blocks.
                let mut halves = vec![f16::ZERO; vectors.len()];
                if vectors.len() >= PAR {
                    halves
                        .par_chunks_mut(1 << 16)
                        .zip(vectors.par_chunks(1 << 16))
                        .for_each(|(h, v)| h.convert_from_f32_slice(v));
                } else {
                    halves.convert_from_f32_slice(vectors);
                }
                w.write_all(bytemuck::cast_slice(&halves)).map_err(io)?
            }
        }
        self.ids.extend_from_slice(ids);
        self.means.extend_from_slice(means);
        self.total_weights.extend_from_slice(total_weights);
        Ok(())
    }

    /// Completes the file: appends `gaussian_ids`, `means` and `total_weights` behind the
    /// vectors, writes the header (the metadata of [`Embeddings`]) into the reserved region,
    /// fsyncs and renames `<path>.partial` to `path`.
    ///
    /// Errors: I/O (the partial file is removed).
    pub fn finish(mut self, model: &str, scene_gaussians: u64, source_ply: &str) -> Result<()> {
        let w = self
            .file
            .take()
            .ok_or_else(|| Error::internal("embeddings writer already finished"))?;
        let (mut hbytes, data_len) = self.header_json(model, scene_gaussians, source_ply)?;
        let mut f = self.append_tail(w, data_len)?;
        let reserve = (HEADER_RESERVE - 8) as usize;
        let res = if hbytes.len() <= reserve {
            hbytes.resize(reserve, b' ');
            write_reserved_header(&mut f, &hbytes).map(|()| self.partial.clone())
        } else {
            drop(f);
            move_behind_header(&self.partial, hbytes)
        };
        match res {
            Ok(done) => std::fs::rename(&done, &self.path).map_err(|e| Error::io(&self.path, e)),
            Err(e) => Err(Error::io(&self.partial, e)),
        }
    }

    /// The safetensors JSON header for the rows written so far (tensor dtypes, shapes and
    /// offsets in file order: embeddings, ids, means, weights; plus the metadata), and the
    /// length in bytes of the data section it describes.
    fn header_json(
        &self,
        model: &str,
        scene_gaussians: u64,
        source_ply: &str,
    ) -> Result<(Vec<u8>, usize)> {
        let n = self.ids.len();
        let (dtype, elem) = match self.precision {
            StoredPrecision::F32 => ("F32", 4usize),
            StoredPrecision::F16 => ("F16", 2usize),
        };
        let sizes = [
            ("embeddings", dtype, vec![n, self.dim], elem * n * self.dim),
            ("gaussian_ids", "U32", vec![n], 4 * n),
            ("means", "F32", vec![n, 3], 12 * n),
            ("total_weights", "F32", vec![n], 4 * n),
        ];
        let mut header = serde_json::Map::new();
        header.insert(
            "__metadata__".into(),
            serde_json::json!({
                "format": FORMAT, "version": VERSION, "model": model,
                "scene_gaussians": scene_gaussians.to_string(), "source_ply": source_ply,
            }),
        );
        let mut off = 0usize;
        for (name, dt, shape, len) in &sizes {
            header.insert(
                (*name).into(),
                serde_json::json!({"dtype": dt, "shape": shape, "data_offsets": [off, off + len]}),
            );
            off += len;
        }
        let hbytes = serde_json::to_vec(&serde_json::Value::Object(header))
            .map_err(|e| Error::internal(format!("embeddings header: {e}")))?;
        Ok((hbytes, off))
    }

    /// Writes ids, means and total weights behind the vectors, flushes, and checks that the
    /// data section is exactly `data_len` bytes long. Returns the open partial file.
    fn append_tail(
        &self,
        mut w: std::io::BufWriter<std::fs::File>,
        data_len: usize,
    ) -> Result<std::fs::File> {
        use std::io::Seek;
        let partial = &self.partial;
        let io = |e| Error::io(partial, e);
        w.write_all(bytemuck::cast_slice(&self.ids)).map_err(io)?;
        w.write_all(bytemuck::cast_slice(&self.means)).map_err(io)?;
        w.write_all(bytemuck::cast_slice(&self.total_weights))
            .map_err(io)?;
        let mut f = w.into_inner().map_err(|e| io(e.into_error()))?;
        let end = f.stream_position().map_err(io)?;
        if end != HEADER_RESERVE + data_len as u64 {
            return Err(Error::internal(format!(
                "{}: {} data bytes written, {data_len} expected",
                partial.display(),
                end - HEADER_RESERVE
            )));
        }
        Ok(f)
    }
}

/// Writes the 8-byte length and the header `hbytes` (already padded to fill the reserved
/// region: `HEADER_RESERVE - 8` bytes) at the start of `f`, then fsyncs it.
fn write_reserved_header(f: &mut std::fs::File, hbytes: &[u8]) -> std::io::Result<()> {
    use std::io::{Seek, SeekFrom};
    f.seek(SeekFrom::Start(0))?;
    f.write_all(&(hbytes.len() as u64).to_le_bytes())?;
    f.write_all(hbytes)?;
    f.sync_all()
}

/// For a header too large for the reserved region: writes `<partial>2` with the header
/// (padded to a multiple of 8 bytes) followed by the data section of `partial`, fsyncs it and
/// removes `partial`. Returns the new file's path; on failure both files are removed.
fn move_behind_header(partial: &Path, mut hbytes: Vec<u8>) -> std::io::Result<std::path::PathBuf> {
    use std::io::{Seek, SeekFrom};
    while !hbytes.len().is_multiple_of(8) {
        hbytes.push(b' ');
    }
    let mut again = partial.as_os_str().to_owned();
    again.push("2");
    let again = std::path::PathBuf::from(again);
    let r = (|| -> std::io::Result<()> {
        let mut src = std::fs::File::open(partial)?;
        src.seek(SeekFrom::Start(HEADER_RESERVE))?;
        let mut out = std::io::BufWriter::with_capacity(1 << 22, std::fs::File::create(&again)?);
        out.write_all(&(hbytes.len() as u64).to_le_bytes())?;
        out.write_all(&hbytes)?;
        std::io::copy(&mut src, &mut out)?;
        out.into_inner().map_err(|e| e.into_error())?.sync_all()
    })();
    let _ = std::fs::remove_file(partial);
    if r.is_err() {
        let _ = std::fs::remove_file(&again);
    }
    r.map(|()| again)
}

impl Drop for EmbeddingsWriter {
    fn drop(&mut self) {
        // Unfinished (or finished: then the file was renamed and this is a no-op).
        self.file = None;
        let _ = std::fs::remove_file(&self.partial);
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use safetensors::tensor::TensorView;

    #[test]
    fn streaming_writer_equals_the_in_memory_writer() {
        let dir = tempfile::tempdir().unwrap();
        let dim = 5;
        let n = 37;
        let mut e = Embeddings {
            dim,
            model: "m".into(),
            scene_gaussians: 100,
            source_ply: "scene.ply".into(),
            ..Default::default()
        };
        for i in 0..n {
            e.ids.push(i as u32 * 2 + 1);
            e.means.push([i as f32, -(i as f32), 0.5]);
            let v: Vec<f32> = (0..dim)
                .map(|d| ((i * 7 + d * 3) % 11) as f32 - 5.0)
                .collect();
            let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-6);
            e.vectors.extend(v.iter().map(|x| x / norm));
            e.total_weights.push(0.25 * i as f32 + 1.0);
        }
        for precision in [StoredPrecision::F32, StoredPrecision::F16] {
            let a = dir.path().join(format!("a-{precision:?}.safetensors"));
            let b = dir.path().join(format!("b-{precision:?}.safetensors"));
            e.write(&a, precision).unwrap();
            let mut w = EmbeddingsWriter::create(&b, dim, precision).unwrap();
            for (lo, hi) in [(0, 10), (10, 11), (11, 11), (11, n)] {
                w.push(
                    &e.ids[lo..hi],
                    &e.means[lo..hi],
                    &e.vectors[lo * dim..hi * dim],
                    &e.total_weights[lo..hi],
                )
                .unwrap();
            }
            w.finish(&e.model, e.scene_gaussians, &e.source_ply)
                .unwrap();
            assert_eq!(Embeddings::read(&a).unwrap(), Embeddings::read(&b).unwrap());
            assert!(
                !dir.path()
                    .join(format!("b-{precision:?}.safetensors.partial"))
                    .exists()
            );
        }
        // A header longer than the reserve (a 10 kB source path) takes the copying route.
        let long = dir.path().join("long.safetensors");
        let mut w = EmbeddingsWriter::create(&long, dim, StoredPrecision::F16).unwrap();
        w.push(&e.ids, &e.means, &e.vectors, &e.total_weights)
            .unwrap();
        let source = "d/".repeat(5000) + "scene.ply";
        w.finish(&e.model, e.scene_gaussians, &source).unwrap();
        let back = Embeddings::read(&long).unwrap();
        assert_eq!(back.source_ply, source);
        assert_eq!(back.ids, e.ids);
        assert!(
            std::fs::read_dir(dir.path())
                .unwrap()
                .all(|f| { !f.unwrap().file_name().to_string_lossy().contains("partial") })
        );
        // Out of order and unfinished writers leave nothing behind.
        let c = dir.path().join("c.safetensors");
        let mut w = EmbeddingsWriter::create(&c, dim, StoredPrecision::F16).unwrap();
        w.push(
            &e.ids[5..6],
            &e.means[5..6],
            &e.vectors[5 * dim..6 * dim],
            &e.total_weights[5..6],
        )
        .unwrap();
        assert!(matches!(
            w.push(
                &e.ids[2..3],
                &e.means[2..3],
                &e.vectors[2 * dim..3 * dim],
                &e.total_weights[2..3]
            ),
            Err(Error::Internal(_))
        ));
        drop(w);
        let left: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .filter_map(|e| e.ok())
            .filter(|e| e.file_name().to_string_lossy().starts_with('c'))
            .collect();
        assert!(left.is_empty(), "{left:?}");
    }

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
        let max_err = crate::similarity::max_abs_difference(&back.vectors, &e.vectors);
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
            Err(Error::Internal(_))
        ));
    }
}
