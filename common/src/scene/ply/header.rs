//! The `.ply` header: the body's encoding, the vertex element's typed properties and their
//! byte offsets, and the scalar-only elements stored before it. Both the decoder and the
//! highlighter lay out a vertex record from this, so it lives apart from either.

use std::io::BufRead;
use std::path::Path;

use crate::{Error, Result};

/// Body encoding declared by the `format` header line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Encoding {
    Ascii,
    BinaryLe,
    BinaryBe,
}

/// A PLY scalar property type.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum ScalarType {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl ScalarType {
    fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "char" | "int8" => ScalarType::I8,
            "uchar" | "uint8" => ScalarType::U8,
            "short" | "int16" => ScalarType::I16,
            "ushort" | "uint16" => ScalarType::U16,
            "int" | "int32" => ScalarType::I32,
            "uint" | "uint32" => ScalarType::U32,
            "float" | "float32" => ScalarType::F32,
            "double" | "float64" => ScalarType::F64,
            _ => return None,
        })
    }

    /// Size in bytes of one value.
    pub(crate) fn size(self) -> usize {
        match self {
            ScalarType::I8 | ScalarType::U8 => 1,
            ScalarType::I16 | ScalarType::U16 => 2,
            ScalarType::I32 | ScalarType::U32 | ScalarType::F32 => 4,
            ScalarType::F64 => 8,
        }
    }

    /// The PLY type name.
    #[cfg(test)]
    pub(crate) fn name(self) -> &'static str {
        match self {
            ScalarType::I8 => "char",
            ScalarType::U8 => "uchar",
            ScalarType::I16 => "short",
            ScalarType::U16 => "ushort",
            ScalarType::I32 => "int",
            ScalarType::U32 => "uint",
            ScalarType::F32 => "float",
            ScalarType::F64 => "double",
        }
    }
}

/// One scalar property of the vertex element.
#[derive(Debug, Clone)]
pub(super) struct Property {
    pub(super) name: String,
    pub(super) ty: ScalarType,
    /// Byte offset inside a binary vertex record.
    pub(super) offset: usize,
}

/// What the header says about the vertex element.
#[derive(Debug)]
pub(super) struct Header {
    pub(super) encoding: Encoding,
    pub(super) vertex_count: usize,
    pub(super) props: Vec<Property>,
    /// Bytes per binary vertex record.
    pub(super) stride: usize,
    /// Bytes of header, up to and including the `end_header` line break.
    pub(super) header_len: usize,
    /// Binary: bytes of the elements stored before `vertex`. ASCII: their number of tokens.
    pub(super) skip_before: usize,
}

impl Header {
    pub(super) fn find(&self, name: &str) -> Option<&Property> {
        self.props.iter().find(|p| p.name == name)
    }

    /// `(byte offset in a vertex record, byte size)` of every property whose name starts with
    /// `prefix`, in header order.
    pub(super) fn byte_ranges(&self, prefix: &str) -> Vec<(usize, usize)> {
        self.props
            .iter()
            .filter(|p| p.name.starts_with(prefix))
            .map(|p| (p.offset, p.ty.size()))
            .collect()
    }
}

struct ElementDecl {
    name: String,
    count: usize,
    props: Vec<(String, ScalarType)>,
    has_list: Option<String>,
}

/// What the header lines declared, up to `end_header`.
#[derive(Default)]
struct Declared {
    encoding: Option<Encoding>,
    elements: Vec<ElementDecl>,
}

impl Declared {
    /// Takes one header line (after the `ply` line); `Ok(true)` at `end_header`.
    fn line(&mut self, path: &Path, text: &str) -> Result<bool> {
        let fmt = |m: String| Error::format(path, m);
        let mut tok = text.split_ascii_whitespace();
        match tok.next() {
            None | Some("comment") | Some("obj_info") => {}
            Some("format") => {
                self.encoding = Some(match tok.next() {
                    Some("ascii") => Encoding::Ascii,
                    Some("binary_little_endian") => Encoding::BinaryLe,
                    Some("binary_big_endian") => Encoding::BinaryBe,
                    other => {
                        return Err(fmt(format!("unknown PLY format {:?}", other.unwrap_or(""))));
                    }
                });
            }
            Some("element") => {
                let name = tok.next().unwrap_or("").to_string();
                let count = tok
                    .next()
                    .and_then(|c| c.parse::<usize>().ok())
                    .ok_or_else(|| fmt(format!("malformed header line `{text}`")))?;
                self.elements.push(ElementDecl {
                    name,
                    count,
                    props: Vec::new(),
                    has_list: None,
                });
            }
            Some("property") => self.property(path, text, tok)?,
            Some("end_header") => return Ok(true),
            Some(other) => {
                return Err(fmt(format!("unknown PLY header keyword `{other}`")));
            }
        }
        Ok(false)
    }

    /// Adds a `property` line (its words after `property` in `tok`) to the last element.
    fn property<'a>(
        &mut self,
        path: &Path,
        text: &str,
        mut tok: impl Iterator<Item = &'a str>,
    ) -> Result<()> {
        let fmt = |m: String| Error::format(path, m);
        let el = self.elements.last_mut().ok_or_else(|| {
            fmt(format!(
                "header line `{text}` comes before any `element` line"
            ))
        })?;
        let ty = tok.next().unwrap_or("");
        if ty == "list" {
            let name = tok.last().unwrap_or("?").to_string();
            el.has_list.get_or_insert(name);
            return Ok(());
        }
        let ty = ScalarType::parse(ty).ok_or_else(|| {
            fmt(format!(
                "unknown property type `{ty}` in header line `{text}`"
            ))
        })?;
        let name = tok
            .next()
            .ok_or_else(|| fmt(format!("malformed header line `{text}`")))?
            .to_string();
        el.props.push((name, ty));
        Ok(())
    }
}

/// Parses the header from `reader` (positioned at the start of the file).
pub(super) fn parse_header(path: &Path, reader: &mut impl BufRead) -> Result<Header> {
    let (declared, header_len) = read_header_lines(path, reader)?;
    let encoding = declared
        .encoding
        .ok_or_else(|| Error::format(path, "PLY header has no `format` line"))?;
    vertex_header(path, encoding, declared.elements, header_len)
}

/// Reads the header lines up to `end_header`: what they declare and the header's length in
/// bytes.
fn read_header_lines(path: &Path, reader: &mut impl BufRead) -> Result<(Declared, usize)> {
    const MAX_HEADER: usize = 1 << 20;
    let fmt = |m: &str| Error::format(path, m);
    let mut line = Vec::new();
    let mut header_len = 0usize;
    let mut declared = Declared::default();
    let mut first = true;
    loop {
        line.clear();
        let n = reader
            .read_until(b'\n', &mut line)
            .map_err(|e| Error::io(path, e))?;
        if n == 0 {
            return Err(fmt(
                "PLY header has no `end_header` line (file truncated or not a PLY)",
            ));
        }
        header_len += n;
        if header_len > MAX_HEADER {
            return Err(fmt(
                "PLY header longer than 1 MiB without `end_header`: not a PLY file",
            ));
        }
        let text = String::from_utf8_lossy(&line);
        let text = text.trim();
        if first {
            if text != "ply" {
                return Err(fmt(
                    "not a PLY file (first line is not `ply`); pass the 3DGS `point_cloud.ply`",
                ));
            }
            first = false;
            continue;
        }
        if declared.line(path, text)? {
            return Ok((declared, header_len));
        }
    }
}

/// The vertex element's layout: its properties' offsets, and the bytes (binary) or values
/// (ASCII) of the scalar-only elements before it, which the body reader skips.
fn vertex_header(
    path: &Path,
    encoding: Encoding,
    elements: Vec<ElementDecl>,
    header_len: usize,
) -> Result<Header> {
    let fmt = |m: String| Error::format(path, m);
    let mut skip_before = 0usize;
    for el in elements {
        if el.name == "vertex" {
            if let Some(list) = el.has_list {
                return Err(fmt(format!(
                    "vertex property `{list}` is a list; a 3DGS .ply has only scalar vertex \
                     properties (export it with the INRIA layout)"
                )));
            }
            let mut props = Vec::with_capacity(el.props.len());
            let mut offset = 0usize;
            for (name, ty) in el.props {
                props.push(Property { name, ty, offset });
                offset += ty.size();
            }
            return Ok(Header {
                encoding,
                vertex_count: el.count,
                props,
                stride: offset,
                header_len,
                skip_before,
            });
        }
        if let Some(list) = el.has_list {
            return Err(Error::Unsupported {
                path: path.into(),
                message: format!(
                    "element `{}` (before `vertex`) has list property `{list}`; only a vertex \
                     element first, or scalar-only elements before it, are supported",
                    el.name
                ),
            });
        }
        let per = match encoding {
            Encoding::Ascii => el.props.len(),
            _ => el.props.iter().map(|(_, t)| t.size()).sum(),
        };
        skip_before = el
            .count
            .checked_mul(per)
            .and_then(|b| b.checked_add(skip_before))
            .ok_or_else(|| fmt("element sizes overflow".into()))?;
    }
    Err(fmt(
        "PLY header has no `element vertex`: not a point/Gaussian file".into(),
    ))
}

/// The error for a body shorter than `header` declares (`have` bytes in all).
pub(super) fn truncated(path: &Path, header: &Header, have: u64) -> Error {
    Error::format(
        path,
        format!(
            "truncated: the header declares {} vertices of {} bytes (+{} bytes of earlier \
             elements) after a {}-byte header, but the file has {have} bytes; re-copy or re-export \
             the .ply",
            header.vertex_count, header.stride, header.skip_before, header.header_len
        ),
    )
}
