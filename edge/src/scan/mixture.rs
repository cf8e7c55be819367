//! Mixture rows ([`slag_common::shards::mixture`]) in the scan store, and their exact scan kernel.
//!
//! A mixture store keeps the scene's codebook (`A × D` f32, the f16 values of its file) and per
//! Gaussian `S` `(atom, weight)` slots. At load every row's weights are divided by the norm of
//! its reconstruction ([`slag_common::mixture::row_norm`], the definition
//! [`slag_common::mixture::MixtureEmbeddings::scores`] divides by), so a row's cosine with a unit
//! query `q` is `Σ_s w'_s · (q·E_{a_s})`. A scan first computes `q·E_j` for every codebook row
//! with the dense SIMD kernel ([`super::kernels::scan_chunk`] over the codebook as an f32 store:
//! `A · D` multiply-adds per query), then `S` multiply-adds per Gaussian: the work per row no
//! longer depends on D.

use slag_common::Error;
use slag_common::mixture::row_norm;
use slag_common::shards::mixture::UNUSED;
use slag_common::shards::{MixtureShard, StoredVectors};

use super::kernels;

/// Codebook rows per rayon task of [`MixtureRows::project`] (256 KiB of f32 rows at D = 512).
const PROJECT_ROWS: usize = 128;

/// The mixture rows of a store: codebook, slots, atoms and norm-scaled weights.
#[derive(Debug, Clone)]
pub struct MixtureRows {
    dim: usize,
    slots: usize,
    codebook_crc: u32,
    /// `[A * D]` codebook as an f32 store (for the dense kernel).
    codebook: StoredVectors,
    atoms_in_codebook: usize,
    /// `[N * S]` codebook rows; an empty slot points at row 0 with weight 0.
    atoms: Vec<u32>,
    /// `[N * S]` weights divided by the row's reconstruction norm (0 for a zero row).
    weights: Vec<f32>,
}

impl MixtureRows {
    /// An empty set of rows over `codebook` (`[A * dim]` row-major), whose file has CRC-32
    /// `codebook_crc`, with `slots` slots per row.
    ///
    /// Errors: [`Error::Param`] for `dim == 0`, `slots == 0`, or a codebook that is not rows
    /// of `dim` values, or is empty.
    pub fn new(
        dim: usize,
        slots: usize,
        codebook: Vec<f32>,
        codebook_crc: u32,
    ) -> Result<MixtureRows, Error> {
        if dim == 0 || slots == 0 || codebook.is_empty() || !codebook.len().is_multiple_of(dim) {
            return Err(Error::param(
                "codebook",
                format!("{} values, dim {dim}, {slots} slots", codebook.len()),
                "a non-empty codebook of rows of the scene's width and at least one slot",
            ));
        }
        Ok(MixtureRows {
            dim,
            slots,
            codebook_crc,
            atoms_in_codebook: codebook.len() / dim,
            codebook: StoredVectors::F32(codebook),
            atoms: Vec::new(),
            weights: Vec::new(),
        })
    }

    /// Slots per row S.
    pub fn slots(&self) -> usize {
        self.slots
    }
    /// Codebook rows A.
    pub fn atoms_in_codebook(&self) -> usize {
        self.atoms_in_codebook
    }
    /// CRC-32 of the codebook file the rows index.
    pub fn codebook_crc(&self) -> u32 {
        self.codebook_crc
    }
    /// Number of rows N.
    pub fn len(&self) -> usize {
        self.atoms.len() / self.slots
    }
    /// True without rows.
    pub fn is_empty(&self) -> bool {
        self.atoms.is_empty()
    }
    /// Bytes held: codebook (`A·D·4`) plus `8·S` per row (u32 atom + f32 weight).
    pub fn memory_bytes(&self) -> usize {
        self.codebook.values() * 4 + self.atoms.len() * 8
    }

    /// Reserves room for `rows` more rows.
    ///
    /// Errors: the allocator refuses ([`std::collections::TryReserveError`]).
    pub fn try_reserve(&mut self, rows: usize) -> Result<(), std::collections::TryReserveError> {
        let n = rows.saturating_mul(self.slots);
        self.atoms.try_reserve_exact(n)?;
        self.weights.try_reserve_exact(n)
    }

    /// Checks a shard against these rows (dim, slots, codebook, atoms in range): what
    /// [`MixtureRows::push`] would refuse, without changing anything.
    ///
    /// Errors: [`Error::Mismatch`] (another width, slot count or codebook), [`Error::Format`]
    /// (an atom beyond the codebook: the shard does not belong to it).
    pub fn check(&self, s: &MixtureShard) -> Result<(), Error> {
        let h = &s.header;
        if h.dim as usize != self.dim
            || s.slots as usize != self.slots
            || s.codebook_crc != self.codebook_crc
        {
            return Err(Error::mismatch(
                slag_common::Mismatched::Dtype,
                format!(
                    "mixture shard (tile {}: dim {}, {} slots, codebook {:08x}) does not belong \
                     to this store (dim {}, {} slots, codebook {:08x}); fetch the scene again",
                    h.tile_id,
                    h.dim,
                    s.slots,
                    s.codebook_crc,
                    self.dim,
                    self.slots,
                    self.codebook_crc
                ),
            ));
        }
        if let Some(a) = s
            .atoms
            .iter()
            .find(|&&a| a != UNUSED && a as usize >= self.atoms_in_codebook)
        {
            return Err(Error::format(
                format!("shard {}", h.tile_id),
                format!(
                    "atom {a} beyond the codebook's {} rows; fetch the scene again",
                    self.atoms_in_codebook
                ),
            ));
        }
        if s.atoms.len() != s.ids.len() * self.slots || s.weights.len() != s.atoms.len() {
            return Err(Error::Invalid(format!(
                "mixture shard (tile {}) is inconsistent: {} ids, {} atoms, {} weights; \
                 re-download it",
                h.tile_id,
                s.ids.len(),
                s.atoms.len(),
                s.weights.len()
            )));
        }
        Ok(())
    }

    /// Appends the rows of a checked shard ([`MixtureRows::check`]): empty slots become atom 0
    /// with weight 0, and each row's weights are divided by its reconstruction's norm.
    pub(super) fn push_checked(&mut self, s: &MixtureShard) {
        let Some(book) = self.codebook_f32() else {
            return;
        };
        use rayon::prelude::*;
        let (dim, slots) = (self.dim, self.slots);
        let mut scaled = vec![0.0f32; s.weights.len()];
        scaled
            .par_chunks_mut(slots)
            .zip(s.atoms.par_chunks_exact(slots))
            .zip(s.weights.par_chunks_exact(slots))
            .for_each(|((out, a), w)| {
                let norm = row_norm(book, dim, a, w.iter().map(|x| x.to_f32()));
                let inv = if norm > 0.0 { norm.recip() } else { 0.0 };
                out.iter_mut()
                    .zip(w)
                    .for_each(|(o, x)| *o = x.to_f32() * inv);
            });
        self.atoms
            .extend(s.atoms.iter().map(|&a| if a == UNUSED { 0 } else { a }));
        self.weights.extend(scaled);
    }

    fn codebook_f32(&self) -> Option<&[f32]> {
        match &self.codebook {
            StoredVectors::F32(v) => Some(v),
            _ => None,
        }
    }

    /// Row `i` reconstructed (`[D]`, unit norm unless the row is zero), `None` beyond N.
    pub fn row_f32(&self, i: usize) -> Option<Vec<f32>> {
        let book = self.codebook_f32()?;
        let slots = self.atoms.get(i * self.slots..(i + 1) * self.slots)?;
        let weights = self.weights.get(i * self.slots..(i + 1) * self.slots)?;
        let mut out = vec![0.0f32; self.dim];
        for (&a, &w) in slots.iter().zip(weights) {
            let e = &book[a as usize * self.dim..(a as usize + 1) * self.dim];
            out.iter_mut().zip(e).for_each(|(o, &v)| *o += w * v);
        }
        Some(out)
    }

    /// `q_t · E_j` for every codebook row `j` and query `t` (`[A][Q]`), with the dense kernel.
    /// Blocks of [`PROJECT_ROWS`] codebook rows go to the rayon threads.
    pub(super) fn project<const Q: usize>(&self, qs: &kernels::Queries<'_, Q>) -> Vec<[f32; Q]> {
        use rayon::prelude::*;
        let a = self.atoms_in_codebook;
        let mut proj = vec![[0.0f32; Q]; a];
        proj.par_chunks_mut(PROJECT_ROWS)
            .enumerate()
            .for_each(|(b, out)| {
                let start = b * PROJECT_ROWS;
                let end = start + out.len();
                kernels::scan_chunk::<Q>(
                    &self.codebook,
                    kernels::RowSpan {
                        d: self.dim,
                        start,
                        end,
                        keep: None,
                    },
                    qs,
                    out,
                );
            });
        proj
    }

    /// Scores rows `start..end` into `out[r]` (row `start + r`) from the codebook projections
    /// `proj` ([`MixtureRows::project`]): `S` multiply-adds per row and query. Rows with
    /// `keep(i)` false are left untouched.
    pub(super) fn scan_chunk<const Q: usize>(
        &self,
        proj: &[[f32; Q]],
        start: usize,
        end: usize,
        keep: Option<kernels::Keep<'_>>,
        out: &mut [[f32; Q]],
    ) {
        let s = self.slots;
        let atoms = self.atoms[start * s..end * s].chunks_exact(s);
        let weights = self.weights[start * s..end * s].chunks_exact(s);
        for (r, ((a, w), o)) in atoms.zip(weights).zip(out.iter_mut()).enumerate() {
            if keep.is_some_and(|k| !k(start + r)) {
                continue;
            }
            let mut acc = [0.0f32; Q];
            for (&a, &w) in a.iter().zip(w) {
                // Atoms were checked against the codebook on push.
                let p = &proj[a as usize];
                for t in 0..Q {
                    acc[t] += w * p[t];
                }
            }
            *o = acc;
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::super::synthetic::{random_centres, synthetic_mixture};
    use super::super::{ScanRequest, VectorStore, lerf_relevancy, scan};
    use slag_common::Error;

    #[test]
    fn mixture_scans_equal_the_reference_and_a_dense_copy() {
        let (n, dim, slots, clusters) = (5000, 24, 3, 8);
        let centres = random_centres(dim, clusters, 3);
        let store = synthetic_mixture(n, dim, 64, slots, &centres, clusters, 9).unwrap();
        assert!(store.is_mixture());
        let m = store.mixture().unwrap();
        assert_eq!((m.len(), m.slots(), m.atoms_in_codebook()), (n, slots, 64));
        // Every score is the cosine of the row's reconstruction (unit after the norm scaling).
        let q: Vec<f32> = centres[..dim].to_vec();
        let qs = [q.as_slice()];
        let hits = scan(&store, &ScanRequest::top_k(&qs, n)).unwrap();
        assert_eq!(hits.len(), n);
        for h in &hits {
            let row = store.row_f32(h.row).unwrap();
            let norm = row.iter().map(|x| x * x).sum::<f32>().sqrt();
            assert!((norm - 1.0).abs() < 1e-5, "row {} norm {norm}", h.row);
            let want: f32 = row.iter().zip(&q).map(|(a, b)| a * b).sum();
            assert!((h.score - want).abs() < 1e-5, "{} vs {want}", h.score);
        }
        // Threshold, box and a combiner select as on a dense f32 copy of the same rows.
        let mut dense = VectorStore::new(dim, slag_common::shards::Dtype::F32).unwrap();
        let flat: Vec<f32> = (0..n).flat_map(|i| store.row_f32(i).unwrap()).collect();
        dense
            .push_f32_rows(store.ids(), store.means(), &flat)
            .unwrap();
        let neg: Vec<f32> = centres[dim..2 * dim].to_vec();
        let q2 = [q.as_slice(), neg.as_slice()];
        let reqs = [
            ScanRequest::threshold(&qs, 0.28),
            ScanRequest {
                bbox: Some(([-20.0; 3], [10.0; 3])),
                ..ScanRequest::top_k(&qs, 300)
            },
            ScanRequest {
                combine: Some(&lerf_relevancy),
                ..ScanRequest::top_k(&q2, 200)
            },
        ];
        for req in &reqs {
            let a = scan(&store, req).unwrap();
            let b = scan(&dense, req).unwrap();
            assert!(
                a.len().abs_diff(b.len()) <= 1,
                "{req:?}: {} vs {}",
                a.len(),
                b.len()
            );
            for (x, y) in a.iter().zip(&b) {
                assert!((x.score - y.score).abs() < 1e-5, "{req:?}");
            }
        }
        assert_eq!(store.bytes_per_gaussian(), 8 * slots + 16);
    }

    #[test]
    fn foreign_shards_are_refused_and_leave_the_store_unchanged() {
        use slag_common::shards::{
            Aabb, Dtype, MIXTURE_SHARD_FORMAT_VERSION, MixtureShard, ShardHeader,
        };
        let book = vec![1.0, 0.0, 0.0, 1.0];
        let mut store = VectorStore::new_mixture(2, 2, book, 0xabc).unwrap();
        let shard = |atoms: Vec<u32>, crc: u32| MixtureShard {
            header: ShardHeader {
                version: MIXTURE_SHARD_FORMAT_VERSION,
                scene_id: "s".into(),
                model: "m".into(),
                dim: 2,
                dtype: Dtype::F16,
                count: 1,
                aabb: Aabb::default(),
                tile_id: 4,
            },
            slots: 2,
            codebook_crc: crc,
            ids: vec![7],
            means: vec![[0.0; 3]],
            atoms,
            weights: vec![half::f16::from_f32(0.6), half::f16::from_f32(0.8)],
            scales: None,
            opacities: None,
            rotations: None,
            sh_dc: None,
            segments: None,
        };
        assert!(matches!(
            store.push_mixture_shard(shard(vec![0, 1], 0xdef)),
            Err(Error::Mismatch { .. })
        ));
        assert!(matches!(
            store.push_mixture_shard(shard(vec![0, 2], 0xabc)),
            Err(Error::Format { .. })
        ));
        assert!(store.is_empty());
        store.push_mixture_shard(shard(vec![0, 1], 0xabc)).unwrap();
        // 0.6·e0 + 0.8·e1 has norm 1 (up to f16): its cosine with e1 is 0.8.
        let q = [0.0f32, 1.0];
        let qs = [q.as_slice()];
        let h = scan(&store, &ScanRequest::top_k(&qs, 1)).unwrap();
        assert!((h[0].score - 0.8).abs() < 1e-3, "{h:?}");
        // A dense store refuses mixture rows, a mixture store dense ones.
        let mut dense = VectorStore::new(2, Dtype::F16).unwrap();
        assert!(matches!(
            dense.push_mixture_shard(shard(vec![0, 1], 0xabc)),
            Err(Error::Mismatch { .. })
        ));
        assert!(matches!(
            store.push_f32_rows(&[1], &[[0.0; 3]], &[1.0, 0.0]),
            Err(Error::Mismatch { .. })
        ));
        assert!(VectorStore::new_mixture(2, 2, vec![1.0; 3], 0).is_err());
    }
}
