//! Tests of `.ply` reading and writing against an independent writer of any encoding and
//! property list: round trips, reordered and mixed-type properties, and the errors that name
//! the vertex and property at fault.

#![allow(clippy::needless_range_loop)]

use std::path::Path;

use super::header::{Encoding, ScalarType, parse_header};
use crate::Error;
use crate::scene::{Gaussians, PlyLoadOptions, SH_C0, load_ply, write_highlighted_ply, write_ply};

/// Independent test writer: any encoding, any property list, values given as f64 per row.
pub(crate) fn encode(enc: Encoding, props: &[(&str, ScalarType)], rows: &[Vec<f64>]) -> Vec<u8> {
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
    let crash = include_bytes!("../../../tests/data/fuzz-ply-beyond-f32.ply");
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
