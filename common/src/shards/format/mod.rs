//! The shard file: one spatial tile of per-Gaussian embeddings, self-describing and checksummed.
//!
//! # Byte layout (format version 1)
//!
//! All integers and floats are **little-endian**. The header length is a multiple of 8 and every
//! payload section starts on a 4-byte boundary relative to the start of the shard, so a reader
//! that maps the shard at an 8-aligned address can view each section in place as `u32`/`f32`.
//!
//! Header (`header_len` bytes):
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 8 | magic `b"SLAGSHRD"` |
//! | 8 | 2 | format version `u16` (= [`SHARD_FORMAT_VERSION`]) |
//! | 10 | 1 | dtype `u8`: 0 = f32, 1 = f16, 2 = int8 with per-vector scale |
//! | 11 | 1 | flags `u8`: bit 0 = scales, bit 1 = opacities, bit 2 = rotations, bit 3 = SH DC present; others must be 0 |
//! | 12 | 4 | embedding dim `D` `u32` |
//! | 16 | 4 | Gaussian count `N` `u32` |
//! | 20 | 4 | `header_len` `u32` (offset of the payload; multiple of 8) |
//! | 24 | 8 | tile id `u64` |
//! | 32 | 24 | AABB of the means: `min[3]`, `max[3]` as `f32`, world frame, scene units |
//! | 56 | 8 | payload length in bytes `u64` |
//! | 64 | 4 | CRC-32 (IEEE, `crc32fast`) of the payload |
//! | 68 | 2 | scene id length `S` `u16` |
//! | 70 | 2 | embedding model id length `M` `u16` |
//! | 72 | S | scene id, UTF-8 |
//! | 72+S | M | model id, UTF-8 |
//! | … | | zero padding up to `header_len - 4` |
//! | `header_len-4` | 4 | CRC-32 of header bytes `[0, header_len-4)` |
//!
//! Payload (`payload_len` bytes, starting at `header_len`), sections in this order:
//!
//! 1. Gaussian ids `u32[N]` (index in the source `.ply`);
//! 2. means `f32[N][3]` (world frame, scene units);
//! 3. int8 only: per-vector scales `f32[N]`;
//! 4. embeddings `[N][D]`: `f32`, `f16` (IEEE half), or `i8` (value = `q * scale[i]`),
//!    followed by zero padding to a 4-byte boundary;
//! 5. if flag bit 0: Gaussian scales `f32[N][3]` (log-scale as in the INRIA `.ply`, for display);
//! 6. if flag bit 1: opacities `f32[N]` (pre-sigmoid as in the INRIA `.ply`, for display);
//! 7. if flag bit 2: rotations `f32[N][4]`, quaternions (w, x, y, z) as `rot_0..3` of the INRIA
//!    `.ply`, **normalised** (as [`crate::scene::load_ply`] returns them), for display;
//! 8. if flag bit 3: SH DC colour `f32[N][3]` (`f_dc_0..2` of the INRIA `.ply`:
//!    `rgb = 0.5 + SH_C0 * f_dc`), for display.
//!
//! Bits 2 and 3 were added within version 1: every section is optional and appended after the
//! older ones, so shards without them are byte-identical to before. A reader that predates them
//! rejects a shard carrying them with [`ShardError::Malformed`] `"unknown flags 0x0c"` (it checks
//! the flags before the payload length): upgrade slag-edge, or re-partition without
//! `--display-ply`.
//!
//! **Version 2** ([`MIXTURE_SHARD_FORMAT_VERSION`], mixture shards only, layout in
//! [`super::mixture`]): the same header with dtype 1 (f16: the weights) and 8 more bytes at
//! offset 72 (slots `S` `u32`, CRC-32 of the scene's codebook file `u32`) before the strings; the
//! payload holds ids, means, atom indices `u32[N][S]` and weights `f16[N][S]` (padded to 4 bytes)
//! in place of the embeddings, then the same display sections. Dense shards stay version 1,
//! byte for byte; the dense decoders refuse a version-2 shard with [`ShardError::MixtureRows`].
//!
//! **Version 3** ([`SEGMENTS_SHARD_FORMAT_VERSION`], dense shards with geometric segments):
//! version 1's header and payload with flag bit 4 set (required at version 3, refused at 1
//! and 2) and one more section after the display sections: 9. segment ids `u32[N]`, the
//! scene-wide segment of each Gaussian ([`crate::segments`]). Dense shards without segments
//! stay version 1, byte for byte; readers before version 3 refuse a version-3 shard with
//! [`ShardError::UnsupportedVersion`] (upgrade slag-edge, or re-partition with segments off).
//!
//! **Version 4** ([`MIXTURE_SEGMENTS_SHARD_FORMAT_VERSION`], mixture shards with geometric
//! segments): version 2's header and payload with flag bit 4 set (required at version 4) and the
//! same segment-id section 9 after the display sections. Mixture shards without segments stay
//! version 2, byte for byte; readers before version 4 refuse a version-4 shard with
//! [`ShardError::UnsupportedVersion`].
//!
//! The file is exactly `header_len + payload_len` bytes; trailing bytes are an error. The
//! checksum a server publishes for a whole shard (manifest, HTTP `ETag`) is [`shard_checksum`],
//! the CRC-32 of all its bytes.

mod columns;
mod header;

use half::f16;

use crate::Error;
pub use columns::DisplaySlices;
pub(super) use columns::{
    RowSection, ShardColumns, decoded_shard, put_le, read_f16s, read_payload, read_u32s,
    shard_input,
};
use header::le_f32s;
pub(super) use header::{header_len_for, parse_header};

/// Magic bytes opening every shard.
pub const SHARD_MAGIC: [u8; 8] = *b"SLAGSHRD";
/// Shard format version of dense shards (f32 / f16 / int8 rows), written by [`encode_shard`].
pub const SHARD_FORMAT_VERSION: u16 = 1;
/// Shard format version of *mixture* shards (codebook atom indices and weights per row instead
/// of dense vectors, [`super::mixture`]): version 1's header plus 8 bytes (slots, codebook
/// checksum). Only mixture shards carry it, so dense shards are byte-identical to before.
pub const MIXTURE_SHARD_FORMAT_VERSION: u16 = 2;
/// Shard format version of dense shards that carry segment ids (flag bit 4, section 9 of the
/// module doc), written by [`encode_shard`] when [`ShardInput::segments`] is given. Dense shards
/// without segments stay version 1.
pub const SEGMENTS_SHARD_FORMAT_VERSION: u16 = 3;
/// Shard format version of *mixture* shards that carry segment ids (version 2's layout with flag
/// bit 4 and section 9), written by `encode_mixture_shard` when its input has segments. Mixture
/// shards without segments stay version 2.
pub const MIXTURE_SEGMENTS_SHARD_FORMAT_VERSION: u16 = 4;
/// Newest shard format version this crate reads.
pub const NEWEST_SHARD_FORMAT_VERSION: u16 = MIXTURE_SEGMENTS_SHARD_FORMAT_VERSION;

/// Whether shards of format `version` hold codebook mixture rows (versions 2 and 4).
pub fn is_mixture_version(version: u16) -> bool {
    version == MIXTURE_SHARD_FORMAT_VERSION || version == MIXTURE_SEGMENTS_SHARD_FORMAT_VERSION
}

/// Whether shards of format `version` carry segment ids (versions 3 and 4).
pub fn has_segments_version(version: u16) -> bool {
    version == SEGMENTS_SHARD_FORMAT_VERSION || version == MIXTURE_SEGMENTS_SHARD_FORMAT_VERSION
}
/// Largest embedding width accepted when decoding (guards allocations on corrupted input).
pub const MAX_DIM: u32 = 1 << 16;
/// Most slots per Gaussian a mixture shard may hold (guards allocations on corrupted input; the
/// encoder keeps 16 at most in practice).
pub const MAX_SLOTS: u32 = 256;
pub(super) const FIXED_HEADER: usize = 72;
/// Largest `header_len` the decoders accept (bytes): writers pad the header to a multiple of 8
/// only, readers allow up to this much.
pub(super) const MAX_HEADER_LEN: usize = 1 << 20;
/// Bytes the mixture header (version 2) adds after the fixed header: slots `u32`, codebook
/// checksum `u32`.
pub(super) const MIXTURE_HEADER_EXTRA: usize = 8;
pub(super) const FLAG_SCALES: u8 = 1;
pub(super) const FLAG_OPACITIES: u8 = 2;
pub(super) const FLAG_ROTATIONS: u8 = 4;
pub(super) const FLAG_SH_DC: u8 = 8;
pub(super) const KNOWN_FLAGS: u8 = FLAG_SCALES | FLAG_OPACITIES | FLAG_ROTATIONS | FLAG_SH_DC;
/// Segment ids present (version 3 only, where it is required).
pub(super) const FLAG_SEGMENTS: u8 = 16;

/// Storage type of the embedding vectors in a shard.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Hash, Default, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum Dtype {
    /// IEEE single precision, 4 bytes per component (exact).
    F32,
    /// IEEE half precision, 2 bytes per component (absolute error ≤ ~5e-4 for unit vectors).
    #[default]
    F16,
    /// Symmetric int8 per vector: `q = round(v / s)`, `s = max|v| / 127`; 1 byte per component
    /// plus one `f32` scale per vector (absolute error ≤ `s / 2`).
    I8,
}

impl Dtype {
    /// Code stored in the header.
    pub fn code(self) -> u8 {
        match self {
            Dtype::F32 => 0,
            Dtype::F16 => 1,
            Dtype::I8 => 2,
        }
    }
    /// Inverse of [`Dtype::code`].
    pub fn from_code(code: u8) -> Option<Dtype> {
        match code {
            0 => Some(Dtype::F32),
            1 => Some(Dtype::F16),
            2 => Some(Dtype::I8),
            _ => None,
        }
    }
    /// Bytes used per vector of width `dim` (including the int8 scale).
    pub fn bytes_per_vector(self, dim: usize) -> usize {
        match self {
            Dtype::F32 => 4 * dim,
            Dtype::F16 => 2 * dim,
            Dtype::I8 => dim + 4,
        }
    }
}

impl std::str::FromStr for Dtype {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self, Error> {
        match s.to_ascii_lowercase().as_str() {
            "f32" => Ok(Dtype::F32),
            "f16" => Ok(Dtype::F16),
            "i8" | "int8" => Ok(Dtype::I8),
            _ => Err(Error::param("dtype", format!("{s:?}"), "f32, f16 or int8")),
        }
    }
}

/// An axis-aligned box, world frame, scene units.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct Aabb {
    /// Smallest x, y, z.
    pub min: [f32; 3],
    /// Largest x, y, z.
    pub max: [f32; 3],
}

impl Aabb {
    /// Tight box of `points`; `None` when empty.
    pub fn of_points(points: impl IntoIterator<Item = [f32; 3]>) -> Option<Aabb> {
        let mut it = points.into_iter();
        let first = it.next()?;
        let mut b = Aabb {
            min: first,
            max: first,
        };
        for p in it {
            for (a, v) in p.iter().enumerate() {
                b.min[a] = b.min[a].min(*v);
                b.max[a] = b.max[a].max(*v);
            }
        }
        Some(b)
    }
}

/// Decoding failure of a shard. Never a panic: every malformed input maps to one of these.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ShardError {
    /// Fewer bytes than the header or payload lengths require.
    #[error("shard truncated: {needed} bytes needed, {got} present; re-download the shard")]
    Truncated {
        /// Bytes the header says the shard has (or the fixed header size).
        needed: u64,
        /// Bytes present.
        got: u64,
    },
    /// The first 8 bytes are not [`SHARD_MAGIC`].
    #[error("not a slag shard (bad magic); pass a file produced by slag-encoder partition/export")]
    BadMagic,
    /// A format version this crate does not read.
    #[error(
        "shard format version {0}, this slag reads 1 to {NEWEST_SHARD_FORMAT_VERSION}; upgrade slag or re-export"
    )]
    UnsupportedVersion(u16),
    /// A stored CRC-32 does not match the bytes.
    #[error(
        "shard {section} checksum mismatch (stored {stored:08x}, computed {computed:08x}); the shard is corrupted, re-download it"
    )]
    Checksum {
        /// `"header"` or `"payload"`.
        section: &'static str,
        /// CRC stored in the shard.
        stored: u32,
        /// CRC of the bytes present.
        computed: u32,
    },
    /// A field is out of range or inconsistent (dtype code, flags, lengths, UTF-8 strings).
    #[error("malformed shard: {0}")]
    Malformed(String),
    /// A valid mixture shard (format version [`MIXTURE_SHARD_FORMAT_VERSION`]) handed to a dense
    /// decoder ([`decode_shard`], [`decode_shard_stored`]): its rows are codebook mixtures, not
    /// vectors.
    #[error(
        "shard of tile {tile_id} holds codebook mixture rows (format version 2), not dense \
         vectors; read it with its scene's codebook (decode_mixture_shard), or re-partition the \
         dense embeddings"
    )]
    MixtureRows {
        /// Tile id from the header.
        tile_id: u64,
    },
    /// A manifest whose tiles are not a set that adds up ([`super::Manifest::check_set`]): a
    /// tile id listed twice, a tile with the codebook's id, Gaussian counts whose sum is not the
    /// manifest's total, or (found when the shards are loaded) a Gaussian id in two shards. The
    /// message names where the manifest came from and the rule it breaks.
    #[error(
        "manifest is not a set of tiles: {0}; nothing of it is stored or served: re-partition \
         the scene on the shard server (slag-encoder partition), then fetch again"
    )]
    ManifestNotASet(String),
}

/// Everything the shard header says about its payload.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ShardHeader {
    /// Format version ([`SHARD_FORMAT_VERSION`]).
    pub version: u16,
    /// Scene id (same as in the manifest).
    pub scene_id: String,
    /// Embedding model id (CLIP visual model, [`crate::embeddings::Embeddings::model`]).
    pub model: String,
    /// Embedding width D.
    pub dim: u32,
    /// Storage type of the vectors.
    pub dtype: Dtype,
    /// Number of Gaussians N.
    pub count: u32,
    /// Box of the means, world frame.
    pub aabb: Aabb,
    /// Tile id (as in the manifest).
    pub tile_id: u64,
}

decoded_shard! {
    /// A decoded shard: the Gaussians of one tile. Vectors are held as f32 (dequantised).
    #[derive(Debug, Clone, PartialEq)]
    pub struct Shard {
        header {
            /// Header fields.
            pub header: ShardHeader,
        }
        rows {
            /// `[N * D]` row-major embeddings, dequantised to f32.
            pub vectors: Vec<f32>,
        }
    }
}

impl Shard {
    /// Row `i` of the embedding matrix.
    pub fn vector(&self, i: usize) -> &[f32] {
        let d = self.header.dim as usize;
        &self.vectors[i * d..(i + 1) * d]
    }
}

shard_input! {
    /// Borrowed content to encode into one shard (see [`encode_shard`]). `Default`: no rows, no
    /// optional sections, dtype [`Dtype::F16`], `dim` 0 (set it).
    #[derive(Debug, Clone, Copy, Default)]
    pub struct ShardInput<'a> {
        header {
            /// Storage type to write.
            pub dtype: Dtype,
        }
        rows {
            /// `[N * D]` f32 row-major vectors (normally unit norm; any finite values encode).
            pub vectors: &'a [f32],
        }
    }
}

pub(super) fn align(n: usize, a: usize) -> usize {
    n.div_ceil(a) * a
}

/// Quantises one vector to symmetric int8 and appends the codes to `out`; returns the scale.
///
/// `s = max|v| / 127` (rounded down one f32 step when `127·s` would overflow to infinity),
/// `q = round(v / s)` clamped to `[-127, 127]`; the stored value is `q·s`. Round trip (asserted
/// by `common/tests/stability.rs`): `|v - q·s| ≤ 0.50002·s` per component (`s/2` plus f32
/// rounding), and `q·s` is finite.
///
/// Degenerate inputs give the zero vector (scale 0, all codes 0; cosine 0 with any query), never
/// a NaN: an all-zero vector, and a vector whose largest component is below
/// `127 · f32::MIN_POSITIVE` (≈ 1.5e-36), where `s` would be subnormal and inexact. Non-finite
/// components are not valid input (the callers, [`encode_shard`] and the edge store, reject them
/// with a typed error); if given anyway they are left out of the scale and quantise to 0.
pub fn quantize_i8(v: &[f32], out: &mut Vec<u8>) -> f32 {
    let m = v
        .iter()
        .filter(|x| x.is_finite())
        .fold(0.0f32, |m, x| m.max(x.abs()));
    let scale = if m >= 127.0 * f32::MIN_POSITIVE {
        let s = m / 127.0;
        if (s * 127.0).is_finite() {
            s
        } else {
            f32::from_bits(s.to_bits() - 1)
        }
    } else {
        0.0
    };
    for &x in v {
        let q = if scale > 0.0 && x.is_finite() {
            (x / scale).round().clamp(-127.0, 127.0) as i8
        } else {
            0
        };
        out.push(q as u8);
    }
    scale
}

/// Largest finite IEEE half value; f32 values beyond `F16_MAX` (after rounding) would be stored
/// as infinity.
pub const F16_MAX: f32 = 65504.0;

/// Encodes one shard (layout in the module doc).
///
/// Errors: array lengths that disagree with N and D ([`Error::Internal`]), `dim` of 0 or above
/// [`MAX_DIM`] ([`Error::Param`] `dim`), N above `u32::MAX` ([`Error::Limit`]
/// [`crate::Resource::ShardGaussians`]), scene or model ids longer than 65535 bytes, non-finite
/// means or vectors ([`Error::Invalid`]), and for [`Dtype::F16`] a vector value that rounds
/// beyond the f16 range ([`F16_MAX`]; [`Error::Param`] `dtype`).
/// f16 values are rounded to nearest (subnormal halves below 6.1e-5, zero below 2^-25).
pub fn encode_shard(input: &ShardInput<'_>) -> crate::Result<Vec<u8>> {
    let columns = input.columns("encode_shard");
    columns.check_shape()?;
    let (n, d) = (input.ids.len(), input.dim);
    if input.means.len() != n || input.vectors.len() != n * d {
        return Err(Error::internal(format!(
            "encode_shard: {n} ids but {} means and {} vector values for dim {d}",
            input.means.len(),
            input.vectors.len()
        )));
    }
    columns.check_columns()?;
    if input.vectors.iter().any(|x| !x.is_finite()) {
        return Err(Error::Invalid(
            "encode_shard: non-finite embedding value; fix the encoder output".into(),
        ));
    }
    if input.dtype == Dtype::F16
        && let Some(x) = input
            .vectors
            .iter()
            .find(|&&x| !f16::from_f32(x).is_finite())
    {
        return Err(Error::param(
            "dtype",
            "f16",
            format!(
                "f32 or int8 for the embedding value {x}, beyond the f16 range (±{F16_MAX}), or \
                 L2-normalised vectors (CLIP embeddings are unit vectors)"
            ),
        ));
    }
    let rows = RowSection {
        dtype: input.dtype,
        versions: [SHARD_FORMAT_VERSION, SEGMENTS_SHARD_FORMAT_VERSION],
        mixture: None,
        bytes_per_row: input.dtype.bytes_per_vector(d),
    };
    Ok(columns.encode(&rows, |p| match input.dtype {
        Dtype::F32 => put_le(p, input.vectors, f32::to_le_bytes),
        Dtype::F16 => input
            .vectors
            .iter()
            .for_each(|&x| p.extend_from_slice(&f16::from_f32(x).to_le_bytes())),
        Dtype::I8 => {
            let mut q = Vec::with_capacity(n * d);
            for row in input.vectors.chunks_exact(d) {
                let scale = quantize_i8(row, &mut q);
                p.extend_from_slice(&scale.to_le_bytes());
            }
            p.extend_from_slice(&q);
        }
    }))
}

/// Size model of the shards of one partition: everything that fixes a shard's byte length apart
/// from its Gaussian count N (the header's string lengths and which optional sections it carries).
/// [`ShardLayout::shard_len`] is the exact length [`encode_shard`] writes (module-doc layout), so
/// a partitioner can cap tiles by bytes rather than by Gaussians.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ShardLayout {
    /// Storage type of the vectors.
    pub dtype: Dtype,
    /// Embedding width D.
    pub dim: usize,
    /// Log-scales section present (flag bit 0).
    pub scales: bool,
    /// Opacities section present (flag bit 1).
    pub opacities: bool,
    /// Rotations section present (flag bit 2).
    pub rotations: bool,
    /// SH DC section present (flag bit 3).
    pub sh_dc: bool,
    /// Segment ids present (flag bit 4, version 3).
    pub segments: bool,
    /// Scene id length in bytes (UTF-8).
    pub scene_id_len: usize,
    /// Embedding model id length in bytes (UTF-8).
    pub model_len: usize,
}

impl ShardLayout {
    /// The layout [`encode_shard`] gives `input` (its N aside).
    pub fn of_input(input: &ShardInput<'_>) -> ShardLayout {
        ShardLayout {
            dtype: input.dtype,
            dim: input.dim,
            scales: input.scales.is_some(),
            opacities: input.opacities.is_some(),
            rotations: input.rotations.is_some(),
            sh_dc: input.sh_dc.is_some(),
            segments: input.segments.is_some(),
            scene_id_len: input.scene_id.len(),
            model_len: input.model.len(),
        }
    }

    pub(super) fn flags(&self) -> u8 {
        (if self.scales { FLAG_SCALES } else { 0 })
            | (if self.opacities { FLAG_OPACITIES } else { 0 })
            | (if self.rotations { FLAG_ROTATIONS } else { 0 })
            | (if self.sh_dc { FLAG_SH_DC } else { 0 })
            | (if self.segments { FLAG_SEGMENTS } else { 0 })
    }

    /// Header bytes (`header_len`: 72 fixed + ids + CRC, padded to a multiple of 8).
    pub fn header_len(&self) -> u64 {
        align(FIXED_HEADER + self.scene_id_len + self.model_len + 4, 8) as u64
    }

    /// Payload bytes per Gaussian: id (4) + mean (12) + vector
    /// ([`Dtype::bytes_per_vector`]) + the optional display sections (12 + 4 + 16 + 12). A
    /// shard of N Gaussians is `header_len + N · bytes_per_row` plus 0..=3 bytes of padding
    /// after the embeddings section ([`ShardLayout::shard_len`] is exact).
    pub fn bytes_per_row(&self) -> u64 {
        let mut b = 16 + self.dtype.bytes_per_vector(self.dim) as u64;
        b += if self.scales { 12 } else { 0 };
        b += if self.opacities { 4 } else { 0 };
        b += if self.rotations { 16 } else { 0 };
        b += if self.segments { 4 } else { 0 };
        b + if self.sh_dc { 12 } else { 0 }
    }

    /// Exact byte length of an encoded shard of `n` Gaussians (header + payload), as
    /// [`encode_shard`] writes it and a manifest's `TileInfo::bytes` records it. Saturates
    /// instead of overflowing for absurd `n`.
    pub fn shard_len(&self, n: u64) -> u64 {
        let d = self.dim as u64;
        let n = n.min(u64::MAX / (64 + 4 * d.max(1)));
        self.header_len() + expected_payload(self.dtype, self.flags(), n, d)
    }

    /// Largest N (≤ `u32::MAX`, the format's count field) whose shard fits in `max_bytes`
    /// ([`ShardLayout::shard_len`]`(N) ≤ max_bytes`); 0 when not even one Gaussian fits.
    pub fn max_rows_within(&self, max_bytes: u64) -> u64 {
        rows_within(self.header_len(), self.bytes_per_row(), max_bytes, |n| {
            self.shard_len(n)
        })
    }
}

/// Largest N (≤ `u32::MAX`) with `shard_len(N) ≤ max_bytes`, for a layout of `header` header
/// bytes and `row` payload bytes per Gaussian (`shard_len(n)` ≤ `header + n·row + 3`, the
/// padding); 0 when not even one Gaussian fits. Shared by dense and mixture layouts.
pub(super) fn rows_within(
    header: u64,
    row: u64,
    max_bytes: u64,
    shard_len: impl Fn(u64) -> u64,
) -> u64 {
    let row = row.max(1);
    if max_bytes < shard_len(1) {
        return 0;
    }
    // shard_len(n) ≤ header + n·row + 3, and row ≥ 16 > 3: at most one step down is needed.
    let mut n = ((max_bytes - header) / row).min(u32::MAX as u64);
    while n > 0 && shard_len(n) > max_bytes {
        n -= 1;
    }
    n
}

/// CRC-32 (IEEE) of a whole encoded shard: the checksum the manifest lists and the HTTP `ETag`.
pub fn shard_checksum(bytes: &[u8]) -> u32 {
    crc32fast::hash(bytes)
}

/// Expected payload length for the header fields (u64, overflow-free for u32 N and D ≤ 2^16).
pub(super) fn expected_payload(dtype: Dtype, flags: u8, n: u64, d: u64) -> u64 {
    let vec_bytes = match dtype {
        Dtype::F32 => 4 * n * d,
        Dtype::F16 => 2 * n * d,
        Dtype::I8 => 4 * n + n * d,
    };
    payload_with_rows(flags, n, vec_bytes)
}

/// Payload length of `n` rows whose row section (vectors, or mixture atoms + weights) takes
/// `row_bytes` bytes in all: ids + means + rows, padded to 4, then the flagged display sections.
pub(super) fn payload_with_rows(flags: u8, n: u64, row_bytes: u64) -> u64 {
    let mut len = 4 * n + 12 * n + row_bytes;
    len = len.div_ceil(4) * 4;
    if flags & FLAG_SCALES != 0 {
        len += 12 * n;
    }
    if flags & FLAG_OPACITIES != 0 {
        len += 4 * n;
    }
    if flags & FLAG_ROTATIONS != 0 {
        len += 16 * n;
    }
    if flags & FLAG_SH_DC != 0 {
        len += 12 * n;
    }
    if flags & FLAG_SEGMENTS != 0 {
        len += 4 * n;
    }
    len
}

/// Reads only the header of a shard (validating its CRC), without touching the payload.
pub fn decode_header(bytes: &[u8]) -> Result<ShardHeader, ShardError> {
    parse_header(bytes).map(|h| h.header)
}

/// Embedding rows of a shard as stored (no dequantisation): what a scanner keeps in memory so
/// that an f16 store costs 2 bytes and an int8 store 1 byte (+ one `f32` scale per row) per value.
#[derive(Debug, Clone, PartialEq)]
pub enum StoredVectors {
    /// `[N * D]` row-major `f32`.
    F32(Vec<f32>),
    /// `[N * D]` row-major IEEE half.
    F16(Vec<f16>),
    /// Symmetric int8: value `[i * D + j]` is `q[i * D + j] as f32 * scales[i]` ([`quantize_i8`]).
    I8 {
        /// `[N * D]` row-major quantised values.
        q: Vec<i8>,
        /// `[N]` per-row scales (`max |v| / 127`, `0` for an all-zero row).
        scales: Vec<f32>,
    },
}

impl StoredVectors {
    /// The storage type.
    pub fn dtype(&self) -> Dtype {
        match self {
            StoredVectors::F32(_) => Dtype::F32,
            StoredVectors::F16(_) => Dtype::F16,
            StoredVectors::I8 { .. } => Dtype::I8,
        }
    }
    /// Number of stored values (`N * D`).
    pub fn values(&self) -> usize {
        match self {
            StoredVectors::F32(v) => v.len(),
            StoredVectors::F16(v) => v.len(),
            StoredVectors::I8 { q, .. } => q.len(),
        }
    }
    /// All rows dequantised to `f32`, `[N * D]` row-major.
    pub fn to_f32(&self, dim: usize) -> Vec<f32> {
        match self {
            StoredVectors::F32(v) => v.clone(),
            StoredVectors::F16(v) => v.iter().map(|h| h.to_f32()).collect(),
            StoredVectors::I8 { q, scales } => {
                let mut out = Vec::with_capacity(q.len());
                for (row, s) in q.chunks_exact(dim.max(1)).zip(scales) {
                    out.extend(row.iter().map(|&b| b as f32 * s));
                }
                out
            }
        }
    }
}

decoded_shard! {
    /// A decoded shard with its vectors kept in the stored type ([`decode_shard_stored`]).
    #[derive(Debug, Clone, PartialEq)]
    pub struct StoredShard {
        header {
            /// Header fields.
            pub header: ShardHeader,
        }
        rows {
            /// `[N * D]` embeddings as stored.
            pub vectors: StoredVectors,
        }
    }
}

/// Decodes a shard, verifying magic, version, both CRCs and every length, and dequantises the
/// vectors to `f32` (see [`decode_shard_stored`] to keep them as stored).
///
/// Errors: [`ShardError`] for any truncated, corrupted, foreign or inconsistent input; never
/// panics and never allocates more than the input length implies.
pub fn decode_shard(bytes: &[u8]) -> Result<Shard, ShardError> {
    let s = decode_shard_stored(bytes)?;
    let d = s.header.dim as usize;
    Ok(Shard {
        vectors: s.vectors.to_f32(d),
        header: s.header,
        ids: s.ids,
        means: s.means,
        scales: s.scales,
        opacities: s.opacities,
        rotations: s.rotations,
        sh_dc: s.sh_dc,
        segments: s.segments,
    })
}

/// Decodes a shard like [`decode_shard`] but keeps the embeddings in their stored type.
///
/// Errors: [`ShardError`] for any truncated, corrupted, foreign or inconsistent input.
pub fn decode_shard_stored(bytes: &[u8]) -> Result<StoredShard, ShardError> {
    let parsed = match parse_header(bytes) {
        Ok(p) if p.mixture.is_some() => {
            return Err(ShardError::MixtureRows {
                tile_id: p.header.tile_id,
            });
        }
        Ok(p) => p,
        // A version-2 header that does not parse as one: a version this dense decoder does not
        // read (checked before anything else, as for every other version).
        Err(e) => {
            return Err(match bytes.get(8..10) {
                Some(&[a, b])
                    if bytes.starts_with(&SHARD_MAGIC)
                        && is_mixture_version(u16::from_le_bytes([a, b])) =>
                {
                    ShardError::UnsupportedVersion(u16::from_le_bytes([a, b]))
                }
                _ => e,
            });
        }
    };
    let (dtype, n, d) = (
        parsed.header.dtype,
        parsed.header.count as u64,
        parsed.header.dim,
    );
    let expected = expected_payload(dtype, parsed.flags, n, d as u64);
    let what = || format!("{n} Gaussians of dim {d} ({dtype:?})");
    let d = d as usize;
    let (ids, means, vectors, display) = read_payload(bytes, &parsed, expected, what, |r, n| {
        Ok(match dtype {
            Dtype::F32 => StoredVectors::F32(le_f32s(r.take(4 * n * d)?)),
            Dtype::F16 => StoredVectors::F16(read_f16s(r, n * d)?),
            Dtype::I8 => {
                let scales = le_f32s(r.take(4 * n)?);
                let q = r.take(n * d)?.iter().map(|&b| b as i8).collect();
                StoredVectors::I8 { q, scales }
            }
        })
    })?;
    Ok(StoredShard {
        header: parsed.header,
        ids,
        means,
        vectors,
        scales: display.scales,
        opacities: display.opacities,
        rotations: display.rotations,
        sh_dc: display.sh_dc,
        segments: display.segments,
    })
}

/// `(length, CRC-32 of every byte but the header's own CRC field)` of an encoded shard, for
/// golden tests. (The CRC of a whole shard does not see its header: a CRC over a block that ends
/// with its own CRC is a constant.)
#[cfg(test)]
pub(super) fn fingerprint(bytes: &[u8]) -> (usize, u32) {
    let hl = u32::from_le_bytes([bytes[20], bytes[21], bytes[22], bytes[23]]) as usize;
    let mut h = crc32fast::Hasher::new();
    h.update(&bytes[..hl - 4]);
    h.update(&bytes[hl..]);
    (bytes.len(), h.finalize())
}

/// Asserts that `r` is a checksum error of `section` (`"header"` or `"payload"`).
#[cfg(test)]
pub(super) fn assert_checksum_error<T: std::fmt::Debug>(r: Result<T, ShardError>, section: &str) {
    match r {
        Err(ShardError::Checksum { section: s, .. }) if s == section => {}
        other => panic!("expected a {section} checksum error, got {other:?}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn unit(v: Vec<f32>) -> Vec<f32> {
        let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        if n < 1e-6 {
            v.iter().map(|_| 0.0).collect()
        } else {
            v.iter().map(|x| x / n).collect()
        }
    }

    #[derive(Debug, Clone)]
    struct Case {
        ids: Vec<u32>,
        means: Vec<[f32; 3]>,
        vectors: Vec<f32>,
        dim: usize,
        scales: Option<Vec<[f32; 3]>>,
        opacities: Option<Vec<f32>>,
        rotations: Option<Vec<[f32; 4]>>,
        sh_dc: Option<Vec<[f32; 3]>>,
        scene: String,
        model: String,
        tile: u64,
    }

    prop_compose! {
        fn case()(n in 0usize..20, dim in 1usize..40)(
            ids in proptest::collection::vec(any::<u32>(), n),
            means in proptest::collection::vec(prop::array::uniform3(-1e4f32..1e4), n),
            rows in proptest::collection::vec(proptest::collection::vec(-1.0f32..1.0, dim), n),
            scales in proptest::option::of(proptest::collection::vec(
                prop::array::uniform3(-10f32..3.0),
                n,
            )),
            opacities in proptest::option::of(proptest::collection::vec(-8f32..8.0, n)),
            rotations in proptest::option::of(proptest::collection::vec(
                prop::array::uniform4(-1f32..1.0),
                n,
            )),
            sh_dc in proptest::option::of(proptest::collection::vec(
                prop::array::uniform3(-2f32..2.0),
                n,
            )),
            scene in "[a-z0-9_-]{0,12}",
            model in "\\PC{0,10}",
            tile in any::<u64>(),
            dim in Just(dim),
        ) -> Case {
            let vectors = rows.into_iter().flat_map(unit).collect();
            Case {
                ids,
                means,
                vectors,
                dim,
                scales,
                opacities,
                rotations,
                sh_dc,
                scene,
                model,
                tile,
            }
        }
    }

    fn input(c: &Case, dtype: Dtype) -> ShardInput<'_> {
        ShardInput {
            scene_id: &c.scene,
            model: &c.model,
            tile_id: c.tile,
            dim: c.dim,
            dtype,
            ids: &c.ids,
            means: &c.means,
            vectors: &c.vectors,
            scales: c.scales.as_deref(),
            opacities: c.opacities.as_deref(),
            rotations: c.rotations.as_deref(),
            sh_dc: c.sh_dc.as_deref(),
            segments: None,
        }
    }

    fn encode(c: &Case, dtype: Dtype) -> Vec<u8> {
        encode_shard(&input(c, dtype)).expect("valid input encodes")
    }

    fn dtype() -> impl Strategy<Value = Dtype> {
        prop_oneof![Just(Dtype::F32), Just(Dtype::F16), Just(Dtype::I8)]
    }

    proptest! {
        #[test]
        fn round_trip_every_dtype(c in case(), dt in dtype()) {
            let bytes = encode(&c, dt);
            prop_assert_eq!(bytes.len() % 4, 0);
            let s = decode_shard(&bytes).expect("decodes");
            prop_assert_eq!(&s.header.scene_id, &c.scene);
            prop_assert_eq!(&s.header.model, &c.model);
            prop_assert_eq!(s.header.tile_id, c.tile);
            prop_assert_eq!(s.header.dtype, dt);
            prop_assert_eq!(s.header.dim as usize, c.dim);
            prop_assert_eq!(s.header.count as usize, c.ids.len());
            prop_assert_eq!(&s.ids, &c.ids);
            prop_assert_eq!(&s.means, &c.means);
            prop_assert_eq!(&s.scales, &c.scales);
            prop_assert_eq!(&s.opacities, &c.opacities);
            prop_assert_eq!(&s.rotations, &c.rotations);
            prop_assert_eq!(&s.sh_dc, &c.sh_dc);
            let stored = decode_shard_stored(&bytes).expect("decodes stored");
            prop_assert_eq!(&stored.rotations, &c.rotations);
            prop_assert_eq!(&stored.sh_dc, &c.sh_dc);
            prop_assert_eq!(Some(s.header.aabb), Aabb::of_points(c.means.iter().copied()).or(Some(Aabb::default())));
            prop_assert_eq!(s.vectors.len(), c.vectors.len());
            for (row_in, row_out) in c.vectors.chunks(c.dim).zip(s.vectors.chunks(c.dim)) {
                let maxabs = row_in.iter().fold(0f32, |m, x| m.max(x.abs()));
                let tol = match dt { Dtype::F32 => 0.0, Dtype::F16 => 1e-3 * maxabs.max(1e-3), Dtype::I8 => maxabs / 127.0 * 0.5 + 1e-7 };
                for (a, b) in row_in.iter().zip(row_out) {
                    prop_assert!((a - b).abs() <= tol, "{:?}: {} vs {} tol {}", dt, a, b, tol);
                }
            }
            prop_assert_eq!(decode_header(&bytes).expect("header"), s.header);
        }

        #[test]
        fn layout_predicts_the_encoded_length(c in case(), dt in dtype(), budget in 0u64..4000) {
            let layout = ShardLayout::of_input(&input(&c, dt));
            let n = c.ids.len() as u64;
            let len = encode(&c, dt).len() as u64;
            prop_assert_eq!(layout.shard_len(n), len);
            let linear = layout.header_len() + n * layout.bytes_per_row();
            prop_assert!(len >= linear && len <= linear + 3, "{} vs linear {}", len, linear);
            // The byte cap is the largest count that fits.
            let k = layout.max_rows_within(budget);
            if k > 0 {
                prop_assert!(layout.shard_len(k) <= budget);
            } else {
                prop_assert!(layout.shard_len(1) > budget);
            }
            prop_assert!(layout.shard_len(k + 1) > budget);
        }

        #[test]
        fn truncation_is_a_typed_error(c in case(), dt in dtype(), cut in any::<prop::sample::Index>()) {
            let bytes = encode(&c, dt);
            let k = cut.index(bytes.len());
            let r = decode_shard(&bytes[..k]);
            prop_assert!(matches!(r, Err(ShardError::Truncated { .. })), "cut at {} of {}: {:?}", k, bytes.len(), r.map(|_| ()));
        }

        #[test]
        fn corruption_never_panics_and_is_detected(c in case(), dt in dtype(),
                flips in proptest::collection::vec((any::<prop::sample::Index>(), 1u8..=255), 1..4)) {
            let mut bytes = encode(&c, dt);
            for (at, x) in &flips {
                let i = at.index(bytes.len());
                bytes[i] ^= x;
            }
            // Flips may cancel out; only a changed file must be rejected.
            let original = encode(&c, dt);
            let r = decode_shard(&bytes);
            if bytes != original {
                prop_assert!(r.is_err(), "corruption not detected");
            } else {
                prop_assert!(r.is_ok());
            }
        }

        #[test]
        fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..300), magic in any::<bool>()) {
            let mut b = bytes;
            if magic && b.len() >= 10 {
                b[..8].copy_from_slice(&SHARD_MAGIC);
                b[8..10].copy_from_slice(&SHARD_FORMAT_VERSION.to_le_bytes());
            }
            let _ = decode_shard(&b);
        }
    }

    #[test]
    fn foreign_and_versioned_inputs_give_specific_errors() {
        let c = Case {
            ids: vec![3, 9],
            means: vec![[0.0, 1.0, 2.0], [-1.0, 5.0, 0.5]],
            vectors: unit(vec![1.0, 2.0, 3.0])
                .into_iter()
                .chain(unit(vec![0.0, -1.0, 0.5]))
                .collect(),
            dim: 3,
            scales: None,
            opacities: Some(vec![0.1, 0.2]),
            rotations: Some(vec![[1.0, 0.0, 0.0, 0.0], [0.5, 0.5, 0.5, 0.5]]),
            sh_dc: None,
            scene: "s".into(),
            model: "m".into(),
            tile: 7,
        };
        let mut b = encode(&c, Dtype::I8);
        assert_eq!(
            decode_shard(
                b"hello world, this is not a shard at all, no no no no no no no no no no no"
            ),
            Err(ShardError::BadMagic)
        );
        b.push(0);
        assert!(matches!(decode_shard(&b), Err(ShardError::Malformed(_))));
        b.pop();
        b[8] = 2;
        assert_eq!(decode_shard(&b), Err(ShardError::UnsupportedVersion(2)));
        b[8] = 1;
        let last = b.len() - 1;
        b[last] ^= 0x40;
        assert_checksum_error(decode_shard(&b), "payload");
        b[last] ^= 0x40;
        b[30] ^= 1; // inside the tile id/AABB
        assert_checksum_error(decode_shard(&b), "header");
        b[30] ^= 1;
        // The shard carries opacities (bit 1) and rotations (bit 2) in that order.
        let s = decode_shard_stored(&b).expect("valid");
        assert_eq!(s.rotations, c.rotations);
        assert_eq!(s.opacities, c.opacities);
        assert_eq!(b[11], FLAG_OPACITIES | FLAG_ROTATIONS);
        // A flag bit this reader does not know (with a valid header CRC) is a clear error.
        let header_len = u32::from_le_bytes([b[20], b[21], b[22], b[23]]) as usize;
        b[11] |= 0x10;
        let crc = crc32fast::hash(&b[..header_len - 4]);
        b[header_len - 4..header_len].copy_from_slice(&crc.to_le_bytes());
        match decode_shard(&b) {
            Err(ShardError::Malformed(m)) => assert!(m.contains("unknown flags 0x16"), "{m}"),
            other => panic!("expected unknown flags, got {other:?}"),
        }
    }

    #[test]
    fn rejects_bad_encoder_input() {
        let one_row = ShardInput {
            scene_id: "s",
            model: "m",
            dim: 1,
            dtype: Dtype::F32,
            ids: &[1],
            means: &[[0.0; 3]],
            vectors: &[1.0],
            ..ShardInput::default()
        };
        assert!(encode_shard(&one_row).is_ok());
        // One vector value for a width of 2; a rotation column shorter than the ids.
        for bad in [
            ShardInput { dim: 2, ..one_row },
            ShardInput {
                rotations: Some(&[]),
                ..one_row
            },
        ] {
            assert!(matches!(encode_shard(&bad), Err(Error::Internal(_))));
        }
    }

    /// The bytes on disk do not drift: the [`fingerprint`] of shards of fixed content (every
    /// dtype, with and without the display and segment sections) as this format writes them.
    #[test]
    fn encoded_bytes_are_stable() {
        let ids = [3u32, 1, 4, 1_000_000];
        let means = [
            [0.5, -1.0, 2.0],
            [1e3, 0.0, -7.25],
            [0.0; 3],
            [-3.0, 4.0, 5.5],
        ];
        let vectors: Vec<f32> = (0..12).map(|i| (i as f32 * 0.7).sin()).collect();
        let scales = [[0.1f32, -0.2, 0.3]; 4];
        let opacities = [0.5f32, -1.0, 2.0, 0.0];
        let rotations = [[1.0f32, 0.0, 0.0, 0.0]; 4];
        let sh_dc = [[0.25f32, -0.5, 1.0]; 4];
        let segments = [7u32, 7, 0, 2];
        let mut got = Vec::new();
        for dtype in [Dtype::F32, Dtype::F16, Dtype::I8] {
            let plain = ShardInput {
                scene_id: "scene-a",
                model: "color-clip",
                tile_id: 9,
                dim: 3,
                dtype,
                ids: &ids,
                means: &means,
                vectors: &vectors,
                ..ShardInput::default()
            };
            let full = ShardInput {
                scales: Some(&scales),
                opacities: Some(&opacities),
                rotations: Some(&rotations),
                sh_dc: Some(&sh_dc),
                segments: Some(&segments),
                ..plain
            };
            for input in [plain, full] {
                let bytes = encode_shard(&input).expect("encodes");
                got.push(fingerprint(&bytes));
            }
        }
        assert_eq!(got, GOLDEN_DENSE, "{got:x?}");
    }

    /// [`fingerprint`]s per dtype (f32, f16, int8), plain then with every optional section.
    const GOLDEN_DENSE: [(usize, u32); 6] = [
        (208, 0x8c3a_61c0),
        (400, 0x999d_9623),
        (184, 0xc1f3_21b0),
        (376, 0x76bf_5c33),
        (188, 0x9e19_6dea),
        (380, 0x4959_02a9),
    ];

    /// Sets header byte `at` to `v` and re-seals the header CRC.
    fn patch_header(bytes: &mut [u8], at: usize, v: u8) {
        bytes[at] = v;
        let hl = u32::from_le_bytes([bytes[20], bytes[21], bytes[22], bytes[23]]) as usize;
        let crc = crc32fast::hash(&bytes[..hl - 4]);
        bytes[hl - 4..hl].copy_from_slice(&crc.to_le_bytes());
    }

    #[test]
    #[allow(clippy::unwrap_used)]
    fn segments_make_version_3_and_round_trip() {
        let ids = [4u32, 9, 2];
        let means = [[0.0, 1.0, 2.0], [3.0, 4.0, 5.0], [6.0, 7.0, 8.0]];
        let vectors = [1.0, 0.0, 0.0, 1.0, 0.6, 0.8];
        let segments = [7u32, 7, 0];
        let scales = [[0.1f32; 3]; 3];
        let opacities = [0.5f32; 3];
        for dtype in [Dtype::F32, Dtype::F16, Dtype::I8] {
            for display in [false, true] {
                let input = ShardInput {
                    scene_id: "scene",
                    model: "m",
                    tile_id: 3,
                    dim: 2,
                    dtype,
                    ids: &ids,
                    means: &means,
                    vectors: &vectors,
                    scales: display.then_some(&scales[..]),
                    opacities: display.then_some(&opacities[..]),
                    rotations: None,
                    sh_dc: None,
                    segments: Some(&segments),
                };
                let bytes = encode_shard(&input).unwrap();
                assert_eq!(
                    bytes.len() as u64,
                    ShardLayout::of_input(&input).shard_len(3)
                );
                let s = decode_shard(&bytes).unwrap();
                assert_eq!(s.header.version, SEGMENTS_SHARD_FORMAT_VERSION);
                assert_eq!(s.segments.as_deref(), Some(&segments[..]));
                assert_eq!(s.ids, ids);
                assert_eq!(s.scales.is_some(), display);
                // Without segments: version 1, and no segments read back.
                let v1 = encode_shard(&ShardInput {
                    segments: None,
                    ..input
                })
                .unwrap();
                let s1 = decode_shard(&v1).unwrap();
                assert_eq!(s1.header.version, SHARD_FORMAT_VERSION);
                assert_eq!(s1.segments, None);
                assert_eq!(bytes.len() - v1.len(), 12);
                // Version 3 without its flag, version 1 with it, and version 4: refused.
                let mut no_flag = bytes.clone();
                patch_header(&mut no_flag, 11, bytes[11] & !FLAG_SEGMENTS);
                assert!(matches!(
                    decode_shard(&no_flag),
                    Err(ShardError::Malformed(_))
                ));
                let mut v1_flag = v1.clone();
                patch_header(&mut v1_flag, 11, v1[11] | FLAG_SEGMENTS);
                assert!(matches!(
                    decode_shard(&v1_flag),
                    Err(ShardError::Malformed(_))
                ));
                let mut v4 = bytes.clone();
                patch_header(&mut v4, 8, 4);
                assert_eq!(decode_shard(&v4), Err(ShardError::UnsupportedVersion(4)));
            }
        }
    }
}
