//! Decoding a `.ply` body into activated [`Gaussians`]: picking the INRIA columns the caller
//! asked for, then reading binary records (in parallel chunks, fixed byte offsets) or ASCII
//! tokens (fixed positions), validating and activating each vertex (exp scales, normalised
//! rotations wxyz, sigmoid opacities, SH coefficients interleaved per channel).

use std::fs::File;
use std::io::{BufReader, Read};
use std::path::Path;

use rayon::prelude::*;

use super::OPACITY_MAX;
use super::header::{Encoding, Header, ScalarType, parse_header, truncated};
use crate::scene::{Gaussians, PlyLoadOptions, ShCoeffs};
use crate::{Error, Result};

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

pub(in crate::scene) fn read(path: &Path, options: PlyLoadOptions) -> Result<Gaussians> {
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
pub(in crate::scene) fn read_bytes(
    path: &Path,
    bytes: &[u8],
    options: PlyLoadOptions,
) -> Result<Gaussians> {
    let mut reader = std::io::Cursor::new(bytes);
    let header = parse_header(path, &mut reader)?;
    let cols = select_columns(path, &header, options)?;
    match header.encoding {
        Encoding::Ascii => read_ascii(path, &header, &cols, reader),
        _ => read_binary(path, &header, &cols, reader, bytes.len() as u64),
    }
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
