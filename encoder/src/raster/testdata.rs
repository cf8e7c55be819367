//! Test/benchmark-only loaders for the shared snowmiku scene (minimal INRIA `.ply` and COLMAP
//! text readers). The real loaders are `slag_common::scene::load_ply` /
//! `slag_common::camera::load_views`; these exist so the rasterizer can be tested before those
//! land. Shared by `raster::tests` and `benches/raster.rs` (via `#[path]`).

#![allow(dead_code)]

use std::path::{Path, PathBuf};

use glam::{DMat3, DQuat, DVec3};
use slag_common::camera::{Intrinsics, WorldToCamera};
use slag_common::scene::{Gaussians, ShCoeffs};

pub fn snowmiku_dir() -> PathBuf {
    slag_common::paths::shared_dir()
        .join("scenes")
        .join("snowmiku")
}

/// Minimal INRIA .ply reader: binary little-endian, all-float properties.
pub fn load_ply_for_test(path: &Path, colours: bool) -> Gaussians {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let end = b"end_header\n";
    let hdr_end = bytes
        .windows(end.len())
        .position(|w| w == end)
        .expect("ply header")
        + end.len();
    let header = std::str::from_utf8(&bytes[..hdr_end]).expect("ascii header");
    assert!(
        header.contains("format binary_little_endian"),
        "test loader needs binary LE"
    );
    let mut n = 0usize;
    let mut props = Vec::new();
    for line in header.lines() {
        let f: Vec<&str> = line.split_whitespace().collect();
        match f.as_slice() {
            ["element", "vertex", c] => n = c.parse().expect("count"),
            ["property", "float", name] => props.push(name.to_string()),
            ["property", t, _] => panic!("test loader: unsupported property type {t}"),
            _ => {}
        }
    }
    let stride = props.len() * 4;
    let body = &bytes[hdr_end..];
    assert!(body.len() >= n * stride, "truncated ply");
    let col = |name: &str| {
        props
            .iter()
            .position(|p| p == name)
            .unwrap_or_else(|| panic!("no {name}"))
    };
    let get = |i: usize, c: usize| {
        let o = i * stride + c * 4;
        f32::from_le_bytes([body[o], body[o + 1], body[o + 2], body[o + 3]])
    };
    let (x, s0, r0, op) = (col("x"), col("scale_0"), col("rot_0"), col("opacity"));
    let mut g = Gaussians::default();
    for i in 0..n {
        g.means.push([get(i, x), get(i, x + 1), get(i, x + 2)]);
        g.scales.push([0, 1, 2].map(|k| get(i, s0 + k).exp()));
        let q = [0, 1, 2, 3].map(|k| get(i, r0 + k));
        let nq = q.iter().map(|v| v * v).sum::<f32>().sqrt();
        g.rotations.push(q.map(|v| v / nq));
        g.opacities.push(1.0 / (1.0 + (-get(i, op)).exp()));
    }
    if colours {
        let dc = col("f_dc_0");
        let n_rest = props.iter().filter(|p| p.starts_with("f_rest_")).count();
        let rest = if n_rest > 0 { col("f_rest_0") } else { 0 };
        let per = n_rest / 3 + 1;
        let degree = match per {
            1 => 0,
            4 => 1,
            9 => 2,
            16 => 3,
            _ => panic!("odd f_rest count {n_rest}"),
        };
        let mut coeffs = Vec::with_capacity(n * per * 3);
        for i in 0..n {
            for l in 0..per {
                for c in 0..3 {
                    coeffs.push(if l == 0 {
                        get(i, dc + c)
                    } else {
                        get(i, rest + c * (per - 1) + (l - 1))
                    });
                }
            }
        }
        g.sh = Some(ShCoeffs { degree, coeffs });
    }
    g
}

/// COLMAP text model: (image name, full-resolution intrinsics, pose), PINHOLE only.
pub fn load_views_for_test(scene: &Path) -> Vec<(String, Intrinsics, WorldToCamera)> {
    let sparse = scene.join("sparse").join("0");
    let cams = std::fs::read_to_string(sparse.join("cameras.txt")).expect("cameras.txt");
    let mut intr = std::collections::HashMap::new();
    for line in cams
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
    {
        let f: Vec<&str> = line.split_whitespace().collect();
        assert_eq!(f[1], "PINHOLE", "test loader handles PINHOLE only");
        let v: Vec<f64> = f[4..8].iter().map(|s| s.parse().expect("number")).collect();
        let k = Intrinsics {
            width: f[2].parse().expect("w"),
            height: f[3].parse().expect("h"),
            fx: v[0],
            fy: v[1],
            cx: v[2],
            cy: v[3],
        };
        intr.insert(f[0].to_string(), k);
    }
    let imgs = std::fs::read_to_string(sparse.join("images.txt")).expect("images.txt");
    let mut out = Vec::new();
    let mut lines = imgs.lines().filter(|l| !l.starts_with('#'));
    while let Some(line) = lines.next() {
        let f: Vec<&str> = line.split_whitespace().collect();
        if f.len() < 10 {
            continue;
        }
        let v: Vec<f64> = f[1..8].iter().map(|s| s.parse().expect("number")).collect();
        let q = DQuat::from_xyzw(v[1], v[2], v[3], v[0]).normalize();
        let pose = WorldToCamera {
            rotation: DMat3::from_quat(q),
            translation: DVec3::new(v[4], v[5], v[6]),
        };
        out.push((f[9].to_string(), intr[f[8]], pose));
        let _ = lines.next(); // the 2D points line (may be empty)
    }
    out.sort_by(|a, b| a.0.cmp(&b.0));
    out
}
