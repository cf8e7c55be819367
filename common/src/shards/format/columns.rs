//! The columns every shard holds besides its row section (module doc, "Byte layout"): the
//! header strings and tile, the ids and means, the optional display sections and the segment
//! ids; how dense and mixture inputs and decoded shards declare them, and how the encoders write
//! and the decoders read them around their own rows.

use half::f16;

use super::header::{HeaderFields, ParsedHeader, Reader, assemble, le_f32s, triples};
use super::{
    Aabb, Dtype, FLAG_OPACITIES, FLAG_ROTATIONS, FLAG_SCALES, FLAG_SEGMENTS, FLAG_SH_DC, MAX_DIM,
    ShardError, align,
};
use crate::Error;

/// The columns a dense and a mixture shard input share: the header strings and tile, the ids
/// and means, and the optional display and segment sections (everything but the embedding
/// rows). `what` names the encoder in messages.
#[derive(Clone, Copy)]
pub(in crate::shards) struct ShardColumns<'a> {
    pub what: &'static str,
    pub scene_id: &'a str,
    pub model: &'a str,
    pub tile_id: u64,
    pub dim: usize,
    pub ids: &'a [u32],
    pub means: &'a [[f32; 3]],
    pub display: DisplaySlices<'a>,
    pub segments: Option<&'a [u32]>,
}

/// The optional display sections of one shard, borrowed, each `[N]` when present (INRIA `.ply`
/// conventions): what a viewer draws besides the means.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct DisplaySlices<'a> {
    /// Log-scales `[N]`.
    pub scales: Option<&'a [[f32; 3]]>,
    /// Pre-sigmoid opacities `[N]`.
    pub opacities: Option<&'a [f32]>,
    /// Normalised rotations (w, x, y, z) `[N]`.
    pub rotations: Option<&'a [[f32; 4]]>,
    /// SH DC colour (`f_dc_0..2`, `rgb = 0.5 + SH_C0 * f_dc`) `[N]`.
    pub sh_dc: Option<&'a [[f32; 3]]>,
}

/// Declares a borrowed shard input: the header fields every shard has (`scene_id`, `model`,
/// `tile_id`, `dim`), the caller's `header` fields, the ids and means, the caller's `rows` fields
/// (its row section), then the optional display and segment columns; and its `columns` method,
/// the [`ShardColumns`] the encoders share. Dense ([`super::ShardInput`]) and mixture
/// ([`crate::shards::MixtureShardInput`]) inputs are declared by it, so their common fields
/// cannot drift apart.
macro_rules! shard_input {
    (
        $(#[$attr:meta])*
        pub struct $name:ident<$a:lifetime> {
            header { $($(#[$hattr:meta])* pub $hfield:ident: $hty:ty,)* }
            rows { $($(#[$rattr:meta])* pub $rfield:ident: $rty:ty,)* }
        }
    ) => {
        $(#[$attr])*
        pub struct $name<$a> {
            /// Scene id (≤ 65535 bytes UTF-8).
            pub scene_id: &$a str,
            /// Embedding model id (≤ 65535 bytes UTF-8).
            pub model: &$a str,
            /// Tile id.
            pub tile_id: u64,
            /// Embedding width D (1..=[`MAX_DIM`](crate::shards::format::MAX_DIM)): of the
            /// vectors, or of a mixture shard's codebook rows.
            pub dim: usize,
            $($(#[$hattr])* pub $hfield: $hty,)*
            /// Source-`.ply` indices `[N]`.
            pub ids: &$a [u32],
            /// Centres `[N]`, world frame, scene units.
            pub means: &$a [[f32; 3]],
            $($(#[$rattr])* pub $rfield: $rty,)*
            /// Optional log-scales `[N]`.
            pub scales: Option<&$a [[f32; 3]]>,
            /// Optional pre-sigmoid opacities `[N]`.
            pub opacities: Option<&$a [f32]>,
            /// Optional normalised rotations (w, x, y, z) `[N]`.
            pub rotations: Option<&$a [[f32; 4]]>,
            /// Optional SH DC colour (`f_dc_0..2`) `[N]`.
            pub sh_dc: Option<&$a [[f32; 3]]>,
            /// Optional scene-wide segment ids `[N]` ([`crate::segments`]); when given, the
            /// shard is written in its kind's version with segments
            /// ([`SEGMENTS_SHARD_FORMAT_VERSION`](crate::shards::SEGMENTS_SHARD_FORMAT_VERSION)
            /// dense,
            /// [`MIXTURE_SEGMENTS_SHARD_FORMAT_VERSION`](crate::shards::MIXTURE_SEGMENTS_SHARD_FORMAT_VERSION)
            /// mixture).
            pub segments: Option<&$a [u32]>,
        }

        impl<$a> $name<$a> {
            /// This input with the optional display sections of `display` and the segment ids
            /// `segments` (each `[N]` when present), the other fields kept.
            pub fn with_display(
                self,
                display: $crate::shards::DisplaySlices<$a>,
                segments: Option<&$a [u32]>,
            ) -> Self {
                let $crate::shards::DisplaySlices { scales, opacities, rotations, sh_dc } = display;
                Self { scales, opacities, rotations, sh_dc, segments, ..self }
            }

            /// The columns every shard shares, for the encoder named `what` (in messages).
            pub(in crate::shards) fn columns(
                &self,
                what: &'static str,
            ) -> $crate::shards::format::ShardColumns<$a> {
                $crate::shards::format::ShardColumns {
                    what,
                    scene_id: self.scene_id,
                    model: self.model,
                    tile_id: self.tile_id,
                    dim: self.dim,
                    ids: self.ids,
                    means: self.means,
                    display: $crate::shards::DisplaySlices {
                        scales: self.scales,
                        opacities: self.opacities,
                        rotations: self.rotations,
                        sh_dc: self.sh_dc,
                    },
                    segments: self.segments,
                }
            }
        }
    };
}
pub(in crate::shards) use shard_input;

/// Declares a decoded shard: the caller's `header` fields, the ids and means, the caller's
/// `rows` fields (its row section as decoded), then the optional display and segment columns;
/// and its `display` method. [`super::Shard`], [`super::StoredShard`] and
/// [`crate::shards::MixtureShard`] are declared by it.
macro_rules! decoded_shard {
    (
        $(#[$attr:meta])*
        pub struct $name:ident {
            header { $($(#[$hattr:meta])* pub $hfield:ident: $hty:ty,)* }
            rows { $($(#[$rattr:meta])* pub $rfield:ident: $rty:ty,)* }
        }
    ) => {
        $(#[$attr])*
        pub struct $name {
            $($(#[$hattr])* pub $hfield: $hty,)*
            /// Source-`.ply` indices `[N]`.
            pub ids: Vec<u32>,
            /// Centres `[N]`, world frame, scene units.
            pub means: Vec<[f32; 3]>,
            $($(#[$rattr])* pub $rfield: $rty,)*
            /// Optional log-scales (INRIA `.ply` convention), `[N]`, for display.
            pub scales: Option<Vec<[f32; 3]>>,
            /// Optional pre-sigmoid opacities (INRIA `.ply` convention), `[N]`, for display.
            pub opacities: Option<Vec<f32>>,
            /// Optional normalised rotations, quaternions (w, x, y, z) (INRIA `rot_0..3`), `[N]`,
            /// for display.
            pub rotations: Option<Vec<[f32; 4]>>,
            /// Optional SH DC colour (INRIA `f_dc_0..2`, `rgb = 0.5 + SH_C0 * f_dc`), `[N]`, for
            /// display.
            pub sh_dc: Option<Vec<[f32; 3]>>,
            /// Optional scene-wide geometric segment id of each Gaussian ([`crate::segments`]),
            /// `[N]`; present in shards of a version with segments only (3 dense, 4 mixture).
            pub segments: Option<Vec<u32>>,
        }

        impl $name {
            /// The display sections the shard carries.
            pub fn display(&self) -> $crate::shards::DisplaySlices<'_> {
                $crate::shards::DisplaySlices {
                    scales: self.scales.as_deref(),
                    opacities: self.opacities.as_deref(),
                    rotations: self.rotations.as_deref(),
                    sh_dc: self.sh_dc.as_deref(),
                }
            }
        }
    };
}
pub(in crate::shards) use decoded_shard;

/// How one shard kind stores its embedding rows (payload section 3) and marks them in the header.
pub(in crate::shards) struct RowSection {
    /// Header dtype.
    pub dtype: Dtype,
    /// Format version without and with the segments section.
    pub versions: [u16; 2],
    /// The mixture header extension `(slots, codebook checksum)`, for mixture shards.
    pub mixture: Option<(u32, u32)>,
    /// Payload bytes per row of the section (for the allocation).
    pub bytes_per_row: usize,
}

impl ShardColumns<'_> {
    /// Errors: `dim` outside 1..=[`MAX_DIM`] ([`Error::Param`]), N above `u32::MAX`
    /// ([`Error::Limit`]).
    pub(in crate::shards) fn check_shape(&self) -> crate::Result<()> {
        if self.dim == 0 || self.dim > MAX_DIM as usize {
            return Err(Error::param(
                "dim",
                self.dim,
                format!("an embedding width in 1..={MAX_DIM}"),
            ));
        }
        let n = self.ids.len();
        if u32::try_from(n).is_err() {
            return Err(Error::limit(crate::Resource::ShardGaussians, n, u32::MAX));
        }
        Ok(())
    }

    /// Errors: a display or segments column whose length differs from the ids'
    /// ([`Error::Internal`]); ids longer than 65535 bytes or a non-finite mean
    /// ([`Error::Invalid`]).
    pub(in crate::shards) fn check_columns(&self) -> crate::Result<()> {
        let n = self.ids.len();
        let d = &self.display;
        if d.scales.is_some_and(|v| v.len() != n)
            || d.opacities.is_some_and(|v| v.len() != n)
            || d.rotations.is_some_and(|v| v.len() != n)
            || d.sh_dc.is_some_and(|v| v.len() != n)
            || self.segments.is_some_and(|v| v.len() != n)
        {
            return Err(Error::internal(format!(
                "{}: a display or segments column's length differs from the id count",
                self.what
            )));
        }
        let bad = |m: &str| Err(Error::Invalid(format!("{}: {m}", self.what)));
        if self.scene_id.len() > u16::MAX as usize || self.model.len() > u16::MAX as usize {
            return bad("scene or model id longer than 65535 bytes");
        }
        if self.means.iter().flatten().any(|x| !x.is_finite()) {
            return bad("non-finite mean; fix the encoder output");
        }
        Ok(())
    }

    /// The shard (module-doc layout): header, then ids, means, the row section `write_rows`
    /// appends, zero padding to 4 bytes, the display sections and the segments. The caller has
    /// run both checks.
    pub(in crate::shards) fn encode(
        &self,
        rows: &RowSection,
        write_rows: impl FnOnce(&mut Vec<u8>),
    ) -> Vec<u8> {
        let n = self.ids.len();
        let mut p: Vec<u8> = Vec::with_capacity(n * (16 + rows.bytes_per_row) + 4);
        put_le(&mut p, self.ids, u32::to_le_bytes);
        put_le(&mut p, self.means.as_flattened(), f32::to_le_bytes);
        write_rows(&mut p);
        p.resize(align(p.len(), 4), 0);
        let mut flags = write_display(&mut p, &self.display);
        if let Some(seg) = self.segments {
            flags |= FLAG_SEGMENTS;
            put_le(&mut p, seg, u32::to_le_bytes);
        }
        assemble(
            &HeaderFields {
                version: rows.versions[usize::from(self.segments.is_some())],
                dtype: rows.dtype,
                flags,
                dim: self.dim as u32,
                count: n as u32,
                tile_id: self.tile_id,
                aabb: Aabb::of_points(self.means.iter().copied()).unwrap_or_default(),
                scene_id: self.scene_id,
                model: self.model,
                mixture: rows.mixture,
            },
            p,
        )
    }
}

/// Appends the display sections given (layout order) to a payload; returns their flag bits.
pub(in crate::shards) fn write_display(p: &mut Vec<u8>, display: &DisplaySlices<'_>) -> u8 {
    let sections = [
        (FLAG_SCALES, display.scales.map(<[[f32; 3]]>::as_flattened)),
        (FLAG_OPACITIES, display.opacities),
        (
            FLAG_ROTATIONS,
            display.rotations.map(<[[f32; 4]]>::as_flattened),
        ),
        (FLAG_SH_DC, display.sh_dc.map(<[[f32; 3]]>::as_flattened)),
    ];
    let mut flags = 0u8;
    for (bit, values) in sections {
        if let Some(values) = values {
            flags |= bit;
            put_le(p, values, f32::to_le_bytes);
        }
    }
    flags
}

/// Appends `values` to `p` as their little-endian bytes (`le`, e.g. `f32::to_le_bytes`: the
/// payload's byte order).
pub(in crate::shards) fn put_le<T: Copy, const K: usize>(
    p: &mut Vec<u8>,
    values: &[T],
    le: fn(T) -> [u8; K],
) {
    values.iter().for_each(|&x| p.extend_from_slice(&le(x)));
}

/// Ids, means, the row section and the display and segment sections of a shard payload
/// ([`read_payload`]).
pub(in crate::shards) type Payload<R> = (Vec<u32>, Vec<[f32; 3]>, R, DisplaySections);

/// Checks the payload of the shard `bytes` whose header is `parsed` ([`checked_payload`]:
/// `expected` bytes, `what` describing the rows for the message) and reads it in layout order:
/// ids, means, the row section (`read_rows`, given the row count), padding to 4 bytes, the
/// display and segment sections the flags announce.
pub(in crate::shards) fn read_payload<'b, R>(
    bytes: &'b [u8],
    parsed: &ParsedHeader,
    expected: u64,
    what: impl FnOnce() -> String,
    read_rows: impl FnOnce(&mut Reader<'b>, usize) -> Result<R, ShardError>,
) -> Result<Payload<R>, ShardError> {
    let payload = checked_payload(
        bytes,
        parsed.header_len,
        parsed.payload_len,
        parsed.payload_crc,
        expected,
        what,
    )?;
    let n = parsed.header.count as usize;
    let mut r = Reader { b: payload, at: 0 };
    let ids = read_u32s(&mut r, n)?;
    let means = triples(le_f32s(r.take(12 * n)?));
    let rows = read_rows(&mut r, n)?;
    r.at = align(r.at, 4);
    let display = read_display(&mut r, parsed.flags, n)?;
    Ok((ids, means, rows, display))
}

/// `n` little-endian `u32`s.
pub(in crate::shards) fn read_u32s(r: &mut Reader<'_>, n: usize) -> Result<Vec<u32>, ShardError> {
    Ok(r.take(4 * n)?
        .chunks_exact(4)
        .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect())
}

/// `n` little-endian IEEE halves.
pub(in crate::shards) fn read_f16s(r: &mut Reader<'_>, n: usize) -> Result<Vec<f16>, ShardError> {
    Ok(r.take(2 * n)?
        .chunks_exact(2)
        .map(|c| f16::from_le_bytes([c[0], c[1]]))
        .collect())
}

/// The optional display sections of a payload ([`read_display`]).
#[derive(Debug, Default)]
pub(in crate::shards) struct DisplaySections {
    pub scales: Option<Vec<[f32; 3]>>,
    pub opacities: Option<Vec<f32>>,
    pub rotations: Option<Vec<[f32; 4]>>,
    pub sh_dc: Option<Vec<[f32; 3]>>,
    pub segments: Option<Vec<u32>>,
}

/// Reads the display sections the flags announce, in layout order.
pub(in crate::shards) fn read_display(
    r: &mut Reader<'_>,
    flags: u8,
    n: usize,
) -> Result<DisplaySections, ShardError> {
    let scales = if flags & FLAG_SCALES != 0 {
        Some(triples(le_f32s(r.take(12 * n)?)))
    } else {
        None
    };
    let opacities = if flags & FLAG_OPACITIES != 0 {
        Some(le_f32s(r.take(4 * n)?))
    } else {
        None
    };
    let rotations = if flags & FLAG_ROTATIONS != 0 {
        Some(
            le_f32s(r.take(16 * n)?)
                .chunks_exact(4)
                .map(|c| [c[0], c[1], c[2], c[3]])
                .collect(),
        )
    } else {
        None
    };
    let sh_dc = if flags & FLAG_SH_DC != 0 {
        Some(triples(le_f32s(r.take(12 * n)?)))
    } else {
        None
    };
    let segments = if flags & FLAG_SEGMENTS != 0 {
        Some(read_u32s(r, n)?)
    } else {
        None
    };
    Ok(DisplaySections {
        scales,
        opacities,
        rotations,
        sh_dc,
        segments,
    })
}

/// Checks the payload length against `expected`, the file length and the payload CRC; returns
/// the payload. `what` describes the rows for the message.
pub(in crate::shards) fn checked_payload(
    bytes: &[u8],
    header_len: usize,
    payload_len: u64,
    payload_crc: u32,
    expected: u64,
    what: impl FnOnce() -> String,
) -> Result<&[u8], ShardError> {
    if payload_len != expected {
        return Err(ShardError::Malformed(format!(
            "payload length {payload_len} but {} need {expected}",
            what()
        )));
    }
    let total = header_len as u64 + payload_len;
    if (bytes.len() as u64) < total {
        return Err(ShardError::Truncated {
            needed: total,
            got: bytes.len() as u64,
        });
    }
    if (bytes.len() as u64) > total {
        return Err(ShardError::Malformed(format!(
            "{} trailing bytes after the payload",
            bytes.len() as u64 - total
        )));
    }
    let payload = &bytes[header_len..];
    let computed = crc32fast::hash(payload);
    if computed != payload_crc {
        return Err(ShardError::Checksum {
            section: "payload",
            stored: payload_crc,
            computed,
        });
    }
    // Lengths are now proven to fit in memory (they sum to bytes.len()).
    Ok(payload)
}
