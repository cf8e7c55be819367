//! Writing `.ply` files: a whole scene in the INRIA layout (logit opacities, log scales), a
//! float-only vertex header for other writers, and a copy of a binary scene with some
//! Gaussians' SH colours replaced (the highlight the edge serves for a query's matches).

use std::path::Path;

use super::OPACITY_MAX;
use super::header::{Encoding, ScalarType, parse_header, truncated};
use crate::scene::{Gaussians, SH_C0};
use crate::{Error, Result};

/// See [`super::write_highlighted_ply`].
pub(in crate::scene) fn write_highlighted(
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
pub(in crate::scene) fn write(path: &Path, g: &Gaussians) -> Result<()> {
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
