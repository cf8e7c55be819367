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
        if dim == 0 || slots == 0 || codebook.is_empty() || codebook.len() % dim != 0 {
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
        let (dim, slots) = (self.dim, self.slots);
        let mut scaled = Vec::with_capacity(s.weights.len());
        for (a, w) in s.atoms.chunks_exact(slots).zip(s.weights.chunks_exact(slots)) {
            let norm = row_norm(book, dim, a, w.iter().map(|x| x.to_f32()));
            let inv = if norm > 0.0 { norm.recip() } else { 0.0 };
            scaled.extend(w.iter().map(|x| x.to_f32() * inv));
        }
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
                kernels::scan_chunk::<Q>(&self.codebook, self.dim, start, end, qs, None, out);
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
