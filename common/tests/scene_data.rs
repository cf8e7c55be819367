//! Loading real data: the shared snowmiku `.ply` and the embedded `data/snowmiku-mini` scene.

use std::path::PathBuf;

use slag_common::camera::{load_views, subsample};
use slag_common::paths::source_tree_shared_dir as shared_dir;
use slag_common::scene::{PlyLoadOptions, SH_C0, load_ply, write_highlighted_ply};

fn snowmiku() -> PathBuf {
    shared_dir().join("scenes").join("snowmiku")
}

fn mini() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join("data")
        .join("snowmiku-mini")
}

/// Vertex `i` of the snowmiku .ply as raw little-endian floats, parsed independently of the loader
/// (62 float properties in the INRIA order).
fn raw_vertex(bytes: &[u8], i: usize) -> Vec<f32> {
    let end = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .expect("header")
        + 11;
    let rec = &bytes[end + i * 62 * 4..end + (i + 1) * 62 * 4];
    rec.chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

#[test]
fn snowmiku_ply_loads_with_valid_activations() {
    let path = snowmiku().join("point_cloud.ply");
    let g = load_ply(&path, PlyLoadOptions { colours: true }).expect("loads");
    assert_eq!(g.len(), 120_000);
    for i in 0..g.len() {
        assert!(g.means[i].iter().all(|v| v.is_finite()));
        assert!(g.scales[i].iter().all(|&s| s.is_finite() && s > 0.0));
        let q = g.rotations[i];
        let n = q.iter().map(|v| v * v).sum::<f32>().sqrt();
        assert!((n - 1.0).abs() < 1e-5, "vertex {i}: |q| = {n}");
        assert!(
            g.opacities[i] > 0.0 && g.opacities[i] < 1.0,
            "vertex {i}: {}",
            g.opacities[i]
        );
    }
    let sh = g.sh.as_ref().expect("colours");
    assert_eq!(sh.degree, 3);
    assert_eq!(sh.coeffs.len(), 120_000 * 16 * 3);
    assert!(sh.coeffs.iter().all(|v| v.is_finite()));
    // Against an independent parse: x y z nx ny nz f_dc(3) f_rest(45) opacity scale(3) rot(4).
    let bytes = std::fs::read(&path).expect("read");
    for i in [0usize, 1, 4_321, 119_999] {
        let r = raw_vertex(&bytes, i);
        assert_eq!(g.means[i], [r[0], r[1], r[2]]);
        assert_eq!(sh.dc(i), [r[6], r[7], r[8]]);
        for c in 0..3 {
            for j in 1..16 {
                assert_eq!(sh.coeffs[(i * 16 + j) * 3 + c], r[9 + c * 15 + j - 1]);
            }
        }
        let o = 1.0 / (1.0 + (-(r[54] as f64)).exp());
        assert!((g.opacities[i] as f64 - o).abs() < 1e-6);
        for k in 0..3 {
            assert!((g.scales[i][k] as f64 / (r[55 + k] as f64).exp() - 1.0).abs() < 1e-6);
        }
    }
    // Geometry only: no SH kept.
    let geo = load_ply(&path, PlyLoadOptions { colours: false }).expect("loads");
    assert!(geo.sh.is_none());
    assert_eq!(geo.means, g.means);
    assert_eq!(geo.opacities, g.opacities);
}

#[test]
fn snowmiku_highlight_round_trip() {
    let src = snowmiku().join("point_cloud.ply");
    let dir = tempfile::tempdir().expect("tempdir");
    let dst = dir.path().join("hl.ply");
    let pick = |i: usize| (i % 1000 == 7).then_some([1.0f32, 0.0, 0.0]);
    write_highlighted_ply(&src, &dst, pick).expect("writes");
    let a = std::fs::read(&src).expect("read");
    let b = std::fs::read(&dst).expect("read");
    assert_eq!(a.len(), b.len());
    let end = a
        .windows(11)
        .position(|w| w == b"end_header\n")
        .expect("header")
        + 11;
    assert_eq!(a[..end], b[..end]);
    for i in 0..120_000 {
        let (ra, rb) = (raw_vertex(&a, i), raw_vertex(&b, i));
        if pick(i).is_none() {
            assert_eq!(ra, rb);
        } else {
            assert_eq!(ra[..6], rb[..6]);
            assert_eq!(ra[54..], rb[54..]);
            let want = [
                (0.5 / SH_C0) as f32,
                (-0.5 / SH_C0) as f32,
                (-0.5 / SH_C0) as f32,
            ];
            assert_eq!(rb[6..9], want);
            assert!(rb[9..54].iter().all(|&v| v == 0.0));
        }
    }
}

#[test]
fn embedded_default_scene_loads() {
    let views = load_views(&mini()).expect("mini views load");
    assert_eq!(views.len(), 13);
    for v in &views {
        let k = v.intrinsics;
        assert_eq!((k.width, k.height), (495, 371));
        let dims = image::image_dimensions(&v.image_path).expect("image readable");
        assert_eq!(dims, (k.width, k.height), "{}", v.image_path.display());
    }
    let g = load_ply(
        &mini().join("point_cloud.ply"),
        PlyLoadOptions { colours: true },
    )
    .expect("mini ply loads");
    assert!(g.len() > 10_000 && g.len() <= 60_000, "{}", g.len());
    assert_eq!(g.sh.as_ref().map(|s| s.degree), Some(0));
    assert!(g.opacities.iter().all(|&o| o > 0.0 && o < 1.0));
    assert!(mini().join("LICENSE").is_file() && mini().join("SOURCE.md").is_file());
    let total: u64 = walk(&mini());
    assert!(total <= 5 << 20, "embedded scene is {total} bytes");
}

fn walk(dir: &std::path::Path) -> u64 {
    std::fs::read_dir(dir)
        .expect("dir")
        .map(|e| {
            let e = e.expect("entry");
            let m = e.metadata().expect("meta");
            if m.is_dir() { walk(&e.path()) } else { m.len() }
        })
        .sum()
}

#[test]
fn embedded_default_scene_matches_its_source() {
    let full = subsample(load_views(&snowmiku()).expect("snowmiku"), 8);
    let small = load_views(&mini()).expect("mini");
    assert_eq!(full.len(), small.len());
    for (f, s) in full.iter().zip(&small) {
        assert_eq!(f.name, s.name);
        assert_eq!(s.intrinsics, f.intrinsics.scaled(0.5));
        let (a, b) = (f.world_to_camera, s.world_to_camera);
        let dr = (a.rotation - b.rotation)
            .to_cols_array()
            .iter()
            .fold(0f64, |m, v| m.max(v.abs()));
        assert!(dr < 1e-9 && (a.translation - b.translation).abs().max_element() < 1e-12);
    }
    // Every kept Gaussian is one of the source's (same centre, scale, colour).
    let src = load_ply(
        &snowmiku().join("point_cloud.ply"),
        PlyLoadOptions { colours: true },
    )
    .expect("source");
    let g = load_ply(
        &mini().join("point_cloud.ply"),
        PlyLoadOptions { colours: true },
    )
    .expect("mini");
    let mut by_mean = std::collections::HashMap::new();
    for i in 0..src.len() {
        by_mean.insert(src.means[i].map(f32::to_bits), i);
    }
    let (sh, ssh) = (g.sh.as_ref().expect("sh"), src.sh.as_ref().expect("sh"));
    for i in 0..g.len() {
        let j = *by_mean
            .get(&g.means[i].map(f32::to_bits))
            .expect("a source Gaussian");
        assert_eq!(sh.dc(i), ssh.dc(j));
        assert!((g.opacities[i] - src.opacities[j]).abs() < 1e-5);
        for k in 0..3 {
            assert!((g.scales[i][k] / src.scales[j][k] - 1.0).abs() < 1e-5);
        }
    }
}
