//! The mixture form: its reconstruction and scores against the dense form, the file's round
//! trip and bytes, and the typed errors for bad queries, files and rows.

use super::*;
use crate::similarity::cosine_scores;
use proptest::prelude::*;
use safetensors::tensor::TensorView;
use std::collections::HashMap;
use std::path::PathBuf;

/// Deterministic xorshift stream in [-1, 1).
fn stream(seed: u64) -> impl FnMut() -> f32 {
    let mut s = seed | 1;
    move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 40) as f32 / (1u64 << 23) as f32 - 1.0
    }
}

fn unit_rows(m: usize, dim: usize, seed: u64) -> Vec<f32> {
    let mut r = stream(seed);
    let mut out = Vec::with_capacity(m * dim);
    for _ in 0..m {
        let v: Vec<f32> = (0..dim).map(|_| r()).collect();
        let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        out.extend(v.iter().map(|x| x / n));
    }
    out
}

/// Each `dim`-wide row scaled to unit L2 norm (zero rows stay zero).
fn unit_rows_of(rows: &[f32], dim: usize) -> Vec<f32> {
    let mut out = rows.to_vec();
    for r in out.chunks_exact_mut(dim) {
        let _ = crate::similarity::normalize_in_place(r);
    }
    out
}

/// Gaussians at the origin over `codebook` (rows `dim` wide), one per `(id, entries)`, each
/// entry a `(codebook row, a)` pair of its ragged row.
fn at_origin(dim: usize, codebook: Vec<f32>, gaussians: &[(u32, &[(u32, f32)])]) -> SparseMixture {
    let mut parts = SparseMixture {
        dim,
        codebook,
        offsets: vec![0],
        ..Default::default()
    };
    for &(id, entries) in gaussians {
        parts.gaussian_ids.push(id);
        parts.means.push([0.0; 3]);
        for &(atom, a) in entries {
            parts.atoms.push(atom);
            parts.weights.push(a);
        }
        parts.offsets.push(parts.atoms.len());
    }
    parts
}

/// N Gaussians, each mixing up to 4 of M rows with positive weights.
fn sample(n: usize, m: usize, dim: usize, seed: u64) -> SparseMixture {
    let mut r = stream(seed ^ 0x5eed);
    let mut parts = SparseMixture {
        dim,
        model_id: "color-clip-visual".into(),
        codebook: unit_rows(m, dim, seed),
        gaussian_ids: (0..n as u32).map(|i| 3 * i + 1).collect(),
        means: (0..n).map(|i| [i as f32, 0.5, -(i as f32)]).collect(),
        offsets: vec![0],
        ..Default::default()
    };
    for i in 0..n {
        let k = 1 + i % 4;
        for t in 0..k {
            parts.atoms.push(((i * 7 + t * 3) % m) as u32);
            parts.weights.push(0.1 + r().abs() * 5.0);
        }
        parts.offsets.push(parts.atoms.len());
    }
    parts
}

/// A new temporary folder, and the path `name` in it (a relative path) where `mix` was written.
fn written_in_tempdir(mix: &MixtureEmbeddings, name: &str) -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join(name);
    mix.write(&p).unwrap();
    (dir, p)
}

/// The f64 normalised weighted mean, straight from E_k = Σ a E / Σ a.
fn exact(parts: &SparseMixture, i: usize) -> Vec<f64> {
    let d = parts.dim;
    let mut acc = vec![0f64; d];
    for e in parts.offsets[i]..parts.offsets[i + 1] {
        let a = parts.atoms[e] as usize;
        for (s, &v) in acc.iter_mut().zip(&parts.codebook[a * d..(a + 1) * d]) {
            *s += f64::from(parts.weights[e]) * v as f64;
        }
    }
    let n = acc.iter().map(|v| v * v).sum::<f64>().sqrt();
    acc.iter().map(|v| v / n).collect()
}

#[test]
fn reconstruction_is_the_normalised_weighted_mean_and_unit_length() {
    let parts = sample(40, 23, 16, 7);
    let mix = MixtureEmbeddings::from_sparse(parts.clone()).unwrap();
    assert_eq!(mix.len(), 40);
    assert_eq!(mix.keep, 4);
    mix.validate().unwrap();
    for i in 0..mix.len() {
        let v = mix.vector(i);
        let e = exact(&parts, i);
        let max = v
            .iter()
            .zip(&e)
            .map(|(a, b)| (*a as f64 - b).abs())
            .fold(0.0, f64::max);
        assert!(max < 1e-3, "Gaussian {i}: max |Δ| {max}");
        let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        assert!((norm - 1.0).abs() < 1e-3, "norm {norm}");
        // Slots ordered by decreasing weight, empty ones last.
        let w = &mix.weights[i * 4..(i + 1) * 4];
        assert!(w.windows(2).all(|p| p[0] >= p[1]));
        let used = mix.atoms[i * 4..(i + 1) * 4]
            .iter()
            .filter(|&&a| a != UNUSED)
            .count();
        assert_eq!(used, 1 + i % 4);
    }
}

#[test]
fn unused_codebook_rows_are_dropped_and_renumbered() {
    let dim = 4;
    let parts = at_origin(
        dim,
        unit_rows(5, dim, 3),
        &[(2, &[(4, 1.0), (1, 3.0)]), (9, &[(4, 2.0)])],
    );
    let mix = MixtureEmbeddings::from_sparse(parts.clone()).unwrap();
    assert_eq!(mix.codebook_len(), 2);
    // Row 1 -> 0, row 4 -> 1; the larger weight (3 on row 1) comes first.
    assert_eq!(mix.atoms, vec![0, 1, 1, UNUSED]);
    assert_eq!(mix.weights[3], 0.0);
    for (j, r) in [1usize, 4].iter().enumerate() {
        for d in 0..dim {
            let want = round_f16(parts.codebook[r * dim + d]);
            assert_eq!(mix.codebook[j * dim + d], want);
        }
    }
    assert_eq!(mix.stored_bytes(), 2 * dim * 2 + 2 * (2 * 6 + 16));
    assert_eq!(mix.bytes_per_gaussian(), mix.stored_bytes() as f64 / 2.0);
}

#[test]
fn scores_equal_dense_cosine_of_the_reconstruction() {
    let mix = MixtureEmbeddings::from_sparse(sample(300, 37, 24, 11)).unwrap();
    let dense = mix.to_dense();
    for i in [0, 17, 299] {
        assert_eq!(&dense[i * 24..(i + 1) * 24], mix.vector(i).as_slice());
    }
    let queries: Vec<Vec<f32>> = (0..3).map(|t| unit_rows(1, 24, 100 + t)).collect();
    let mut q0 = queries[0].clone();
    q0.iter_mut().for_each(|v| *v *= 3.5); // any norm
    let s = mix.scores(&q0).unwrap();
    // The cosine of the reconstruction: its rows are unit only up to f16 rounding.
    let reference = cosine_scores(&unit_rows_of(&dense, 24), 24, &q0).unwrap();
    assert_eq!(s.len(), 300);
    for (a, b) in s.iter().zip(&reference) {
        assert!((a - b).abs() < 1e-5, "{a} vs {b}");
    }
    let refs: Vec<&[f32]> = queries.iter().map(Vec::as_slice).collect();
    let many = mix.scores_many(&refs).unwrap();
    assert_eq!(many.len(), 3);
    for (q, got) in queries.iter().zip(&many) {
        let one = mix.scores(q).unwrap();
        for (a, b) in got.iter().zip(&one) {
            assert!((a - b).abs() < 1e-6);
        }
    }
}

#[test]
fn truncated_mixtures_score_as_eval_colors_cut_variant() {
    // eval-colors' "S = s cut from S": slots past s emptied in place, then the dense cosine
    // of the reconstruction (heldout_variants). `truncated` drops them and the unused rows.
    let mix = MixtureEmbeddings::from_sparse(sample(120, 29, 16, 21)).unwrap();
    let q = unit_rows(1, 16, 77);
    for s in [1, 2, 3, 4, 9] {
        let mut cut = mix.clone();
        for (i, (a, w)) in cut.atoms.iter_mut().zip(cut.weights.iter_mut()).enumerate() {
            if i % mix.keep >= s {
                *a = UNUSED;
                *w = 0.0;
            }
        }
        let reference = cosine_scores(&unit_rows_of(&cut.to_dense(), 16), 16, &q).unwrap();
        let t = mix.truncated(s).unwrap();
        assert_eq!(t.keep, s.min(mix.keep));
        t.validate().unwrap();
        assert!(t.codebook_len() <= mix.codebook_len());
        assert_eq!(t.to_dense(), cut.to_dense());
        for (a, b) in t.scores(&q).unwrap().iter().zip(&reference) {
            assert!((a - b).abs() < 1e-5, "S = {s}: {a} vs {b}");
        }
        let norms = t.norms().unwrap();
        assert!(norms.iter().all(|&n| n.is_finite() && n > 0.0), "{norms:?}");
    }
    assert!(matches!(
        mix.truncated(0),
        Err(Error::Param {
            name: "mixture_slots",
            ..
        })
    ));
}

#[test]
fn max_atom_scores_take_the_best_of_the_strongest_atoms() {
    let mix = MixtureEmbeddings::from_sparse(sample(200, 31, 12, 5)).unwrap();
    let q: Vec<f32> = (0..12).map(|i| (i as f32 * 0.7).sin()).collect();
    let qn = dot(&q, &q).sqrt();
    for top in [1, 2, mix.keep, mix.keep + 3] {
        let s = mix.max_atom_scores(&q, top).unwrap();
        assert_eq!(s.len(), mix.len());
        for (i, &got) in s.iter().enumerate() {
            let slots = i * mix.keep..(i + 1) * mix.keep;
            let want = mix.atoms[slots]
                .iter()
                .take(top)
                .filter(|&&a| a != UNUSED)
                .map(|&a| {
                    let row = &mix.codebook[a as usize * mix.dim..(a as usize + 1) * mix.dim];
                    dot(row, &q) / (qn * dot(row, row).sqrt())
                })
                .fold(f32::NEG_INFINITY, f32::max);
            assert!(
                (got - want).abs() < 1e-5,
                "row {i} top {top}: {got} vs {want}"
            );
        }
    }
    // The max over more atoms never falls.
    let one = mix.max_atom_scores(&q, 1).unwrap();
    let all = mix.max_atom_scores(&q, mix.keep).unwrap();
    assert!(one.iter().zip(&all).all(|(a, b)| b >= a));
    assert!(matches!(
        mix.max_atom_scores(&q, 0),
        Err(Error::Param { name: "top", .. })
    ));
    // A zero query has no direction; one of another width belongs to another model.
    assert!(matches!(
        mix.max_atom_scores(&[0.0; 12], 1),
        Err(Error::Query { field: "text", .. })
    ));
    assert!(matches!(
        mix.max_atom_scores(&[1.0; 11], 1),
        Err(Error::Mismatch { .. })
    ));
}

#[test]
fn bad_queries_are_typed_errors() {
    let mix = MixtureEmbeddings::from_sparse(sample(5, 4, 8, 1)).unwrap();
    let no_direction =
        |r: Result<Vec<f32>>| matches!(r, Err(Error::Query { field: "text", .. }));
    assert!(no_direction(mix.scores(&[0.0; 8])));
    assert!(matches!(mix.scores(&[1.0; 7]), Err(Error::Mismatch { .. })));
    assert!(no_direction(mix.scores(&[f32::NAN; 8])));
    assert!(matches!(
        mix.scores_many(&[&[1.0; 8], &[0.0; 8]]),
        Err(Error::Query { .. })
    ));
    let mut broken = mix.clone();
    broken.atoms.pop();
    assert!(matches!(broken.scores(&[1.0; 8]), Err(Error::Internal(_))));
}

#[test]
fn write_read_round_trip_is_exact() {
    let mix = MixtureEmbeddings::from_sparse(sample(50, 11, 12, 5)).unwrap();
    let (dir, p) = written_in_tempdir(&mix, "sub/mixture.safetensors");
    assert!(!dir.path().join("sub/mixture.safetensors.partial").exists());
    let back = MixtureEmbeddings::read(&p).unwrap();
    assert_eq!(back, mix);
    let len = std::fs::metadata(&p).unwrap().len() as usize;
    assert!(len >= mix.stored_bytes() && len < mix.stored_bytes() + 1024);
    // Empty mixtures round-trip too.
    let empty = MixtureEmbeddings::from_sparse(SparseMixture {
        dim: 12,
        offsets: vec![0],
        ..Default::default()
    })
    .unwrap();
    empty.write(&p).unwrap();
    assert_eq!(MixtureEmbeddings::read(&p).unwrap(), empty);
    assert_eq!(empty.bytes_per_gaussian(), 0.0);
}

#[test]
fn the_same_mixture_always_writes_the_same_bytes() {
    // The metadata went through a HashMap, whose order changes from map to map: files of
    // one run differed in their header. Now the keys are sorted.
    let dir = tempfile::tempdir().unwrap();
    let mix = MixtureEmbeddings::from_sparse(sample(20, 7, 8, 3)).unwrap();
    let bytes: Vec<Vec<u8>> = (0..6)
        .map(|i| {
            let p = dir.path().join(format!("m{i}.safetensors"));
            mix.write(&p).unwrap();
            std::fs::read(&p).unwrap()
        })
        .collect();
    assert!(bytes.iter().all(|b| *b == bytes[0]));
    let n = u64::from_le_bytes(bytes[0][..8].try_into().unwrap()) as usize;
    assert_eq!(n % 8, 0, "header padded to 8 bytes");
    let header = std::str::from_utf8(&bytes[0][8..8 + n]).unwrap();
    assert!(
        header.starts_with(r#"{"__metadata__":{"dim":"8","format":"slag-mixture","keep":"4","#),
        "{header}"
    );
    // Any safetensors reader takes it.
    let (_, meta) = safetensors::SafeTensors::read_metadata(&bytes[0]).unwrap();
    assert_eq!(
        meta.metadata().as_ref().and_then(|m| m.get("version")),
        Some(&VERSION.to_string())
    );
}

#[test]
fn corrupt_or_inconsistent_files_are_format_errors() {
    let mix = MixtureEmbeddings::from_sparse(sample(6, 5, 4, 2)).unwrap();
    let (_dir, p) = written_in_tempdir(&mix, "m.safetensors");
    let bytes = std::fs::read(&p).unwrap();
    std::fs::write(&p, &bytes[..bytes.len() - 5]).unwrap();
    assert!(matches!(
        MixtureEmbeddings::read(&p),
        Err(Error::Format { .. })
    ));
    std::fs::write(&p, b"not safetensors at all").unwrap();
    assert!(matches!(
        MixtureEmbeddings::read(&p),
        Err(Error::Format { .. })
    ));
    // A dense embeddings file is another format.
    let other = safetensors::serialize(Vec::<(&str, TensorView)>::new(), None).unwrap();
    std::fs::write(&p, other).unwrap();
    assert!(matches!(
        MixtureEmbeddings::read(&p),
        Err(Error::Format { .. })
    ));
    // Atom out of range: written by hand past validate.
    let mut bad = mix.clone();
    bad.atoms[0] = 99;
    assert!(matches!(bad.write(&p), Err(Error::Internal(_))));
    let write_raw = |m: &MixtureEmbeddings, keep_meta: usize| {
        let book: Vec<f16> = m.codebook.iter().map(|&v| f16::from_f32(v)).collect();
        let w: Vec<f16> = m.weights.iter().map(|&v| f16::from_f32(v)).collect();
        let (n, s) = (m.len(), m.keep);
        let t = vec![
            (
                "codebook",
                TensorView::new(
                    Dtype::F16,
                    vec![m.codebook_len(), m.dim],
                    bytemuck::cast_slice(&book),
                )
                .unwrap(),
            ),
            (
                "atoms",
                TensorView::new(Dtype::U32, vec![n, s], bytemuck::cast_slice(&m.atoms))
                    .unwrap(),
            ),
            (
                "weights",
                TensorView::new(Dtype::F16, vec![n, s], bytemuck::cast_slice(&w)).unwrap(),
            ),
            (
                "gaussian_ids",
                TensorView::new(Dtype::U32, vec![n], bytemuck::cast_slice(&m.gaussian_ids))
                    .unwrap(),
            ),
            (
                "means",
                TensorView::new(Dtype::F32, vec![n, 3], bytemuck::cast_slice(&m.means))
                    .unwrap(),
            ),
        ];
        let meta: HashMap<String, String> = [
            ("format", FORMAT.to_string()),
            ("version", VERSION.to_string()),
            ("dim", m.dim.to_string()),
            ("keep", keep_meta.to_string()),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect();
        std::fs::write(&p, safetensors::serialize(t, Some(meta)).unwrap()).unwrap();
    };
    write_raw(&mix, mix.keep);
    assert_eq!(MixtureEmbeddings::read(&p).unwrap().atoms, mix.atoms);
    write_raw(&bad, bad.keep);
    assert!(matches!(
        MixtureEmbeddings::read(&p),
        Err(Error::Format { .. })
    ));
    write_raw(&mix, mix.keep + 1);
    assert!(matches!(
        MixtureEmbeddings::read(&p),
        Err(Error::Format { .. })
    ));
    let mut unsorted = mix.clone();
    unsorted.gaussian_ids.swap(0, 1);
    write_raw(&unsorted, mix.keep);
    assert!(matches!(
        MixtureEmbeddings::read(&p),
        Err(Error::Format { .. })
    ));
}

#[test]
fn cancelling_or_inconsistent_rows_are_rejected() {
    let base = at_origin(2, vec![1.0, 0.0, -1.0, 0.0], &[(0, &[(0, 1.0), (1, 1.0)])]);
    assert!(matches!(
        MixtureEmbeddings::from_sparse(base.clone()),
        Err(Error::Invalid(_))
    ));
    let mut repeated = base.clone();
    repeated.atoms = vec![0, 0];
    assert!(matches!(
        MixtureEmbeddings::from_sparse(repeated),
        Err(Error::Invalid(_))
    ));
    let mut out_of_range = base.clone();
    out_of_range.atoms = vec![0, 2];
    assert!(matches!(
        MixtureEmbeddings::from_sparse(out_of_range),
        Err(Error::Invalid(_))
    ));
    let mut short = base;
    short.offsets = vec![0, 1];
    assert!(matches!(
        MixtureEmbeddings::from_sparse(short),
        Err(Error::Invalid(_))
    ));
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]
    /// For random sparse mixtures the mixture scores equal dense cosine scores of `to_dense()`.
    #[test]
    fn scores_match_dense_scores(
        n in 1usize..60, m in 1usize..20, dim in 1usize..40, seed in any::<u64>(),
    ) {
        let mut parts = sample(n, m, dim, seed);
        // Drop repeats that `sample` makes when m is small.
        let mut atoms = Vec::new();
        let mut weights = Vec::new();
        let mut offsets = vec![0];
        for i in 0..n {
            let mut seen = std::collections::HashSet::new();
            for e in parts.offsets[i]..parts.offsets[i + 1] {
                if seen.insert(parts.atoms[e]) {
                    atoms.push(parts.atoms[e]);
                    weights.push(parts.weights[e]);
                }
            }
            offsets.push(atoms.len());
        }
        (parts.atoms, parts.weights, parts.offsets) = (atoms, weights, offsets);
        // Positive weights on random directions can cancel only by accident; skip then.
        let Ok(mix) = MixtureEmbeddings::from_sparse(parts) else { return Ok(()) };
        let dense = mix.to_dense();
        let q = unit_rows(1, dim, seed ^ 99);
        let s = mix.scores(&q).unwrap();
        let reference = cosine_scores(&unit_rows_of(&dense, dim), dim, &q).unwrap();
        for (a, b) in s.iter().zip(&reference) {
            prop_assert!((a - b).abs() < 1e-5, "{} vs {}", a, b);
        }
    }
}
