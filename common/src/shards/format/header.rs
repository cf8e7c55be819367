//! The shard header (module doc, "Byte layout"): writing it before a payload, and reading and
//! validating it with a little-endian cursor that never panics.

use super::{
    Aabb, Dtype, FIXED_HEADER, FLAG_SEGMENTS, KNOWN_FLAGS, MAX_DIM, MAX_HEADER_LEN, MAX_SLOTS,
    MIXTURE_HEADER_EXTRA, MIXTURE_SEGMENTS_SHARD_FORMAT_VERSION, MIXTURE_SHARD_FORMAT_VERSION,
    SEGMENTS_SHARD_FORMAT_VERSION, SHARD_FORMAT_VERSION, SHARD_MAGIC, ShardError, ShardHeader,
    align, has_segments_version, is_mixture_version,
};

/// The header fields [`assemble`] writes.
pub(in crate::shards) struct HeaderFields<'a> {
    pub version: u16,
    pub dtype: Dtype,
    pub flags: u8,
    pub dim: u32,
    pub count: u32,
    pub tile_id: u64,
    pub aabb: Aabb,
    pub scene_id: &'a str,
    pub model: &'a str,
    /// Version 2: `(slots, codebook checksum)`.
    pub mixture: Option<(u32, u32)>,
}

/// Header bytes for the string lengths and version (a multiple of 8).
pub(in crate::shards) fn header_len_for(
    scene_len: usize,
    model_len: usize,
    mixture: bool,
) -> usize {
    let fixed = FIXED_HEADER + if mixture { MIXTURE_HEADER_EXTRA } else { 0 };
    align(fixed + scene_len + model_len + 4, 8)
}

/// Header (module-doc layout; the mixture extension for version 2) followed by `payload`. The
/// caller has checked the string lengths (≤ 65535 bytes).
pub(in crate::shards) fn assemble(f: &HeaderFields<'_>, p: Vec<u8>) -> Vec<u8> {
    let (s, m) = (f.scene_id.len(), f.model.len());
    let header_len = header_len_for(s, m, f.mixture.is_some());
    let mut h: Vec<u8> = Vec::with_capacity(header_len + p.len());
    h.extend_from_slice(&SHARD_MAGIC);
    h.extend_from_slice(&f.version.to_le_bytes());
    h.push(f.dtype.code());
    h.push(f.flags);
    h.extend_from_slice(&f.dim.to_le_bytes());
    h.extend_from_slice(&f.count.to_le_bytes());
    h.extend_from_slice(&(header_len as u32).to_le_bytes());
    h.extend_from_slice(&f.tile_id.to_le_bytes());
    f.aabb
        .min
        .iter()
        .chain(&f.aabb.max)
        .for_each(|x| h.extend_from_slice(&x.to_le_bytes()));
    h.extend_from_slice(&(p.len() as u64).to_le_bytes());
    h.extend_from_slice(&crc32fast::hash(&p).to_le_bytes());
    h.extend_from_slice(&(s as u16).to_le_bytes());
    h.extend_from_slice(&(m as u16).to_le_bytes());
    if let Some((slots, crc)) = f.mixture {
        h.extend_from_slice(&slots.to_le_bytes());
        h.extend_from_slice(&crc.to_le_bytes());
    }
    h.extend_from_slice(f.scene_id.as_bytes());
    h.extend_from_slice(f.model.as_bytes());
    h.resize(header_len - 4, 0);
    let hcrc = crc32fast::hash(&h);
    h.extend_from_slice(&hcrc.to_le_bytes());
    h.extend_from_slice(&p);
    h
}

/// Little-endian cursor that never panics.
pub(in crate::shards) struct Reader<'a> {
    pub(in crate::shards) b: &'a [u8],
    pub(in crate::shards) at: usize,
}

impl<'a> Reader<'a> {
    pub(in crate::shards) fn take(&mut self, n: usize) -> Result<&'a [u8], ShardError> {
        let end = self
            .at
            .checked_add(n)
            .filter(|&e| e <= self.b.len())
            .ok_or(ShardError::Truncated {
                needed: self.at as u64 + n as u64,
                got: self.b.len() as u64,
            })?;
        let s = &self.b[self.at..end];
        self.at = end;
        Ok(s)
    }
    fn arr<const K: usize>(&mut self) -> Result<[u8; K], ShardError> {
        let s = self.take(K)?;
        let mut a = [0u8; K];
        a.copy_from_slice(s);
        Ok(a)
    }
    fn u16(&mut self) -> Result<u16, ShardError> {
        Ok(u16::from_le_bytes(self.arr()?))
    }
    pub(in crate::shards) fn u32(&mut self) -> Result<u32, ShardError> {
        Ok(u32::from_le_bytes(self.arr()?))
    }
    fn u64(&mut self) -> Result<u64, ShardError> {
        Ok(u64::from_le_bytes(self.arr()?))
    }
    fn f32(&mut self) -> Result<f32, ShardError> {
        Ok(f32::from_le_bytes(self.arr()?))
    }
}

pub(in crate::shards) fn le_f32s(b: &[u8]) -> Vec<f32> {
    b.chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

pub(in crate::shards) fn triples(v: Vec<f32>) -> Vec<[f32; 3]> {
    v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
}

/// A parsed, CRC-checked header ([`parse_header`]).
pub(in crate::shards) struct ParsedHeader {
    /// The header fields.
    pub header: ShardHeader,
    /// Offset of the payload.
    pub header_len: usize,
    /// Optional-section flags.
    pub flags: u8,
    /// Payload bytes the header announces.
    pub payload_len: u64,
    /// CRC-32 of the payload the header records.
    pub payload_crc: u32,
    /// Version 2 only: `(slots S, codebook checksum)`.
    pub mixture: Option<(u32, u32)>,
}

/// Decodes and fully validates the header only (checks magic, version, header CRC, lengths
/// against `bytes.len()`); returns the header, `header_len`, flags and payload CRC.
pub(in crate::shards) fn parse_header(bytes: &[u8]) -> Result<ParsedHeader, ShardError> {
    if bytes.len() < FIXED_HEADER {
        if bytes.len() >= 8 && bytes[..8] != SHARD_MAGIC {
            return Err(ShardError::BadMagic);
        }
        return Err(ShardError::Truncated {
            needed: FIXED_HEADER as u64,
            got: bytes.len() as u64,
        });
    }
    let mut r = Reader { b: bytes, at: 0 };
    if r.arr::<8>()? != SHARD_MAGIC {
        return Err(ShardError::BadMagic);
    }
    let f = read_fixed(&mut r)?;
    check_header_bytes(bytes, &f)?;
    let scene_id = std::str::from_utf8(r.take(f.scene_len)?)
        .map_err(|_| ShardError::Malformed("scene id is not UTF-8".into()))?
        .to_string();
    let model = std::str::from_utf8(r.take(f.model_len)?)
        .map_err(|_| ShardError::Malformed("model id is not UTF-8".into()))?
        .to_string();
    let dtype = check_fields(&f)?;
    let header = ShardHeader {
        version: f.version,
        scene_id,
        model,
        dim: f.dim,
        dtype,
        count: f.count,
        aabb: f.aabb,
        tile_id: f.tile_id,
    };
    Ok(ParsedHeader {
        header,
        header_len: f.header_len,
        flags: f.flags,
        payload_len: f.payload_len,
        payload_crc: f.payload_crc,
        mixture: f.mixture,
    })
}

/// The fixed fields of a header (module-doc layout) as read, and the mixture extension.
struct FixedFields {
    version: u16,
    dtype_code: u8,
    flags: u8,
    dim: u32,
    count: u32,
    header_len: usize,
    tile_id: u64,
    aabb: Aabb,
    payload_len: u64,
    payload_crc: u32,
    scene_len: usize,
    model_len: usize,
    /// Versions 2 and 4: `(slots S, codebook checksum)`.
    mixture: Option<(u32, u32)>,
}

/// Reads the fields after the magic up to the strings (the mixture extension for versions 2
/// and 4). Errors: [`ShardError::UnsupportedVersion`], [`ShardError::Truncated`].
fn read_fixed(r: &mut Reader<'_>) -> Result<FixedFields, ShardError> {
    let version = r.u16()?;
    if version != SHARD_FORMAT_VERSION
        && version != MIXTURE_SHARD_FORMAT_VERSION
        && version != SEGMENTS_SHARD_FORMAT_VERSION
        && version != MIXTURE_SEGMENTS_SHARD_FORMAT_VERSION
    {
        return Err(ShardError::UnsupportedVersion(version));
    }
    let dtype_code = r.arr::<1>()?[0];
    let flags = r.arr::<1>()?[0];
    let dim = r.u32()?;
    let count = r.u32()?;
    let header_len = r.u32()? as usize;
    let tile_id = r.u64()?;
    let mut aabb = Aabb::default();
    for a in 0..3 {
        aabb.min[a] = r.f32()?;
    }
    for a in 0..3 {
        aabb.max[a] = r.f32()?;
    }
    let payload_len = r.u64()?;
    let payload_crc = r.u32()?;
    let scene_len = r.u16()? as usize;
    let model_len = r.u16()? as usize;
    let mixture = if is_mixture_version(version) {
        Some((r.u32()?, r.u32()?))
    } else {
        None
    };
    Ok(FixedFields {
        version,
        dtype_code,
        flags,
        dim,
        count,
        header_len,
        tile_id,
        aabb,
        payload_len,
        payload_crc,
        scene_len,
        model_len,
        mixture,
    })
}

/// Checks `header_len` (a multiple of 8, room for the fixed fields and strings, at most
/// [`MAX_HEADER_LEN`], within `bytes`) and the header CRC.
fn check_header_bytes(bytes: &[u8], f: &FixedFields) -> Result<(), ShardError> {
    let header_len = f.header_len;
    let fixed = if f.mixture.is_some() {
        FIXED_HEADER + MIXTURE_HEADER_EXTRA
    } else {
        FIXED_HEADER
    };
    if !header_len.is_multiple_of(8)
        || header_len < align(fixed + f.scene_len + f.model_len + 4, 8)
        || header_len > MAX_HEADER_LEN
    {
        return Err(ShardError::Malformed(format!(
            "header length {header_len} inconsistent"
        )));
    }
    if bytes.len() < header_len {
        return Err(ShardError::Truncated {
            needed: header_len as u64,
            got: bytes.len() as u64,
        });
    }
    let stored = u32::from_le_bytes([
        bytes[header_len - 4],
        bytes[header_len - 3],
        bytes[header_len - 2],
        bytes[header_len - 1],
    ]);
    let computed = crc32fast::hash(&bytes[..header_len - 4]);
    if stored != computed {
        return Err(ShardError::Checksum {
            section: "header",
            stored,
            computed,
        });
    }
    Ok(())
}

/// Checks the dtype, the flags against the version, the embedding width and the mixture
/// extension; returns the dtype.
fn check_fields(f: &FixedFields) -> Result<Dtype, ShardError> {
    let (version, flags, dim) = (f.version, f.flags, f.dim);
    let dtype = Dtype::from_code(f.dtype_code)
        .ok_or_else(|| ShardError::Malformed(format!("unknown dtype code {}", f.dtype_code)))?;
    let known = if has_segments_version(version) {
        KNOWN_FLAGS | FLAG_SEGMENTS
    } else {
        KNOWN_FLAGS
    };
    if flags & !known != 0 {
        return Err(ShardError::Malformed(format!("unknown flags {flags:#04x}")));
    }
    if has_segments_version(version) && flags & FLAG_SEGMENTS == 0 {
        return Err(ShardError::Malformed(format!(
            "format version {version} without its segments section (flag bit 4)"
        )));
    }
    if dim == 0 || dim > MAX_DIM {
        return Err(ShardError::Malformed(format!(
            "embedding dim {dim} outside 1..={MAX_DIM}"
        )));
    }
    if let Some((slots, _)) = f.mixture {
        if dtype != Dtype::F16 {
            return Err(ShardError::Malformed(format!(
                "mixture shard with weight dtype {dtype:?}; mixture weights are f16"
            )));
        }
        if slots == 0 || slots > MAX_SLOTS {
            return Err(ShardError::Malformed(format!(
                "mixture slots {slots} outside 1..={}",
                MAX_SLOTS
            )));
        }
    }
    Ok(dtype)
}
