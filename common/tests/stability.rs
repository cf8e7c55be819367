//! Numerical stability of stored vectors, PLY loading and cosine scoring at the extremes
//! (cases 3, 7, 8 of docs/results/stability.md): int8 / f16 round-trip bounds by proptest, values beyond the f16 range,
//! subnormals, all-zero vectors, NaN / inf input, zero quaternions and extreme logits in the PLY
//! loader, zero-norm queries. Each case asserts a documented typed error or a saturated /
//! normalised finite result.
//!
//! Run: `cargo test --workspace --test stability`.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::Path;

use half::f16;
use proptest::prelude::*;
use slag_common::Error;
use slag_common::embeddings::{Embeddings, StoredPrecision};
use slag_common::scene::{PlyLoadOptions, load_ply_bytes};
use slag_common::shards::Dtype;
use slag_common::shards::format::{
    F16_MAX, ShardInput, decode_shard, decode_shard_stored, encode_shard, quantize_i8,
};
use slag_common::similarity::cosine_scores;
use slag_common::text::l2_normalize;

// ---------------------------------------------------------------------------------------------
// int8 (per-vector scale)

/// Smallest max-|v| that gets a non-zero int8 scale (below it: the zero vector).
const I8_MIN_MAX: f32 = 127.0 * f32::MIN_POSITIVE;

/// One component: zero, subnormal, tiny, ordinary, huge, up to f32::MAX, either sign.
fn component() -> impl Strategy<Value = f32> {
    prop_oneof![
        Just(0.0f32),
        (1u32..0x0080_0000).prop_map(f32::from_bits), // subnormals
        (-38.0f64..38.5).prop_map(|e| 10f64.powf(e).min(f32::MAX as f64) as f32),
        -1.0f32..1.0,
        Just(f32::MAX),
    ]
    .prop_flat_map(|x| prop_oneof![Just(x), Just(-x)])
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    /// `|v - q·s| ≤ 0.50002·s` (s/2 plus f32 rounding), `q·s` finite, for any finite vector;
    /// vectors whose max |v| is below 127·f32::MIN_POSITIVE become the zero vector.
    #[test]
    fn prop_int8_round_trip_is_within_half_a_step(
        v in proptest::collection::vec(component(), 1..40),
    ) {
        let mut q = Vec::new();
        let s = quantize_i8(&v, &mut q);
        prop_assert_eq!(q.len(), v.len());
        prop_assert!(s.is_finite() && s >= 0.0);
        let m = v.iter().fold(0f32, |m, x| m.max(x.abs()));
        if m < I8_MIN_MAX {
            prop_assert_eq!(s, 0.0);
            prop_assert!(q.iter().all(|&b| b == 0));
            return Ok(());
        }
        prop_assert!(s >= f32::MIN_POSITIVE, "subnormal scale {}", s);
        for (&x, &b) in v.iter().zip(&q) {
            let back = (b as i8) as f32 * s;
            prop_assert!(back.is_finite(), "{} -> {} (s {})", x, back, s);
            let err = (x as f64 - back as f64).abs();
            prop_assert!(err <= 0.50002 * s as f64, "{} -> {}: err {} > s/2 = {}", x, back, err, s / 2.0);
        }
    }

    /// f16: `|v - f16(v)| ≤ max(|v|·2^-11, 2^-25)` for |v| ≤ 65504, through the shard codec.
    #[test]
    fn prop_f16_round_trip_bound(
        v in proptest::collection::vec(
            prop_oneof![
                component().prop_map(|x| x.clamp(-F16_MAX, F16_MAX)),
                -1.0f32..1.0,
                -1e-4f32..1e-4,
            ],
            1..40,
        ),
    ) {
        let back = round_trip(&v, Dtype::F16).expect("in range");
        for (&x, &y) in v.iter().zip(&back) {
            let bound = (x.abs() as f64 * 2f64.powi(-11)).max(2f64.powi(-25));
            prop_assert!(y.is_finite());
            prop_assert!((x as f64 - y as f64).abs() <= bound, "{} -> {} (bound {})", x, y, bound);
        }
    }
}

/// Encodes one row as a shard of `dtype` and decodes it back to f32.
fn round_trip(v: &[f32], dtype: Dtype) -> slag_common::Result<Vec<f32>> {
    let bytes = encode_shard(&ShardInput {
        scene_id: "s",
        model: "m",
        tile_id: 0,
        dim: v.len(),
        dtype,
        ids: &[0],
        means: &[[0.0; 3]],
        vectors: v,
        scales: None,
        opacities: None,
        rotations: None,
        sh_dc: None,
        segments: None,
    })?;
    Ok(decode_shard(&bytes).expect("decode").vectors)
}

#[test]
fn extreme_stored_vectors_give_typed_errors_or_finite_results() {
    let all = [Dtype::F32, Dtype::F16, Dtype::I8];
    // All-zero vectors: zero back, no NaN, every dtype (int8 scale 0).
    for dt in all {
        assert_eq!(round_trip(&[0.0; 8], dt).unwrap(), vec![0.0; 8], "{dt:?}");
    }
    let bytes = encode_shard(&ShardInput {
        scene_id: "s",
        model: "m",
        tile_id: 0,
        dim: 4,
        dtype: Dtype::I8,
        ids: &[0],
        means: &[[0.0; 3]],
        vectors: &[0.0; 4],
        scales: None,
        opacities: None,
        rotations: None,
        sh_dc: None,
        segments: None,
    })
    .unwrap();
    match decode_shard_stored(&bytes).unwrap().vectors {
        slag_common::shards::StoredVectors::I8 { scales, .. } => assert_eq!(scales, vec![0.0]),
        other => panic!("{other:?}"),
    }
    // NaN / inf input: Error::Invalid in every dtype.
    for dt in all {
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            let r = round_trip(&[0.5, bad, 0.1], dt);
            assert!(matches!(r, Err(Error::Invalid(_))), "{dt:?} {bad}: {r:?}");
        }
    }
    // Beyond the f16 range: a typed error naming the dtype for f16 (not a stored infinity); f32
    // / int8 keep it.
    for big in [65520.0f32, 1e5, -3e38] {
        match round_trip(&[0.5, big], Dtype::F16) {
            Err(e @ Error::Param { name: "dtype", .. }) => {
                assert!(e.to_string().contains("f16 range"), "{e}")
            }
            other => panic!("{big}: {other:?}"),
        }
        assert_eq!(round_trip(&[0.5, big], Dtype::F32).unwrap(), vec![0.5, big]);
        let i8_back = round_trip(&[0.5, big], Dtype::I8).unwrap();
        assert!(i8_back.iter().all(|x| x.is_finite()));
        assert!((i8_back[1] - big).abs() <= big.abs() / 254.0 * 1.0001);
    }
    // The largest f16 (and values rounding to it) are kept.
    assert_eq!(
        round_trip(&[F16_MAX, -65519.0], Dtype::F16).unwrap(),
        vec![F16_MAX, -F16_MAX]
    );
    // f32::MAX in int8: the scale is stepped down so that 127·s stays finite.
    let back = round_trip(&[f32::MAX, 1.0, -f32::MAX], Dtype::I8).unwrap();
    assert!(back.iter().all(|x| x.is_finite()), "{back:?}");
    assert!((back[0] as f64 - f32::MAX as f64).abs() <= f32::MAX as f64 / 254.0);
    // Subnormal-only vectors: int8 stores the zero vector; f16 flushes them to 0 (below 2^-25).
    let sub = [1e-40f32, -2e-42, 0.0];
    assert_eq!(round_trip(&sub, Dtype::I8).unwrap(), vec![0.0; 3]);
    assert_eq!(round_trip(&sub, Dtype::F16).unwrap(), vec![0.0; 3]);
    assert_eq!(round_trip(&sub, Dtype::F32).unwrap(), sub.to_vec());
    // Non-finite components given to quantize_i8 directly: left out of the scale, coded 0.
    let mut q = Vec::new();
    let s = quantize_i8(&[1.0, f32::NAN, f32::INFINITY, -0.5], &mut q);
    assert_eq!(s, 1.0 / 127.0);
    assert_eq!(
        q.iter().map(|&b| b as i8).collect::<Vec<_>>(),
        vec![127, 0, 0, -64]
    );
}

#[test]
fn embeddings_file_rejects_non_finite_and_out_of_f16_range_values() {
    let dir = tempfile::tempdir().unwrap();
    let e = |v: Vec<f32>| Embeddings {
        ids: vec![7, 9],
        means: vec![[0.0; 3]; 2],
        dim: 2,
        vectors: v,
        total_weights: vec![1.0; 2],
        model: "m".into(),
        scene_gaussians: 10,
        source_ply: "p.ply".into(),
    };
    let path = dir.path().join("e.safetensors");
    for (v, precision, what) in [
        (vec![1.0, 0.0, f32::NAN, 1.0], StoredPrecision::F32, "NaN"),
        (
            vec![1.0, 0.0, f32::INFINITY, 1.0],
            StoredPrecision::F16,
            "inf",
        ),
        (vec![1.0, 0.0, 7e4, 1.0], StoredPrecision::F16, "7e4 in f16"),
    ] {
        match e(v).write(&path, precision) {
            // A non-finite value is bad data; a value beyond f16 asks for f32 precision.
            Err(
                e @ (Error::Invalid(_)
                | Error::Param {
                    name: "precision", ..
                }),
            ) => {
                assert!(e.to_string().contains("Gaussian 9"), "{what}: {e}")
            }
            other => panic!("{what}: {other:?}"),
        }
        assert!(!path.exists(), "{what}: a file was written");
    }
    // 7e4 is fine in f32; subnormals and zero rows are fine in f16 (zero, or the nearest half).
    e(vec![1.0, 0.0, 7e4, 1.0])
        .write(&path, StoredPrecision::F32)
        .unwrap();
    assert_eq!(
        Embeddings::read(&path).unwrap().vectors,
        vec![1.0, 0.0, 7e4, 1.0]
    );
    e(vec![0.0, 0.0, 1e-40, 3e-6])
        .write(&path, StoredPrecision::F16)
        .unwrap();
    let back = Embeddings::read(&path).unwrap().vectors;
    assert_eq!(&back[..3], &[0.0, 0.0, 0.0]);
    assert!((back[3] - 3e-6).abs() <= 2f32.powi(-25), "{back:?}");
    assert_eq!(f16::from_f32(3e-6).to_f32(), back[3]);
}

// ---------------------------------------------------------------------------------------------
// PLY loader: zero / non-unit quaternions, extreme logits and log-scales

fn ply(rows: &[[f64; 11]]) -> Vec<u8> {
    let mut s = String::from("ply\nformat ascii 1.0\n");
    s += &format!("element vertex {}\n", rows.len());
    for p in [
        "x", "y", "z", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
        "opacity",
    ] {
        s += &format!("property float {p}\n");
    }
    s += "end_header\n";
    for r in rows {
        s += &r.map(|v| format!("{v:e}")).join(" ");
        s += "\n";
    }
    s.into_bytes()
}

#[test]
fn ply_loader_normalises_quaternions_clamps_opacities_and_rejects_zero_quaternions() {
    let opts = PlyLoadOptions { colours: false };
    let row = |q: [f64; 4], logit: f64, log_s: f64| {
        [
            0.0, 1.0, 2.0, log_s, log_s, log_s, q[0], q[1], q[2], q[3], logit,
        ]
    };
    let g = load_ply_bytes(
        &ply(&[
            row([2.0, 0.0, 0.0, 0.0], 16.0, -1.0), // non-unit quaternion, logit +16
            row([1e-30, 1e-30, 0.0, 0.0], -16.0, -1.0), // tiny quaternion, logit -16
            row([0.0, 0.0, 0.0, -3.0], 200.0, -200.0), // logit +200, log-scale -200
            row([0.5, 0.5, 0.5, 0.5], -200.0, 0.0), // logit -200
        ]),
        Path::new("t.ply"),
        opts,
    )
    .expect("load");
    let h = std::f32::consts::FRAC_1_SQRT_2;
    assert_eq!(g.rotations[0], [1.0, 0.0, 0.0, 0.0]);
    assert!((g.rotations[1][0] - h).abs() < 1e-7 && (g.rotations[1][1] - h).abs() < 1e-7);
    assert_eq!(g.rotations[2], [0.0, 0.0, 0.0, -1.0]);
    let sig = |x: f64| 1.0 / (1.0 + (-x).exp());
    assert!((g.opacities[0] as f64 - sig(16.0)).abs() < 1e-7);
    assert!((g.opacities[1] as f64 - sig(-16.0)).abs() < 1e-12);
    // sigmoid(±200) rounds to 1 / 0 in f32: clamped into the open interval (0, 1).
    assert!(g.opacities[2] < 1.0 && g.opacities[2] > 0.999_999);
    assert!(g.opacities[3] > 0.0 && g.opacities[3] <= f32::MIN_POSITIVE);
    // exp(-200) underflows f32: scale 0 (the rasterizer's low-pass then gives it 0.3 px²).
    assert_eq!(g.scales[2], [0.0; 3]);
    assert!(g.opacities.iter().all(|o| o.is_finite()));

    // The zero quaternion is not a rotation: a typed format error naming the vertex.
    let r = load_ply_bytes(
        &ply(&[
            row([1.0, 0.0, 0.0, 0.0], 0.0, -1.0),
            row([0.0; 4], 0.0, -1.0),
        ]),
        Path::new("t.ply"),
        opts,
    );
    match r {
        Err(Error::Format { message, .. }) => {
            assert!(
                message.contains("vertex 1") && message.contains("quaternion"),
                "{message}"
            )
        }
        other => panic!("{:?}", other.map(|g| g.rotations)),
    }
    // NaN and an exp() overflow of the log-scale: typed errors too.
    for bad in [
        row([1.0, 0.0, 0.0, 0.0], f64::NAN, -1.0),
        row([1.0, 0.0, 0.0, 0.0], 0.0, 200.0),
    ] {
        let r = load_ply_bytes(&ply(&[bad]), Path::new("t.ply"), opts);
        assert!(
            matches!(r, Err(Error::Format { .. })),
            "{:?}",
            r.map(|g| g.scales)
        );
    }
}

// ---------------------------------------------------------------------------------------------
// cosine scoring and text-embedding normalisation

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// Any finite query: an Error::Query exactly when its norm is below 1e-12, else finite
    /// cosines in [-1, 1] (+1e-5), 0 for zero rows.
    #[test]
    fn prop_cosine_scores_are_finite_or_a_typed_error(
        q in proptest::collection::vec(component(), 8),
    ) {
        let rows: Vec<f32> = [
            vec![0.0f32; 8],
            // Unit rows, as the embeddings file stores them (a non-unit row could score past 1).
            vec![0.5f32.sqrt() * 0.5; 4]
                .into_iter()
                .chain(vec![-(0.5f32.sqrt()) * 0.5; 4])
                .collect(),
            (0..8).map(|i| if i == 3 { 1.0 } else { 0.0 }).collect(),
        ]
        .concat();
        let norm = q.iter().map(|&x| (x as f64).powi(2)).sum::<f64>().sqrt();
        match cosine_scores(&rows, 8, &q) {
            Err(Error::Query { .. }) => prop_assert!(norm < 1e-12 || !norm.is_finite(), "norm {}", norm),
            Err(e) => prop_assert!(false, "{}", e),
            Ok(s) => {
                prop_assert!(norm >= 1e-12);
                prop_assert_eq!(s[0], 0.0);
                prop_assert!(s.iter().all(|x| x.is_finite() && x.abs() <= 1.0 + 1e-5), "{:?}", s);
            }
        }
        let mut v = q.clone();
        match l2_normalize(&mut v, Path::new("m.onnx")) {
            Err(Error::Model { .. }) => prop_assert!(norm <= 1e-12),
            Err(e) => prop_assert!(false, "{}", e),
            Ok(()) => {
                let n = v.iter().map(|&x| (x as f64).powi(2)).sum::<f64>().sqrt();
                prop_assert!((n - 1.0).abs() < 1e-5, "norm after {}", n);
            }
        }
    }
}
