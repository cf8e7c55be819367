//! Shared reading and writing of slag's safetensors files ([`crate::embeddings`],
//! [`crate::mixture`]): the format/version metadata check, typed tensor look-ups, little-endian
//! decoding and the atomic write. Every error names the file ([`Error::format`]) and says what to
//! do.

use std::collections::HashMap;
use std::io::Read;
use std::path::Path;

use half::f16;
use safetensors::SafeTensors;
use safetensors::tensor::{Dtype, TensorView};

use crate::io::write_atomic_parts;
use crate::{Error, Result};

/// Largest safetensors header read by [`metadata_format`], bytes (the encoder's headers are a
/// few KiB).
const MAX_HEADER: u64 = 100 << 20;

/// The `format` of the safetensors file at `path`'s `__metadata__` (`None`: no such entry), from
/// its header alone (a 31 GB dense file is not read).
///
/// Errors ([`Error::Format`] naming `path`): not a safetensors file; [`Error::Io`]: unreadable.
pub(crate) fn metadata_format(path: &Path) -> Result<Option<String>> {
    let bad = |m: String| Error::format(path, m);
    let mut f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut len = [0u8; 8];
    f.read_exact(&mut len)
        .map_err(|e| bad(format!("not a safetensors file ({e})")))?;
    let n = u64::from_le_bytes(len);
    if n > MAX_HEADER {
        return Err(bad(format!("not a safetensors file (header of {n} bytes)")));
    }
    let mut header = vec![0u8; n as usize];
    f.read_exact(&mut header)
        .map_err(|e| bad(format!("not a safetensors file ({e})")))?;
    let json: serde_json::Value = serde_json::from_slice(&header)
        .map_err(|e| bad(format!("not a safetensors file ({e})")))?;
    Ok(json
        .get("__metadata__")
        .and_then(|m| m.get("format"))
        .and_then(|f| f.as_str())
        .map(str::to_owned))
}

/// What a slag safetensors file must declare in its `__metadata__`, and the words its errors use.
pub(crate) struct FileKind {
    /// `format` metadata value, e.g. `"slag-embeddings"`.
    pub format: &'static str,
    /// `version` metadata value this slag reads.
    pub version: &'static str,
    /// Noun for the file in messages, e.g. `"embeddings"` ("not a slag embeddings file").
    pub noun: &'static str,
    /// The encoder's output file name, e.g. `"embeddings.safetensors"`.
    pub file_name: &'static str,
    /// The command that writes a current file, e.g. `"slag-encoder encode"`.
    pub rewrite_with: &'static str,
}

/// A parsed file whose metadata declares `kind`'s format and version.
pub(crate) struct Checked<'a> {
    /// The `__metadata__` strings.
    pub meta: HashMap<String, String>,
    /// The tensors.
    pub tensors: SafeTensors<'a>,
}

/// Parses `bytes` (read from `path`) and checks the `format` and `version` metadata against
/// `kind`.
///
/// Errors ([`Error::Format`] naming `path`): not safetensors, another format, another version, a
/// header that does not match the data.
pub(crate) fn open<'a>(path: &Path, bytes: &'a [u8], kind: &FileKind) -> Result<Checked<'a>> {
    let bad = |m: String| Error::format(path, m);
    let (_, header) = SafeTensors::read_metadata(bytes).map_err(|e| {
        bad(format!(
            "not a safetensors file ({e}); pass the encoder's {}",
            kind.file_name
        ))
    })?;
    let meta = header.metadata().clone().unwrap_or_default();
    if meta.get("format").map(String::as_str) != Some(kind.format) {
        return Err(bad(format!(
            "not a slag {} file (metadata format {:?})",
            kind.noun,
            meta.get("format")
        )));
    }
    if meta.get("version").map(String::as_str) != Some(kind.version) {
        return Err(bad(format!(
            "{} format version {:?}, this slag reads {}; re-run {}",
            kind.noun,
            meta.get("version"),
            kind.version,
            kind.rewrite_with
        )));
    }
    let tensors = SafeTensors::deserialize(bytes).map_err(|e| bad(format!("{e}")))?;
    Ok(Checked { meta, tensors })
}

impl<'a> Checked<'a> {
    /// Tensor `name`, any dtype.
    ///
    /// Errors ([`Error::Format`] naming `path`): no such tensor.
    pub fn tensor(&self, path: &Path, name: &str) -> Result<TensorView<'a>> {
        self.tensors
            .tensor(name)
            .map_err(|e| Error::format(path, format!("tensor {name}: {e}")))
    }

    /// Tensor `name`, which must have dtype `dtype`.
    ///
    /// Errors ([`Error::Format`] naming `path`): no such tensor, another dtype.
    pub fn tensor_of(&self, path: &Path, name: &str, dtype: Dtype) -> Result<TensorView<'a>> {
        let t = self.tensor(path, name)?;
        if t.dtype() != dtype {
            return Err(Error::format(
                path,
                format!("tensor {name} is {:?}, expected {dtype:?}", t.dtype()),
            ));
        }
        Ok(t)
    }
}

/// One tensor of [`write`]: `(name, dtype, shape, little-endian data)`.
pub(crate) type Tensor<'a> = (&'a str, Dtype, Vec<usize>, &'a [u8]);

/// An element type slag stores in safetensors, with its dtype.
pub(crate) trait Element: bytemuck::Pod {
    /// The safetensors dtype of a tensor of this element.
    const DTYPE: Dtype;
}

impl Element for u16 {
    const DTYPE: Dtype = Dtype::U16;
}
impl Element for u32 {
    const DTYPE: Dtype = Dtype::U32;
}
impl Element for f32 {
    const DTYPE: Dtype = Dtype::F32;
}
impl Element for f16 {
    const DTYPE: Dtype = Dtype::F16;
}
impl Element for [f32; 3] {
    const DTYPE: Dtype = Dtype::F32;
}

/// `data` as a tensor of [`write`] of shape `shape`, its dtype that of `T` (so the two cannot
/// disagree), its bytes in the host's order (little-endian on every target slag builds for).
pub(crate) fn tensor<'a, T: Element>(
    name: &'a str,
    shape: Vec<usize>,
    data: &'a [T],
) -> Tensor<'a> {
    (name, T::DTYPE, shape, bytemuck::cast_slice(data))
}

/// Serialises `tensors` (`(name, dtype, shape, little-endian data)`) with the `__metadata__`
/// strings `meta` plus `kind`'s `format` and `version` (the pair [`open`] checks), and writes the
/// file atomically ([`write_atomic_parts`]): the header first, then each tensor's data straight
/// from `tensors`, with no copy of the whole file in memory. The bytes are those of
/// `safetensors::serialize` with that metadata added as its first header entry, keys sorted, so
/// that the same tensors and metadata always give the same bytes
/// (`safetensors::serialize` takes a `HashMap`, whose order changes from run to run).
///
/// Errors: [`Error::Internal`] when a tensor's data length disagrees with its dtype and shape;
/// I/O.
pub(crate) fn write(
    path: &Path,
    kind: &FileKind,
    tensors: Vec<Tensor<'_>>,
    meta: &[(&str, String)],
) -> Result<()> {
    for (_, dtype, shape, data) in &tensors {
        // TensorView checks the length against the dtype and shape (no copy).
        TensorView::new(*dtype, shape.clone(), data)
            .map_err(|e| Error::internal(format!("safetensors: {e}")))?;
    }
    // The crate's layout: by dtype, largest alignment first, then by name.
    let mut order: Vec<&(&str, Dtype, Vec<usize>, &[u8])> = tensors.iter().collect();
    order.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(b.0)));
    let kind_meta = [
        ("format", kind.format.to_string()),
        ("version", kind.version.to_string()),
    ];
    let all_meta: Vec<(&str, String)> = kind_meta.into_iter().chain(meta.iter().cloned()).collect();
    let header = header(&order, &all_meta)?;
    let parts: Vec<&[u8]> = std::iter::once(header.as_slice())
        .chain(order.iter().map(|t| t.3))
        .collect();
    write_atomic_parts(path, &parts)
}

/// The file's first bytes for the tensors in `order` (their data in that order): the header's
/// length (u64, little-endian) and the header, `{"__metadata__":{..},"name":{"dtype":..,
/// "shape":..,"data_offsets":[..]},..}` padded with spaces to a multiple of 8 bytes, as the
/// crate writes it.
///
/// Errors: [`Error::Internal`] when the header cannot be serialised.
fn header(order: &[&(&str, Dtype, Vec<usize>, &[u8])], meta: &[(&str, String)]) -> Result<Vec<u8>> {
    let json = |e: serde_json::Error| Error::internal(format!("safetensors header: {e}"));
    let sorted: std::collections::BTreeMap<&str, &str> =
        meta.iter().map(|(k, v)| (*k, v.as_str())).collect();
    let mut text = format!(
        "{{\"__metadata__\":{}",
        serde_json::to_string(&sorted).map_err(json)?
    );
    let mut offset = 0;
    for (name, dtype, shape, data) in order {
        let info = safetensors::tensor::TensorInfo {
            dtype: *dtype,
            shape: shape.clone(),
            data_offsets: (offset, offset + data.len()),
        };
        offset += data.len();
        let name = serde_json::to_string(name).map_err(json)?;
        text.push_str(&format!(
            ",{name}:{}",
            serde_json::to_string(&info).map_err(json)?
        ));
    }
    text.push('}');
    while text.len() % 8 != 0 {
        text.push(' ');
    }
    let mut out = Vec::with_capacity(8 + text.len());
    out.extend_from_slice(&(text.len() as u64).to_le_bytes());
    out.extend_from_slice(text.as_bytes());
    Ok(out)
}

/// `file` (a safetensors file without metadata, from `safetensors::serialize`) with `meta` as
/// its `__metadata__`, keys in sorted order: the tests' reference for [`write`]. The header
/// stays padded with spaces to a multiple of 8 bytes; data offsets are relative to the end of the
/// header, so the tensors are untouched.
///
/// Errors: [`Error::Internal`] when `file` is not what `safetensors::serialize` writes.
#[cfg(test)]
fn with_metadata(file: &[u8], meta: &[(&str, String)]) -> Result<Vec<u8>> {
    let bad = || Error::internal("safetensors: unexpected header layout from serialize");
    let n = file
        .get(..8)
        .and_then(|b| b.try_into().ok())
        .map(u64::from_le_bytes)
        .and_then(|n| usize::try_from(n).ok())
        .ok_or_else(bad)?;
    let header = file.get(8..8 + n).ok_or_else(bad)?;
    let data = &file[8 + n..];
    let rest = header.strip_prefix(b"{").ok_or_else(bad)?;
    let rest = std::str::from_utf8(rest).map_err(|_| bad())?.trim_end();
    let sorted: std::collections::BTreeMap<&str, &str> =
        meta.iter().map(|(k, v)| (*k, v.as_str())).collect();
    let meta_json = serde_json::to_string(&sorted)
        .map_err(|e| Error::internal(format!("safetensors metadata: {e}")))?;
    // `rest` is `"name":{..},..}` or `}` for a file without tensors.
    let sep = if rest == "}" { "" } else { "," };
    let mut out_header = format!("{{\"__metadata__\":{meta_json}{sep}{rest}");
    while out_header.len() % 8 != 0 {
        out_header.push(' ');
    }
    let mut out = Vec::with_capacity(8 + out_header.len() + data.len());
    out.extend_from_slice(&(out_header.len() as u64).to_le_bytes());
    out.extend_from_slice(out_header.as_bytes());
    out.extend_from_slice(data);
    Ok(out)
}

/// Little-endian f32 values (a trailing partial value is ignored).
pub(crate) fn le_f32(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

/// Little-endian u32 values (a trailing partial value is ignored).
pub(crate) fn le_u32(bytes: &[u8]) -> Vec<u32> {
    bytes
        .chunks_exact(4)
        .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

/// Little-endian IEEE half values, widened to f32 (exact; a trailing odd byte is ignored).
pub(crate) fn le_f16(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(2)
        .map(|c| f16::from_le_bytes([c[0], c[1]]).to_f32())
        .collect()
}

/// `[x, y, z]` rows of a flat `[N * 3]` array (a trailing partial row is ignored).
pub(crate) fn triples(flat: &[f32]) -> Vec<[f32; 3]> {
    flat.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn the_streamed_file_is_the_serialized_one_with_its_metadata() {
        let dir = tempfile::tempdir().unwrap();
        let a: Vec<u8> = (0..24u8).collect();
        let b: Vec<u8> = (0..6u8).map(|v| v * 3).collect();
        let c: Vec<u8> = (0..16u8).rev().collect();
        let tensors = vec![
            ("zeta", Dtype::U16, vec![3], &b[..]),
            ("alpha", Dtype::F32, vec![2, 3], &a[..]),
            ("mid", Dtype::U32, vec![4], &c[..]),
            ("empty", Dtype::F16, vec![0, 5], &[][..]),
        ];
        let kind = FileKind {
            format: "test",
            version: "1",
            noun: "test",
            file_name: "t.safetensors",
            rewrite_with: "the test",
        };
        let meta = [("extra", "x".to_string())];
        let all_meta = [
            ("version", "1".to_string()),
            ("format", "test".to_string()),
            ("extra", "x".to_string()),
        ];
        let views: Vec<(&str, TensorView)> = tensors
            .iter()
            .map(|(n, d, s, x)| (*n, TensorView::new(*d, s.clone(), x).unwrap()))
            .collect();
        let whole = safetensors::serialize(views, None::<HashMap<String, String>>).unwrap();
        let path = dir.path().join("t.safetensors");
        write(&path, &kind, tensors.clone(), &meta).unwrap();
        assert_eq!(
            std::fs::read(&path).unwrap(),
            with_metadata(&whole, &all_meta).unwrap()
        );
        let mut bad = tensors;
        bad[0].2 = vec![4];
        assert!(matches!(
            write(&path, &kind, bad, &meta),
            Err(Error::Internal(_))
        ));
    }
}
