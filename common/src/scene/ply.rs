//! INRIA `.ply` reading and writing.
//!
//! The header is parsed into a list of named, typed vertex properties; the body is then decoded
//! with fixed per-property byte offsets (binary) or fixed token positions (ASCII), in large chunks,
//! keeping only the columns the caller asked for.

use std::fs::File;
use std::io::{BufRead, BufReader, Read};
use std::path::Path;

use rayon::prelude::*;

use super::{Gaussians, PlyLoadOptions, SH_C0, ShCoeffs};
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
struct Property {
    name: String,
    ty: ScalarType,
    /// Byte offset inside a binary vertex record.
    offset: usize,
}

/// What the header says about the vertex element.
#[derive(Debug)]
struct Header {
    encoding: Encoding,
    vertex_count: usize,
    props: Vec<Property>,
    /// Bytes per binary vertex record.
    stride: usize,
    /// Bytes of header, up to and including the `end_header` line break.
    header_len: usize,
    /// Binary: bytes of the elements stored before `vertex`. ASCII: their number of tokens.
    skip_before: usize,
}

impl Header {
    fn find(&self, name: &str) -> Option<&Property> {
        self.props.iter().find(|p| p.name == name)
    }

    /// `(byte offset in a vertex record, byte size)` of every property whose name starts with
    /// `prefix`, in header order.
    fn byte_ranges(&self, prefix: &str) -> Vec<(usize, usize)> {
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
fn parse_header(path: &Path, reader: &mut impl BufRead) -> Result<Header> {
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

/// Reads one binary scalar at `off` of `rec` as f64.
#[inline(always)]
fn read_scalar(rec: &[u8], off: usize, ty: ScalarType, big_endian: bool) -> f64 {
    macro_rules! rd {
        ($t:ty, $n:expr) => {{
            let mut b = [0u8; $n];
            b.copy_from_slice(&rec[off..off + $n]);
            if big_endian {
                <$t>::from_be_bytes(b) as f64
            } else {
                <$t>::from_le_bytes(b) as f64
            }
        }};
    }
    match ty {
        ScalarType::I8 => rec[off] as i8 as f64,
        ScalarType::U8 => rec[off] as f64,
        ScalarType::I16 => rd!(i16, 2),
        ScalarType::U16 => rd!(u16, 2),
        ScalarType::I32 => rd!(i32, 4),
        ScalarType::U32 => rd!(u32, 4),
        ScalarType::F32 => rd!(f32, 4),
        ScalarType::F64 => rd!(f64, 8),
    }
}

/// The columns to decode, in the order [`Builder::push`] expects them.
struct Columns {
    names: Vec<String>,
    /// Index of each needed column in `Header::props`.
    prop_index: Vec<usize>,
    /// Number of `f_rest_*` columns (0 without colours).
    rest: usize,
    colours: bool,
}

fn select_columns(path: &Path, header: &Header, options: PlyLoadOptions) -> Result<Columns> {
    let mut names: Vec<String> = ["x", "y", "z", "scale_0", "scale_1", "scale_2"]
        .iter()
        .chain(["rot_0", "rot_1", "rot_2", "rot_3", "opacity"].iter())
        .map(|s| s.to_string())
        .collect();
    let mut rest = 0;
    if options.colours {
        names.extend(["f_dc_0", "f_dc_1", "f_dc_2"].iter().map(|s| s.to_string()));
        rest = header
            .props
            .iter()
            .filter(|p| p.name.starts_with("f_rest_"))
            .count();
        if !matches!(rest, 0 | 9 | 24 | 45) {
            return Err(Error::format(
                path,
                format!(
                    "{rest} `f_rest_*` properties: an SH degree 1, 2 or 3 scene has 9, 24 or 45 \
                     (3 x ((degree+1)^2 - 1)); the file is not an INRIA-layout 3DGS .ply"
                ),
            ));
        }
        names.extend((0..rest).map(|k| format!("f_rest_{k}")));
    }
    let mut prop_index = Vec::with_capacity(names.len());
    let mut missing = Vec::new();
    for n in &names {
        match header.props.iter().position(|p| &p.name == n) {
            Some(i) => prop_index.push(i),
            None => missing.push(n.as_str()),
        }
    }
    if !missing.is_empty() {
        let have: Vec<&str> = header.props.iter().map(|p| p.name.as_str()).collect();
        return Err(Error::format(
            path,
            format!(
                "missing vertex properties {missing:?} (found {have:?}); a 3DGS .ply in the INRIA \
                 layout needs x y z scale_0..2 rot_0..3 opacity{}",
                if options.colours {
                    " f_dc_0..2 (and f_rest_* for SH degree > 0)"
                } else {
                    ""
                }
            ),
        ));
    }
    Ok(Columns {
        names,
        prop_index,
        rest,
        colours: options.colours,
    })
}

/// The largest f32 below 1 (`1 - 2^-24`): activated opacities are clamped to it.
pub(crate) const OPACITY_MAX: f32 = 1.0 - 1.0 / 16_777_216.0;

/// Accumulates activated Gaussians.
struct Builder<'a> {
    path: &'a Path,
    cols: &'a Columns,
    out: Gaussians,
    coeffs: Vec<f32>,
    degree: u8,
}

impl<'a> Builder<'a> {
    fn new(path: &'a Path, cols: &'a Columns, n: usize) -> Self {
        let degree = match cols.rest {
            0 => 0,
            9 => 1,
            24 => 2,
            _ => 3,
        };
        let per = (degree as usize + 1).pow(2);
        Builder {
            path,
            cols,
            out: Gaussians {
                means: Vec::with_capacity(n),
                scales: Vec::with_capacity(n),
                rotations: Vec::with_capacity(n),
                opacities: Vec::with_capacity(n),
                sh: None,
            },
            coeffs: if cols.colours {
                Vec::with_capacity(n * per * 3)
            } else {
                Vec::new()
            },
            degree,
        }
    }

    /// `v` holds the raw values of vertex `i` in `Columns::names` order.
    #[inline]
    fn push(&mut self, i: usize, v: &[f64]) -> Result<()> {
        // Every value is stored as f32: one beyond the f32 range (an ASCII or `double` property
        // like 1e39) would become ±inf after the conversion, so it is rejected like a NaN.
        if let Some(j) = v.iter().position(|&x| !(x as f32).is_finite()) {
            return Err(Error::format(
                self.path,
                format!(
                    "vertex {i}: property `{}` is {} (non-finite or beyond the f32 range); the \
                     scene is corrupt (diverged training?); re-export or retrain it",
                    self.cols.names[j], v[j]
                ),
            ));
        }
        let mut scale = [0f32; 3];
        for k in 0..3 {
            let s = v[3 + k].exp() as f32;
            if !s.is_finite() {
                return Err(Error::format(
                    self.path,
                    format!(
                        "vertex {i}: scale_{k} = {} overflows exp(); scales must be stored as \
                         logarithms (INRIA layout)",
                        v[3 + k]
                    ),
                ));
            }
            scale[k] = s;
        }
        let q = [v[6], v[7], v[8], v[9]];
        let norm = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
        if norm == 0.0 || !norm.is_finite() {
            return Err(Error::format(
                self.path,
                format!(
                    "vertex {i}: rot_0..3 is the zero quaternion, which is not a rotation; \
                     the scene is corrupt"
                ),
            ));
        }
        let opacity = 1.0 / (1.0 + (-v[10]).exp());
        self.out.means.push([v[0] as f32, v[1] as f32, v[2] as f32]);
        self.out.scales.push(scale);
        self.out.rotations.push([
            (q[0] / norm) as f32,
            (q[1] / norm) as f32,
            (q[2] / norm) as f32,
            (q[3] / norm) as f32,
        ]);
        // Keep sigmoid's open interval in f32: logits beyond ~±16.6 / -103 would round to 1 / 0.
        self.out
            .opacities
            .push((opacity as f32).clamp(f32::MIN_POSITIVE, OPACITY_MAX));
        if self.cols.colours {
            // DC, then rest coefficient j of channel c at f_rest_{c*per_rest + j}.
            self.coeffs
                .extend([v[11] as f32, v[12] as f32, v[13] as f32]);
            let per_rest = self.cols.rest / 3;
            let rest = &v[14..];
            for j in 0..per_rest {
                for c in 0..3 {
                    self.coeffs.push(rest[c * per_rest + j] as f32);
                }
            }
        }
        Ok(())
    }

    /// Appends the Gaussians decoded by `other` (the vertices following this builder's).
    fn append(&mut self, mut other: Builder<'_>) {
        self.out.means.append(&mut other.out.means);
        self.out.scales.append(&mut other.out.scales);
        self.out.rotations.append(&mut other.out.rotations);
        self.out.opacities.append(&mut other.out.opacities);
        self.coeffs.append(&mut other.coeffs);
    }

    fn finish(mut self) -> Gaussians {
        if self.cols.colours {
            self.out.sh = Some(ShCoeffs {
                degree: self.degree,
                coeffs: self.coeffs,
            });
        }
        self.out
    }
}

pub(super) fn read(path: &Path, options: PlyLoadOptions) -> Result<Gaussians> {
    let file = File::open(path).map_err(|e| Error::io(path, e))?;
    let file_len = file.metadata().map_err(|e| Error::io(path, e))?.len();
    let mut reader = BufReader::with_capacity(1 << 16, file);
    let header = parse_header(path, &mut reader)?;
    let cols = select_columns(path, &header, options)?;
    match header.encoding {
        Encoding::Ascii => read_ascii(path, &header, &cols, reader),
        _ => read_binary(path, &header, &cols, reader, file_len),
    }
}

/// [`read`] on bytes already in memory; `path` only names them in errors.
pub(super) fn read_bytes(path: &Path, bytes: &[u8], options: PlyLoadOptions) -> Result<Gaussians> {
    let mut reader = std::io::Cursor::new(bytes);
    let header = parse_header(path, &mut reader)?;
    let cols = select_columns(path, &header, options)?;
    match header.encoding {
        Encoding::Ascii => read_ascii(path, &header, &cols, reader),
        _ => read_binary(path, &header, &cols, reader, bytes.len() as u64),
    }
}

fn truncated(path: &Path, header: &Header, have: u64) -> Error {
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

fn read_binary(
    path: &Path,
    header: &Header,
    cols: &Columns,
    mut reader: impl Read,
    file_len: u64,
) -> Result<Gaussians> {
    let n = header.vertex_count;
    let stride = header.stride;
    let needed = (n as u64)
        .checked_mul(stride as u64)
        .and_then(|b| b.checked_add((header.header_len + header.skip_before) as u64));
    match needed {
        Some(b) if b <= file_len => {}
        _ => return Err(truncated(path, header, file_len)),
    }
    let be = header.encoding == Encoding::BinaryBe;
    std::io::copy(
        &mut (&mut reader).take(header.skip_before as u64),
        &mut std::io::sink(),
    )
    .map_err(|e| Error::io(path, e))?;
    let layout: Vec<(usize, ScalarType)> = cols
        .prop_index
        .iter()
        .map(|&p| (header.props[p].offset, header.props[p].ty))
        .collect();
    let mut builder = Builder::new(path, cols, n);
    let chunk_vertices = ((32usize << 20) / stride.max(1)).max(1);
    let mut buf = vec![0u8; chunk_vertices.min(n.max(1)) * stride];
    // Each chunk is decoded in parallel slices; the slices are appended in order, and the first
    // error in vertex order is returned.
    let slice_vertices = chunk_vertices
        .div_ceil(4 * rayon::current_num_threads().max(1))
        .max(4096);
    let mut done = 0usize;
    while done < n {
        let count = chunk_vertices.min(n - done);
        let bytes = &mut buf[..count * stride];
        reader.read_exact(bytes).map_err(|e| {
            if e.kind() == std::io::ErrorKind::UnexpectedEof {
                truncated(path, header, file_len)
            } else {
                Error::io(path, e)
            }
        })?;
        let parts: Vec<Result<Builder>> = bytes
            .par_chunks(slice_vertices * stride)
            .enumerate()
            .map(|(p, slice)| {
                let first = done + p * slice_vertices;
                let mut part = Builder::new(path, cols, slice.len() / stride);
                let mut vals = vec![0f64; layout.len()];
                for (k, rec) in slice.chunks_exact(stride).enumerate() {
                    for (v, &(off, ty)) in vals.iter_mut().zip(&layout) {
                        *v = read_scalar(rec, off, ty, be);
                    }
                    part.push(first + k, &vals)?;
                }
                Ok(part)
            })
            .collect();
        for part in parts {
            builder.append(part?);
        }
        done += count;
    }
    Ok(builder.finish())
}

fn read_ascii(
    path: &Path,
    header: &Header,
    cols: &Columns,
    mut reader: impl Read,
) -> Result<Gaussians> {
    let mut body = String::new();
    reader
        .read_to_string(&mut body)
        .map_err(|e| match e.kind() {
            std::io::ErrorKind::InvalidData => Error::format(
                path,
                "ASCII PLY body is not valid text (wrong `format` line?)",
            ),
            _ => Error::io(path, e),
        })?;
    let mut tokens = body.split_ascii_whitespace();
    for _ in 0..header.skip_before {
        if tokens.next().is_none() {
            return Err(Error::format(
                path,
                "truncated: the elements before `vertex` are incomplete",
            ));
        }
    }
    // slot[p] = position in `vals` of property p, if needed.
    let mut slot = vec![usize::MAX; header.props.len()];
    for (k, &p) in cols.prop_index.iter().enumerate() {
        slot[p] = k;
    }
    let n = header.vertex_count;
    let mut builder = Builder::new(path, cols, n.min(1 << 24));
    let mut vals = vec![0f64; cols.prop_index.len()];
    for i in 0..n {
        for (p, &s) in slot.iter().enumerate() {
            let tok = tokens.next().ok_or_else(|| {
                Error::format(
                    path,
                    format!(
                        "truncated: vertex {i} of {n} ends before property `{}`; re-export the .ply",
                        header.props[p].name
                    ),
                )
            })?;
            if s != usize::MAX {
                vals[s] = tok.parse::<f64>().map_err(|_| {
                    Error::format(
                        path,
                        format!(
                            "vertex {i}: property `{}` is `{tok}`, not a number",
                            header.props[p].name
                        ),
                    )
                })?;
            }
        }
        builder.push(i, &vals)?;
    }
    Ok(builder.finish())
}

/// See [`super::write_highlighted_ply`].
pub(super) fn write_highlighted(
    src: &Path,
    dst: &Path,
    colour_of: impl Fn(usize) -> Option<[f32; 3]>,
) -> Result<()> {
    let mut bytes = std::fs::read(src).map_err(|e| Error::io(src, e))?;
    let header = parse_header(src, &mut &bytes[..])?;
    if header.encoding == Encoding::Ascii {
        return Err(Error::Unsupported {
            path: src.into(),
            message: "highlighting needs a binary .ply; this one is ASCII (convert it to \
                      binary_little_endian first)"
                .into(),
        });
    }
    let mut dc = Vec::with_capacity(3);
    for c in 0..3 {
        let name = format!("f_dc_{c}");
        let p = header.find(&name).ok_or_else(|| {
            Error::format(
                src,
                format!("no `{name}` property: the .ply has no SH colours to set"),
            )
        })?;
        if !matches!(p.ty, ScalarType::F32 | ScalarType::F64) {
            return Err(Error::Unsupported {
                path: src.into(),
                message: format!(
                    "`{name}` is stored as {:?}; only float/double SH can be set",
                    p.ty
                ),
            });
        }
        dc.push((p.offset, p.ty));
    }
    let rest = header.byte_ranges("f_rest_");
    let start = header.header_len + header.skip_before;
    let end = header
        .vertex_count
        .checked_mul(header.stride)
        .and_then(|b| b.checked_add(start))
        .filter(|&e| e <= bytes.len())
        .ok_or_else(|| truncated(src, &header, bytes.len() as u64))?;
    let be = header.encoding == Encoding::BinaryBe;
    for (i, rec) in bytes[start..end]
        .chunks_exact_mut(header.stride.max(1))
        .enumerate()
    {
        let Some(rgb) = colour_of(i) else { continue };
        if rgb.iter().any(|c| !c.is_finite()) {
            return Err(Error::param(
                "colour",
                format!("{rgb:?} (vertex {i})"),
                "finite RGB components",
            ));
        }
        for (c, &(off, ty)) in dc.iter().enumerate() {
            let v = (rgb[c] as f64 - 0.5) / SH_C0;
            match (ty, be) {
                (ScalarType::F64, false) => rec[off..off + 8].copy_from_slice(&v.to_le_bytes()),
                (ScalarType::F64, true) => rec[off..off + 8].copy_from_slice(&v.to_be_bytes()),
                (_, false) => rec[off..off + 4].copy_from_slice(&(v as f32).to_le_bytes()),
                (_, true) => rec[off..off + 4].copy_from_slice(&(v as f32).to_be_bytes()),
            }
        }
        for &(off, size) in &rest {
            rec[off..off + size].fill(0);
        }
    }
    crate::io::write_atomic(dst, &bytes)
}

/// See [`super::float_vertex_header`].
pub(crate) fn float_vertex_header<S: AsRef<str>>(
    n: usize,
    names: &[S],
    comment: Option<&str>,
) -> Vec<u8> {
    let mut out = String::from("ply\nformat binary_little_endian 1.0\n");
    if let Some(c) = comment {
        out.push_str(&format!("comment {}\n", c.replace(['\n', '\r'], " ")));
    }
    out.push_str(&format!("element vertex {n}\n"));
    for name in names {
        out.push_str(&format!("property float {}\n", name.as_ref()));
    }
    out.push_str("end_header\n");
    out.into_bytes()
}

/// See [`super::write_ply`].
pub(super) fn write(path: &Path, g: &Gaussians) -> Result<()> {
    let n = g.len();
    if g.scales.len() != n || g.rotations.len() != n || g.opacities.len() != n {
        return Err(Error::internal(format!(
            "write_ply: inconsistent lengths (means {n}, scales {}, rotations {}, opacities {})",
            g.scales.len(),
            g.rotations.len(),
            g.opacities.len()
        )));
    }
    let per = g.sh.as_ref().map(|s| s.per_channel()).unwrap_or(0);
    if let Some(sh) = &g.sh
        && (sh.degree > 3 || sh.coeffs.len() != n * per * 3)
    {
        return Err(Error::internal(format!(
            "write_ply: SH degree {} with {} coefficients for {n} Gaussians",
            sh.degree,
            sh.coeffs.len()
        )));
    }
    let mut names: Vec<String> = ["x", "y", "z"].iter().map(|s| s.to_string()).collect();
    if per > 0 {
        names.extend((0..3).map(|c| format!("f_dc_{c}")));
        names.extend((0..3 * (per - 1)).map(|k| format!("f_rest_{k}")));
    }
    names.push("opacity".into());
    names.extend((0..3).map(|k| format!("scale_{k}")));
    names.extend((0..4).map(|k| format!("rot_{k}")));
    let mut bytes = float_vertex_header(n, &names, None);
    bytes.reserve(n * names.len() * 4);
    let mut put = |v: f64| bytes.extend_from_slice(&(v as f32).to_le_bytes());
    for i in 0..n {
        g.means[i].iter().for_each(|&v| put(v as f64));
        if let Some(sh) = &g.sh {
            let c = &sh.coeffs[i * per * 3..(i + 1) * per * 3];
            (0..3).for_each(|ch| put(c[ch] as f64));
            for ch in 0..3 {
                (1..per).for_each(|j| put(c[j * 3 + ch] as f64));
            }
        }
        let o = (g.opacities[i] as f64).clamp(f32::MIN_POSITIVE as f64, OPACITY_MAX as f64);
        put((o / (1.0 - o)).ln());
        g.scales[i]
            .iter()
            .for_each(|&s| put((s as f64).max(1e-30).ln()));
        g.rotations[i].iter().for_each(|&q| put(q as f64));
    }
    crate::io::write_atomic(path, &bytes)
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;
    use crate::scene::{load_ply, write_highlighted_ply, write_ply};

    /// Independent test writer: any encoding, any property list, values given as f64 per row.
    pub(crate) fn encode(
        enc: Encoding,
        props: &[(&str, ScalarType)],
        rows: &[Vec<f64>],
    ) -> Vec<u8> {
        let fmt = match enc {
            Encoding::Ascii => "ascii",
            Encoding::BinaryLe => "binary_little_endian",
            Encoding::BinaryBe => "binary_big_endian",
        };
        let mut h = format!(
            "ply\nformat {fmt} 1.0\ncomment test\nelement vertex {}\n",
            rows.len()
        );
        for (n, t) in props {
            h.push_str(&format!("property {} {n}\n", t.name()));
        }
        h.push_str("end_header\n");
        let mut out = h.into_bytes();
        for row in rows {
            if enc == Encoding::Ascii {
                let toks: Vec<String> = row
                    .iter()
                    .zip(props)
                    .map(|(v, (_, t))| match t {
                        ScalarType::F32 => format!("{}", *v as f32),
                        ScalarType::F64 => format!("{v}"),
                        _ => format!("{}", *v as i64),
                    })
                    .collect();
                out.extend_from_slice(toks.join(" ").as_bytes());
                out.push(b'\n');
                continue;
            }
            let be = enc == Encoding::BinaryBe;
            for (v, (_, t)) in row.iter().zip(props) {
                macro_rules! put {
                    ($x:expr) => {{
                        let x = $x;
                        out.extend_from_slice(&if be { x.to_be_bytes() } else { x.to_le_bytes() })
                    }};
                }
                match t {
                    ScalarType::I8 => put!(*v as i8),
                    ScalarType::U8 => put!(*v as u8),
                    ScalarType::I16 => put!(*v as i16),
                    ScalarType::U16 => put!(*v as u16),
                    ScalarType::I32 => put!(*v as i32),
                    ScalarType::U32 => put!(*v as u32),
                    ScalarType::F32 => put!(*v as f32),
                    ScalarType::F64 => put!(*v),
                }
            }
        }
        out
    }

    /// Deterministic pseudo-random values in [-2, 2), exactly representable as f32.
    struct Lcg(u64);
    impl Lcg {
        fn next(&mut self) -> f64 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (((self.0 >> 40) as f64 / (1u64 << 24) as f64) * 4.0 - 2.0) as f32 as f64
        }
    }

    /// INRIA property list (with normals) for SH degree `deg`.
    fn inria_props(deg: usize) -> Vec<(String, ScalarType)> {
        let mut names: Vec<String> = [
            "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        names.extend((0..3 * ((deg + 1) * (deg + 1) - 1)).map(|k| format!("f_rest_{k}")));
        names.push("opacity".into());
        names.extend((0..3).map(|k| format!("scale_{k}")));
        names.extend((0..4).map(|k| format!("rot_{k}")));
        names.into_iter().map(|n| (n, ScalarType::F32)).collect()
    }

    fn rows(props: &[(String, ScalarType)], n: usize, seed: u64) -> Vec<Vec<f64>> {
        let mut r = Lcg(seed);
        (0..n)
            .map(|_| {
                props
                    .iter()
                    .map(|(_, t)| match t {
                        ScalarType::F32 | ScalarType::F64 => r.next(),
                        _ => (r.next() * 2.0).round().abs(),
                    })
                    .collect()
            })
            .collect()
    }

    /// Independently computed expectation for `rows` of `props`.
    fn check(g: &Gaussians, props: &[(String, ScalarType)], rows: &[Vec<f64>], colours: bool) {
        let get = |i: usize, n: &str| {
            let p = props
                .iter()
                .position(|(name, _)| name == n)
                .expect("property in test");
            rows[i][p]
        };
        assert_eq!(g.len(), rows.len());
        for i in 0..rows.len() {
            for k in 0..3 {
                assert_eq!(g.means[i][k], get(i, ["x", "y", "z"][k]) as f32);
                let s = get(i, &format!("scale_{k}")).exp() as f32;
                assert!(
                    (g.scales[i][k] - s).abs() <= 1e-6 * s,
                    "{} vs {s}",
                    g.scales[i][k]
                );
            }
            let q: Vec<f64> = (0..4).map(|k| get(i, &format!("rot_{k}"))).collect();
            let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
            for k in 0..4 {
                assert!((g.rotations[i][k] as f64 - q[k] / n).abs() < 1e-6);
            }
            let o = 1.0 / (1.0 + (-get(i, "opacity")).exp());
            assert!((g.opacities[i] as f64 - o).abs() < 1e-6);
        }
        if !colours {
            assert!(g.sh.is_none());
            return;
        }
        let sh = g.sh.as_ref().expect("colours requested");
        let rest = props
            .iter()
            .filter(|(n, _)| n.starts_with("f_rest_"))
            .count();
        let per = rest / 3 + 1;
        assert_eq!(sh.per_channel(), per);
        assert_eq!(sh.coeffs.len(), rows.len() * per * 3);
        for i in 0..rows.len() {
            for c in 0..3 {
                assert_eq!(sh.dc(i)[c], get(i, &format!("f_dc_{c}")) as f32);
                for j in 1..per {
                    let want = get(i, &format!("f_rest_{}", c * (per - 1) + j - 1)) as f32;
                    assert_eq!(
                        sh.coeffs[(i * per + j) * 3 + c],
                        want,
                        "vertex {i} coeff {j} ch {c}"
                    );
                }
            }
        }
    }

    fn write_tmp(bytes: &[u8]) -> (tempfile::TempDir, std::path::PathBuf) {
        let dir = tempfile::tempdir().expect("tempdir");
        let p = dir.path().join("s.ply");
        std::fs::write(&p, bytes).expect("write");
        (dir, p)
    }

    /// Asserts that `bytes` (written to a temporary file) load, with colours, as `rows` of
    /// `props` ([`check`]).
    fn assert_loads_as(bytes: &[u8], props: &[(String, ScalarType)], rows: &[Vec<f64>]) {
        let (_d, p) = write_tmp(bytes);
        let g = load_ply(&p, PlyLoadOptions { colours: true }).expect("loads");
        check(&g, props, rows, true);
    }

    /// Asserts that `bytes` (written to a temporary file) do not load with `opts`, and that the
    /// error message names every one of `names` (the vertex, the property...).
    fn assert_load_error(bytes: &[u8], opts: PlyLoadOptions, names: &[&str]) {
        let (_d, p) = write_tmp(bytes);
        let msg = load_ply(&p, opts)
            .expect_err("a bad .ply must not load")
            .to_string();
        for name in names {
            assert!(msg.contains(name), "{name:?} not in {msg}");
        }
    }

    /// For a file whose only fault is in the colours: asserts that it loads without colours, and
    /// [`assert_load_error`] with them.
    fn assert_colour_error(bytes: &[u8], names: &[&str]) {
        let (_d, p) = write_tmp(bytes);
        assert!(load_ply(&p, PlyLoadOptions { colours: false }).is_ok());
        assert_load_error(bytes, PlyLoadOptions { colours: true }, names);
    }

    /// Index of property `name` in `props`.
    fn column(props: &[(String, ScalarType)], name: &str) -> usize {
        props
            .iter()
            .position(|(n, _)| n == name)
            .unwrap_or_else(|| panic!("no property {name}"))
    }

    /// `rows` of `props` as a `.ply` in each of [`ENCODINGS`].
    fn each_encoding<'a>(
        props: &'a [(String, ScalarType)],
        rows: &'a [Vec<f64>],
    ) -> impl Iterator<Item = (Encoding, Vec<u8>)> + 'a {
        ENCODINGS
            .into_iter()
            .map(move |enc| (enc, encode(enc, &refs(props), rows)))
    }

    /// `rows` of `props` as a binary little-endian `.ply`.
    fn binary_le(props: &[(String, ScalarType)], rows: &[Vec<f64>]) -> Vec<u8> {
        encode(Encoding::BinaryLe, &refs(props), rows)
    }

    fn refs(props: &[(String, ScalarType)]) -> Vec<(&str, ScalarType)> {
        props.iter().map(|(n, t)| (n.as_str(), *t)).collect()
    }

    const ENCODINGS: [Encoding; 3] = [Encoding::BinaryLe, Encoding::BinaryBe, Encoding::Ascii];

    #[test]
    fn round_trip_every_encoding_and_sh_degree() {
        for enc in ENCODINGS {
            for deg in 0..=3 {
                let props = inria_props(deg);
                let rows = rows(&props, 37, deg as u64 + 11);
                let (_d, p) = write_tmp(&encode(enc, &refs(&props), &rows));
                for colours in [false, true] {
                    let g = load_ply(&p, PlyLoadOptions { colours }).expect("loads");
                    check(&g, &props, &rows, colours);
                    if colours {
                        assert_eq!(g.sh.as_ref().map(|s| s.degree), Some(deg as u8), "{enc:?}");
                    }
                }
            }
        }
    }

    #[test]
    fn reordered_extra_and_mixed_type_properties() {
        let mut props = inria_props(1);
        props.reverse();
        props.insert(5, ("red".into(), ScalarType::U8));
        props.push(("flags".into(), ScalarType::I32));
        props.push(("weight".into(), ScalarType::I16));
        for (n, t) in props.iter_mut() {
            if ["x", "opacity", "f_dc_1", "f_rest_4", "rot_2"].contains(&n.as_str()) {
                *t = ScalarType::F64;
            }
            if n == "scale_0" {
                *t = ScalarType::I8; // integer log-scale, converted
            }
        }
        let mut rows = rows(&props, 23, 5);
        let xi = column(&props, "x");
        rows[3][xi] = 1.0 + 1e-12; // only representable as double
        for (_, bytes) in each_encoding(&props, &rows) {
            assert_loads_as(&bytes, &props, &rows);
        }
    }

    #[test]
    fn non_finite_value_names_vertex_and_property() {
        let props = inria_props(0);
        for (enc, bad) in [
            (Encoding::BinaryLe, f64::NAN),
            (Encoding::BinaryBe, f64::INFINITY),
            (Encoding::Ascii, f64::NAN),
        ] {
            let mut rows = rows(&props, 10, 3);
            let s1 = column(&props, "scale_1");
            rows[7][s1] = bad;
            let (_d, p) = write_tmp(&encode(enc, &refs(&props), &rows));
            let err = load_ply(&p, PlyLoadOptions::default()).expect_err("must fail");
            let msg = err.to_string();
            assert!(matches!(err, Error::Format { .. }), "{msg}");
            assert!(msg.contains("vertex 7") && msg.contains("scale_1"), "{msg}");
        }
        // A NaN in an SH column matters only when colours are loaded.
        let mut rows = rows(&props, 4, 3);
        let dc = column(&props, "f_dc_2");
        rows[2][dc] = f64::NAN;
        assert_colour_error(&binary_le(&props, &rows), &["vertex 2", "f_dc_2"]);
    }

    #[test]
    fn a_value_beyond_the_f32_range_is_rejected_not_stored_as_infinity() {
        // Found by `fuzz/` (target `ply`): an ASCII x of -1.6e118 parsed as a finite f64 and became
        // -inf in the f32 means.
        let crash = include_bytes!("../../tests/data/fuzz-ply-beyond-f32.ply");
        let path = Path::new("fuzz-ply-beyond-f32.ply");
        for colours in [false, true] {
            let err = crate::scene::load_ply_bytes(crash, path, PlyLoadOptions { colours })
                .expect_err("a mean beyond f32 must be rejected");
            let msg = err.to_string();
            assert!(matches!(err, Error::Format { .. }), "{msg}");
            assert!(msg.contains("vertex 1") && msg.contains("`x`"), "{msg}");
        }
        // The same through a binary `double` property, and for an SH coefficient.
        let props: Vec<(String, ScalarType)> = inria_props(0)
            .into_iter()
            .map(|(n, _)| (n, ScalarType::F64))
            .collect();
        for (name, value) in [("y", 1e39), ("f_dc_1", -4e38)] {
            let mut rows = rows(&props, 3, 5);
            let k = column(&props, name);
            rows[2][k] = value;
            let bytes = binary_le(&props, &rows);
            let err = crate::scene::load_ply_bytes(&bytes, path, PlyLoadOptions { colours: true })
                .expect_err("beyond f32");
            assert!(err.to_string().contains("vertex 2"), "{err}");
            // In memory and from a file alike.
            let (_d, p) = write_tmp(&bytes);
            assert!(load_ply(&p, PlyLoadOptions { colours: true }).is_err());
        }
    }

    #[test]
    fn many_vertices_decode_in_order_and_report_the_first_error() {
        // Enough vertices for several parallel slices per chunk.
        let props = inria_props(1);
        let mut rows = rows(&props, 100_000, 77);
        assert_loads_as(&binary_le(&props, &rows), &props, &rows);
        let op = column(&props, "opacity");
        rows[90_000][op] = f64::NAN;
        rows[50_000][op] = f64::INFINITY;
        assert_load_error(
            &binary_le(&props, &rows),
            PlyLoadOptions::default(),
            &["vertex 50000", "opacity"],
        );
    }

    #[test]
    fn zero_quaternion_names_vertex() {
        let props = inria_props(0);
        let mut rows = rows(&props, 6, 9);
        for k in 0..4 {
            let r = column(&props, &format!("rot_{k}"));
            rows[4][r] = 0.0;
        }
        assert_load_error(
            &binary_le(&props, &rows),
            PlyLoadOptions::default(),
            &["vertex 4", "quaternion"],
        );
    }

    #[test]
    fn missing_property_is_named() {
        let props: Vec<_> = inria_props(0)
            .into_iter()
            .filter(|(n, _)| n != "rot_3")
            .collect();
        let rows = rows(&props, 3, 1);
        assert_load_error(
            &binary_le(&props, &rows),
            PlyLoadOptions::default(),
            &["rot_3"],
        );
        // Colours requested from a geometry-only file.
        let props: Vec<_> = inria_props(0)
            .into_iter()
            .filter(|(n, _)| !n.starts_with("f_dc"))
            .collect();
        let rows = self::rows(&props, 3, 1);
        assert_colour_error(&binary_le(&props, &rows), &["f_dc_0"]);
    }

    #[test]
    fn bad_f_rest_count_is_an_error_only_with_colours() {
        let props: Vec<_> = inria_props(1)
            .into_iter()
            .filter(|(n, _)| n != "f_rest_8" && n != "f_rest_7")
            .collect();
        let rows = rows(&props, 3, 1);
        assert_colour_error(&binary_le(&props, &rows), &["7 `f_rest_*`"]);
    }

    #[test]
    fn list_property_is_rejected() {
        let text = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n\
                    property list uchar int vertex_indices\nend_header\n1 1 0\n";
        assert_load_error(
            text.as_bytes(),
            PlyLoadOptions::default(),
            &["vertex_indices", "list"],
        );
    }

    #[test]
    fn truncated_body_is_a_format_error() {
        let props = inria_props(2);
        let rows = rows(&props, 20, 2);
        for (enc, bytes) in each_encoding(&props, &rows) {
            for cut in [1usize, 17, bytes.len() / 3] {
                let mut end = bytes.len() - cut;
                if enc == Encoding::Ascii {
                    // A cut inside a number still leaves a number: cut whole tokens.
                    end = bytes[..end]
                        .iter()
                        .rposition(|&b| b == b' ')
                        .expect("space");
                }
                let (_d, p) = write_tmp(&bytes[..end]);
                let err = load_ply(&p, PlyLoadOptions { colours: true }).expect_err("truncated");
                assert!(matches!(err, Error::Format { .. }), "{err}");
                assert!(err.to_string().contains("truncated"), "{err}");
            }
        }
        let (_d, p) = write_tmp(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n");
        assert!(load_ply(&p, PlyLoadOptions::default()).is_err());
        let (_d, p) = write_tmp(b"solid stl\n");
        assert!(load_ply(&p, PlyLoadOptions::default()).is_err());
    }

    #[test]
    fn scalar_element_before_vertex_is_skipped() {
        let props = inria_props(0);
        let rows = rows(&props, 5, 4);
        for (enc, body) in each_encoding(&props, &rows) {
            // Insert `element camera 2` (two floats each) before the vertex element.
            let text = String::from_utf8_lossy(
                &body[..body
                    .windows(11)
                    .position(|w| w == b"end_header\n")
                    .expect("eh")
                    + 11],
            )
            .to_string();
            let header_len = text.len();
            let text = text.replacen(
                "element vertex",
                "element camera 2\nproperty float a\nproperty double b\nelement vertex",
                1,
            );
            let mut bytes = text.into_bytes();
            let pre = encode(
                enc,
                &[("a", ScalarType::F32), ("b", ScalarType::F64)],
                &[vec![1.0, 2.0], vec![3.0, 4.0]],
            );
            let pre_header = pre
                .windows(11)
                .position(|w| w == b"end_header\n")
                .expect("eh")
                + 11;
            bytes.extend_from_slice(&pre[pre_header..]);
            bytes.extend_from_slice(&body[header_len..]);
            assert_loads_as(&bytes, &props, &rows);
        }
    }

    #[test]
    fn write_ply_round_trip() {
        let props = inria_props(3);
        let rows = rows(&props, 50, 8);
        let (d, p) = write_tmp(&encode(Encoding::BinaryBe, &refs(&props), &rows));
        let g = load_ply(&p, PlyLoadOptions { colours: true }).expect("loads");
        let out = d.path().join("out.ply");
        write_ply(&out, &g).expect("writes");
        let back = load_ply(&out, PlyLoadOptions { colours: true }).expect("reloads");
        assert_eq!(back.means, g.means);
        assert_eq!(back.sh, g.sh);
        for i in 0..g.len() {
            assert!((back.opacities[i] - g.opacities[i]).abs() < 1e-6);
            for k in 0..3 {
                assert!((back.scales[i][k] / g.scales[i][k] - 1.0).abs() < 1e-6);
            }
            for k in 0..4 {
                assert!((back.rotations[i][k] - g.rotations[i][k]).abs() < 1e-6);
            }
        }
    }

    #[test]
    fn highlighted_copy_changes_only_requested_colours() {
        for (enc, dc_ty) in [
            (Encoding::BinaryLe, ScalarType::F32),
            (Encoding::BinaryBe, ScalarType::F64),
        ] {
            let mut props = inria_props(2);
            props.push(("label".into(), ScalarType::U16));
            for (n, t) in props.iter_mut() {
                if n.starts_with("f_dc") {
                    *t = dc_ty;
                }
            }
            let rows = rows(&props, 30, 21);
            let src_bytes = encode(enc, &refs(&props), &rows);
            let (d, src) = write_tmp(&src_bytes);
            let dst = d.path().join("hl.ply");
            let colour = |i: usize| (i % 4 == 1).then(|| [i as f32 / 30.0, 0.25, 1.0]);
            write_highlighted_ply(&src, &dst, colour).expect("highlight");
            let out = std::fs::read(&dst).expect("read");
            assert_eq!(out.len(), src_bytes.len());
            let header = parse_header(&src, &mut &src_bytes[..]).expect("header");
            let start = header.header_len;
            assert_eq!(out[..start], src_bytes[..start]);
            let sh_offsets = header.byte_ranges("f_");
            for i in 0..rows.len() {
                let a = &src_bytes[start + i * header.stride..start + (i + 1) * header.stride];
                let b = &out[start + i * header.stride..start + (i + 1) * header.stride];
                if colour(i).is_none() {
                    assert_eq!(a, b, "vertex {i} must be untouched");
                    continue;
                }
                for (k, (x, y)) in a.iter().zip(b).enumerate() {
                    if !sh_offsets.iter().any(|&(o, s)| (o..o + s).contains(&k)) {
                        assert_eq!(x, y, "vertex {i} byte {k} outside SH changed");
                    }
                }
            }
            let g = load_ply(&dst, PlyLoadOptions { colours: true }).expect("loads");
            let orig = load_ply(&src, PlyLoadOptions { colours: true }).expect("loads");
            let sh = g.sh.as_ref().expect("sh");
            let per = sh.per_channel();
            for i in 0..rows.len() {
                match colour(i) {
                    Some(rgb) => {
                        for c in 0..3 {
                            let shown = 0.5 + SH_C0 * sh.dc(i)[c] as f64;
                            assert!((shown - rgb[c] as f64).abs() < 1e-6);
                        }
                        assert!(
                            sh.coeffs[(i * per + 1) * 3..(i + 1) * per * 3]
                                .iter()
                                .all(|&v| v == 0.0)
                        );
                    }
                    None => {
                        let o = orig.sh.as_ref().expect("sh");
                        assert_eq!(
                            sh.coeffs[i * per * 3..(i + 1) * per * 3],
                            o.coeffs[i * per * 3..(i + 1) * per * 3]
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn highlighting_ascii_or_colourless_is_refused() {
        let props = inria_props(0);
        let rows = rows(&props, 3, 1);
        let (d, p) = write_tmp(&encode(Encoding::Ascii, &refs(&props), &rows));
        let dst = d.path().join("o.ply");
        let err = write_highlighted_ply(&p, &dst, |_| Some([1.0, 0.0, 0.0])).expect_err("ascii");
        assert!(matches!(err, Error::Unsupported { .. }), "{err}");
        assert!(!dst.exists());
        let props: Vec<_> = props
            .into_iter()
            .filter(|(n, _)| !n.starts_with("f_dc"))
            .collect();
        let rows = self::rows(&props, 3, 1);
        let (d, p) = write_tmp(&binary_le(&props, &rows));
        let dst = d.path().join("o.ply");
        assert!(write_highlighted_ply(&p, &dst, |_| None).is_err());
        assert!(!dst.exists());
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(48))]
        #[test]
        fn binary_round_trip_random_finite(
            vals in proptest::collection::vec(-30.0f32..30.0, 14 * 6),
            be in proptest::bool::ANY,
        ) {
            let props: Vec<(String, ScalarType)> = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2",
                "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
                .iter().map(|n| (n.to_string(), ScalarType::F32)).collect();
            let mut rows: Vec<Vec<f64>> = vals.chunks(14).map(|c| c.iter().map(|&v| v as f64).collect()).collect();
            for r in &mut rows {
                r[10] += 100.0; // keep the quaternion away from zero
            }
            let enc = if be { Encoding::BinaryBe } else { Encoding::BinaryLe };
            assert_loads_as(&encode(enc, &refs(&props), &rows), &props, &rows);
        }
    }
}
