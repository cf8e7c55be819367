//! `.ply` reader on arbitrary bytes, with and without SH colours.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;
use slag_common::scene::{PlyLoadOptions, load_ply_bytes};

fuzz_target!(|data: &[u8]| {
    for colours in [false, true] {
        if let Ok(g) = load_ply_bytes(data, Path::new("fuzz.ply"), PlyLoadOptions { colours }) {
            // A decoded scene is internally consistent: one scale, rotation, opacity per mean,
            // all finite, unit quaternions.
            let n = g.means.len();
            assert!(g.scales.len() == n && g.rotations.len() == n && g.opacities.len() == n);
            assert!(g.means.iter().flatten().all(|x| x.is_finite()));
            for q in &g.rotations {
                let norm = q.iter().map(|x| x * x).sum::<f32>().sqrt();
                assert!((norm - 1.0).abs() < 1e-3, "non-unit quaternion {q:?}");
            }
        }
    }
});
