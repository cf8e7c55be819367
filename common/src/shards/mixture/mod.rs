//! Mixture shards and the scene codebook: the compressed form of [`crate::mixture`] cut into
//! spatial shards.
//!
//! A mixture scene stores every Gaussian as `S` `(codebook row, weight)` slots over one shared
//! codebook of mask embeddings (`A × D`), instead of a dense `D`-vector. Its shards are format
//! version [`MIXTURE_SHARD_FORMAT_VERSION`] (header in [`super::format`]: version 1's fields, dtype
//! f16 for the weights, plus slots `S` and the CRC-32 of the codebook file at offset 72); the
//! payload, little-endian, 4-byte aligned sections:
//!
//! 1. Gaussian ids `u32[N]` (index in the source `.ply`);
//! 2. means `f32[N][3]` (world frame, scene units);
//! 3. atoms `u32[N][S]`: codebook row of each slot, [`UNUSED`] for an empty slot;
//! 4. weights `f16[N][S]` (0 in empty slots), then zero padding to a 4-byte boundary;
//! 5. the display sections of version 1 (flag bits 0–3), unchanged;
//! 6. with segments (format version [`MIXTURE_SEGMENTS_SHARD_FORMAT_VERSION`], flag bit 4): the
//!    scene-wide segment id of each Gaussian `u32[N]` ([`crate::segments`]), as in a dense
//!    version-3 shard. Without segments the shard stays version 2, byte for byte.
//!
//! A Gaussian's embedding is `v = Σ_s weights[s] · codebook[atoms[s]]`; its cosine with a query
//! `q` is `(Σ_s weights[s] · (q·codebook[atoms[s]])) / ‖v‖`, so a query costs one dot product per
//! codebook row and `S` multiply-adds per Gaussian.
//!
//! The codebook is one file per scene (listed in the manifest, [`super::MixtureInfo`], with its
//! size and CRC-32 like a shard): a version-1 dense f16 shard of `A` rows whose tile id is
//! [`CODEBOOK_TILE`], ids `0..A` and zero means ([`encode_codebook`] / [`decode_codebook`]). It
//! reuses the shard container, so its bytes are checked by the same (fuzzed) decoder; each
//! mixture shard names the codebook's checksum in its header, so a shard is never read against
//! another partition's codebook.

use half::f16;

use super::format::{
    Dtype, F16_MAX, MIXTURE_SEGMENTS_SHARD_FORMAT_VERSION, MIXTURE_SHARD_FORMAT_VERSION,
    RowSection, ShardError, ShardHeader, ShardInput, ShardLayout, decode_shard_stored,
    decoded_shard, encode_shard, header_len_for, parse_header, payload_with_rows, put_le,
    read_f16s, read_payload, read_u32s, rows_within, shard_input,
};
use crate::Error;

pub use super::format::MAX_SLOTS;
pub use crate::mixture::UNUSED;

/// Tile id of the codebook file (no spatial tile has it: partition numbers tiles from 0).
pub const CODEBOOK_TILE: u64 = u64::MAX;

shard_input! {
    /// Borrowed content of one mixture shard ([`encode_mixture_shard`]). `Default`: no rows, no
    /// optional sections, `dim` and `slots` 0 (set them).
    #[derive(Debug, Clone, Copy, Default)]
    pub struct MixtureShardInput<'a> {
        header {
            /// Slots per Gaussian S (1..=[`MAX_SLOTS`]).
            pub slots: usize,
            /// CRC-32 of the scene's codebook file ([`super::shard_checksum`] of
            /// [`encode_codebook`]'s bytes).
            pub codebook_crc: u32,
        }
        rows {
            /// `[N * S]` codebook rows, [`UNUSED`] for an empty slot.
            pub atoms: &'a [u32],
            /// `[N * S]` weights (stored as f16, rounded to nearest), 0 in empty slots.
            pub weights: &'a [f32],
        }
    }
}

decoded_shard! {
    /// A decoded mixture shard ([`decode_mixture_shard`]): rows as stored.
    #[derive(Debug, Clone, PartialEq)]
    pub struct MixtureShard {
        header {
            /// Header fields (`version` = [`MIXTURE_SHARD_FORMAT_VERSION`], or
            /// [`MIXTURE_SEGMENTS_SHARD_FORMAT_VERSION`] with segments; `dtype` f16, `dim` = D).
            pub header: ShardHeader,
            /// Slots per Gaussian S.
            pub slots: u32,
            /// CRC-32 of the codebook file these rows index.
            pub codebook_crc: u32,
        }
        rows {
            /// `[N * S]` codebook rows, [`UNUSED`] for an empty slot.
            pub atoms: Vec<u32>,
            /// `[N * S]` weights, finite, 0 in empty slots.
            pub weights: Vec<f16>,
        }
    }
}

/// Payload bytes of the atom and weight sections of `n` rows of `slots` slots (before padding).
fn mixture_row_bytes(n: u64, slots: u64) -> u64 {
    6 * n * slots
}

/// Encodes one mixture shard (module-doc layout).
///
/// Errors: array lengths that disagree with N and S ([`Error::Internal`]), `dim` outside
/// 1..=[`MAX_DIM`](super::format::MAX_DIM) or `slots` outside 1..=[`MAX_SLOTS`]
/// ([`Error::Param`]), N above `u32::MAX` ([`Error::Limit`]), ids longer than 65535 bytes,
/// non-finite means or weights, a weight beyond the f16 range, or an empty slot with a non-zero
/// weight ([`Error::Invalid`]).
pub fn encode_mixture_shard(input: &MixtureShardInput<'_>) -> crate::Result<Vec<u8>> {
    let columns = input.columns("encode_mixture_shard");
    columns.check_shape()?;
    let (n, s) = (input.ids.len(), input.slots);
    if s == 0 || s > MAX_SLOTS as usize {
        return Err(Error::param(
            "mixture_slots",
            s,
            format!("1..={MAX_SLOTS} slots per Gaussian"),
        ));
    }
    if input.means.len() != n || input.atoms.len() != n * s || input.weights.len() != n * s {
        return Err(Error::internal(format!(
            "encode_mixture_shard: {n} ids but {} means, {} atoms and {} weights for {s} slots",
            input.means.len(),
            input.atoms.len(),
            input.weights.len()
        )));
    }
    columns.check_columns()?;
    let bad = |m: String| Error::Invalid(format!("encode_mixture_shard: {m}"));
    for (&a, &w) in input.atoms.iter().zip(input.weights) {
        if !f16::from_f32(w).is_finite() {
            return Err(bad(format!(
                "weight {w} is not a finite f16 value (±{F16_MAX})"
            )));
        }
        if a == UNUSED && w != 0.0 {
            return Err(bad(format!("an empty slot carries weight {w}")));
        }
    }
    let rows = RowSection {
        dtype: Dtype::F16,
        versions: [
            MIXTURE_SHARD_FORMAT_VERSION,
            MIXTURE_SEGMENTS_SHARD_FORMAT_VERSION,
        ],
        mixture: Some((s as u32, input.codebook_crc)),
        bytes_per_row: 6 * s,
    };
    Ok(columns.encode(&rows, |p| {
        put_le(p, input.atoms, u32::to_le_bytes);
        input
            .weights
            .iter()
            .for_each(|&w| p.extend_from_slice(&f16::from_f32(w).to_le_bytes()));
    }))
}

/// Decodes a mixture shard, verifying magic, version, both CRCs and every length, and that each
/// weight is finite and each empty slot weighs 0. Atom indices are checked against the codebook
/// by the reader that holds it (the edge store).
///
/// Errors: [`ShardError`] for any truncated, corrupted, foreign or inconsistent input, including
/// a dense (version 1) shard ([`ShardError::Malformed`]); never panics and never allocates more
/// than the input length implies.
pub fn decode_mixture_shard(bytes: &[u8]) -> Result<MixtureShard, ShardError> {
    let parsed = parse_header(bytes)?;
    let Some((slots, codebook_crc)) = parsed.mixture else {
        return Err(ShardError::Malformed(format!(
            "a dense shard (format version {}) where a mixture shard was expected; the manifest \
             and its shards disagree, fetch again",
            parsed.header.version
        )));
    };
    let n = parsed.header.count as u64;
    let expected = payload_with_rows(parsed.flags, n, mixture_row_bytes(n, slots as u64));
    let what = || format!("{n} Gaussians of {slots} mixture slots");
    let s = slots as usize;
    let (ids, means, (atoms, weights), display) =
        read_payload(bytes, &parsed, expected, what, |r, n| {
            let atoms = read_u32s(r, n * s)?;
            Ok((atoms, read_f16s(r, n * s)?))
        })?;
    for (&a, &w) in atoms.iter().zip(&weights) {
        if !w.is_finite() {
            return Err(ShardError::Malformed(format!(
                "mixture weight {w} is not finite"
            )));
        }
        if a == UNUSED && w != f16::ZERO && w != f16::NEG_ZERO {
            return Err(ShardError::Malformed(format!(
                "an empty mixture slot carries weight {w}"
            )));
        }
    }
    Ok(MixtureShard {
        header: parsed.header,
        slots,
        codebook_crc,
        ids,
        means,
        atoms,
        weights,
        scales: display.scales,
        opacities: display.opacities,
        rotations: display.rotations,
        sh_dc: display.sh_dc,
        segments: display.segments,
    })
}

/// Size model of the mixture shards of one partition (the mixture counterpart of
/// [`ShardLayout`]): exact byte lengths from N, so tiles can be capped in bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MixtureLayout {
    /// Display sections and string lengths, as for dense shards (its `dtype` and `dim` are not
    /// used: a mixture row's size does not depend on D).
    pub base: ShardLayout,
    /// Slots per Gaussian S.
    pub slots: usize,
}

impl MixtureLayout {
    /// Header bytes (80 fixed + ids + CRC, padded to a multiple of 8).
    pub fn header_len(&self) -> u64 {
        header_len_for(self.base.scene_id_len, self.base.model_len, true) as u64
    }

    /// Payload bytes per Gaussian: id (4) + mean (12) + `6 · S` (u32 atom + f16 weight per slot)
    /// + the optional display sections.
    pub fn bytes_per_row(&self) -> u64 {
        let dense =
            self.base.bytes_per_row() - self.base.dtype.bytes_per_vector(self.base.dim) as u64;
        dense + 6 * self.slots as u64
    }

    /// Exact byte length of a mixture shard of `n` Gaussians, as [`encode_mixture_shard`] writes
    /// it. Saturates instead of overflowing for absurd `n`.
    pub fn shard_len(&self, n: u64) -> u64 {
        let n = n.min(u64::MAX / (64 + 6 * self.slots as u64));
        self.header_len()
            + payload_with_rows(
                self.base.flags(),
                n,
                mixture_row_bytes(n, self.slots as u64),
            )
    }

    /// Largest N (≤ `u32::MAX`) whose shard fits in `max_bytes`; 0 when not even one fits.
    pub fn max_rows_within(&self, max_bytes: u64) -> u64 {
        rows_within(self.header_len(), self.bytes_per_row(), max_bytes, |n| {
            self.shard_len(n)
        })
    }
}

/// A scene's codebook as read from its file ([`decode_codebook`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Codebook {
    /// Scene id.
    pub scene_id: String,
    /// Embedding model id.
    pub model: String,
    /// Embedding width D.
    pub dim: usize,
    /// `[A * D]` row-major mask embeddings (f16 values held as f32).
    pub rows: Vec<f32>,
}

impl Codebook {
    /// Number of codebook rows A.
    pub fn len(&self) -> usize {
        self.rows.len().checked_div(self.dim).unwrap_or(0)
    }
    /// True when the codebook has no row.
    pub fn is_empty(&self) -> bool {
        self.rows.is_empty()
    }
}

/// Encodes a scene's codebook file (module doc): `rows` is `[A * D]` row-major, stored as f16.
///
/// Errors: as [`encode_shard`] (a value beyond the f16 range, non-finite values, `dim` out of
/// range, more than `u32::MAX` rows).
pub fn encode_codebook(
    scene_id: &str,
    model: &str,
    dim: usize,
    rows: &[f32],
) -> crate::Result<Vec<u8>> {
    let a = rows.len().checked_div(dim).unwrap_or(0);
    if dim == 0 || a * dim != rows.len() {
        return Err(Error::internal(format!(
            "encode_codebook: {} values are not rows of width {dim}",
            rows.len()
        )));
    }
    let a32 =
        u32::try_from(a).map_err(|_| Error::limit(crate::Resource::ShardGaussians, a, u32::MAX))?;
    let ids: Vec<u32> = (0..a32).collect();
    encode_shard(&ShardInput {
        scene_id,
        model,
        tile_id: CODEBOOK_TILE,
        dim,
        dtype: Dtype::F16,
        ids: &ids,
        means: &vec![[0.0; 3]; a],
        vectors: rows,
        ..ShardInput::default()
    })
}

/// Decodes and checks a codebook file: a valid f16 shard ([`decode_shard_stored`]) with tile id
/// [`CODEBOOK_TILE`], ids `0..A` in order, no display sections, and finite values.
///
/// Errors: [`ShardError`] (any decoding error, or [`ShardError::Malformed`] naming what makes
/// it no codebook).
pub fn decode_codebook(bytes: &[u8]) -> Result<Codebook, ShardError> {
    let s = decode_shard_stored(bytes)?;
    let h = &s.header;
    let not = |m: String| Err(ShardError::Malformed(format!("not a slag codebook: {m}")));
    if h.tile_id != CODEBOOK_TILE {
        return not(format!("tile id {} (a shard, not the codebook)", h.tile_id));
    }
    if h.dtype != Dtype::F16 {
        return not(format!("dtype {:?}, codebooks are f16", h.dtype));
    }
    if s.scales.is_some()
        || s.opacities.is_some()
        || s.rotations.is_some()
        || s.sh_dc.is_some()
        || s.segments.is_some()
    {
        return not("it carries display or segment sections".into());
    }
    if s.ids.iter().enumerate().any(|(i, &id)| id as usize != i) {
        return not("row ids are not 0..A in order".into());
    }
    let rows = match s.vectors {
        super::StoredVectors::F16(v) => v.iter().map(|x| x.to_f32()).collect::<Vec<f32>>(),
        _ => return not("vectors are not f16".into()),
    };
    if rows.iter().any(|x| !x.is_finite()) {
        return not("a non-finite value".into());
    }
    Ok(Codebook {
        scene_id: s.header.scene_id.clone(),
        model: s.header.model.clone(),
        dim: s.header.dim as usize,
        rows,
    })
}

#[cfg(test)]
mod tests;
