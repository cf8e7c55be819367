//! [`MixtureEmbeddings::from_sparse`] against a reference: the straightforward build (one row
//! `Vec` per Gaussian, collected, then packed) kept here as the oracle. The two must agree bit
//! for bit, errors and their messages included, on random sparse mixtures.

#![allow(clippy::unwrap_used)]

use super::*;
use crate::rng::SplitMix64;

/// The reference checks of the parts: serial passes, the first failing check's message.
fn reference_codebook_rows(p: &SparseMixture) -> Result<usize> {
    let (dim, n, entries) = (p.dim, p.gaussian_ids.len(), p.atoms.len());
    let m = p.codebook.len().checked_div(dim).unwrap_or(0);
    let offsets = &p.offsets;
    let lengths_agree = p.means.len() == n
        && offsets.len() == n + 1
        && p.weights.len() == entries
        && offsets.first() == Some(&0)
        && offsets.last() == Some(&entries)
        && offsets.windows(2).all(|w| w[0] <= w[1]);
    let finite =
        p.codebook.iter().all(|v| v.is_finite()) && p.weights.iter().all(|v| v.is_finite());
    let message = if dim == 0 || !p.codebook.len().is_multiple_of(dim) {
        format!("codebook of {} values for dim {dim}", p.codebook.len())
    } else if m >= UNUSED as usize {
        format!("{m} codebook rows; at most {} fit u32 ids", UNUSED - 1)
    } else if !lengths_agree {
        let lengths = [p.means.len(), offsets.len(), entries, p.weights.len()];
        let [a, b, c, d] = lengths;
        format!("{n} ids, {a} means, {b} offsets, {c} atoms, {d} weights disagree")
    } else if !p.gaussian_ids.windows(2).all(|w| w[0] < w[1]) {
        "Gaussian ids are not strictly ascending".into()
    } else if !finite {
        "non-finite codebook value or weight".into()
    } else if let Some(a) = p.atoms.iter().find(|&&a| a as usize >= m) {
        format!("atom {a} beyond the {m} codebook rows")
    } else {
        return Ok(m);
    };
    Err(Error::Invalid(format!("mixture: {message}")))
}

/// The reference renumbering and f16 rounding of the used codebook rows (serial).
fn reference_used_codebook(
    codebook: &[f32],
    dim: usize,
    m: usize,
    atoms: &[u32],
    weights: &[f32],
) -> (Vec<u32>, Vec<f32>) {
    let mut new_row = vec![UNUSED; m];
    for (i, &a) in atoms.iter().enumerate() {
        if weights[i] != 0.0 {
            new_row[a as usize] = 0;
        }
    }
    let mut kept_rows = 0u32;
    let mut book = Vec::new();
    for (r, slot) in new_row.iter_mut().enumerate() {
        if *slot == 0 {
            *slot = kept_rows;
            kept_rows += 1;
            book.extend(
                codebook[r * dim..(r + 1) * dim]
                    .iter()
                    .map(|&v| round_f16(v)),
            );
        }
    }
    (new_row, book)
}

/// The reference Gram matrix: `[M * M]`, entry `(s, t)` the f64 dot product of codebook rows
/// `s` and `t`, summed in dimension order.
fn reference_gram(book: &[f32], dim: usize) -> Vec<f64> {
    let m = book.len() / dim;
    let mut g = vec![0f64; m * m];
    for s in 0..m {
        for t in 0..m {
            let mut dot = 0f64;
            for d in 0..dim {
                dot += book[s * dim + d] as f64 * book[t * dim + d] as f64;
            }
            g[s * m + t] = dot;
        }
    }
    g
}

/// The reference row: sorted, checked with an allocated id list, normalised with an allocated
/// accumulator, or with the Gram matrix `gram` (`[M * M]`) when given.
fn reference_row(
    mut row: Vec<(u32, f64)>,
    book: &[f32],
    dim: usize,
    gram: Option<&[f64]>,
    id: u32,
) -> std::result::Result<Vec<(u32, f64)>, String> {
    row.sort_unstable_by(|x, y| y.1.total_cmp(&x.1).then(x.0.cmp(&y.0)));
    let mut ids: Vec<u32> = row.iter().map(|r| r.0).collect();
    ids.sort_unstable();
    if ids.windows(2).any(|w| w[0] == w[1]) {
        return Err(format!("Gaussian {id} repeats an atom"));
    }
    let norm = match gram {
        Some(g) => {
            let m = book.len() / dim;
            let mut square = 0f64;
            for &(s, a) in &row {
                for &(t, b) in &row {
                    square += a * b * g[s as usize * m + t as usize];
                }
            }
            square.sqrt()
        }
        None => {
            let mut acc = vec![0f64; dim];
            for &(a, w) in &row {
                let e = &book[a as usize * dim..(a as usize + 1) * dim];
                acc.iter_mut().zip(e).for_each(|(s, &v)| *s += w * v as f64);
            }
            acc.iter().map(|v| v * v).sum::<f64>().sqrt()
        }
    };
    if !(norm.is_finite() && norm > 0.0) {
        return Err(format!(
            "Gaussian {id}: its weighted mask embeddings sum to zero (no direction)"
        ));
    }
    let mut out = Vec::with_capacity(row.len());
    for (a, w) in row {
        let s = w / norm;
        if s.abs() > MAX_WEIGHT as f64 {
            return Err(format!(
                "Gaussian {id}: weight {s:e} beyond the f16 range (its mask embeddings \
                 nearly cancel out); such a Gaussian cannot be stored as a mixture, \
                 use the dense embeddings file"
            ));
        }
        out.push((a, round_f16(s as f32) as f64));
    }
    Ok(out)
}

/// The reference build: one `Vec` per Gaussian, collected, the first error in id order, packed;
/// norms from the Gram matrix where `gram` says.
pub(super) fn reference_from_sparse(
    parts: SparseMixture,
    gram: GramUse,
) -> Result<MixtureEmbeddings> {
    let m = reference_codebook_rows(&parts)?;
    let p = parts;
    let (dim, offsets, atoms, weights) = (p.dim, &p.offsets, &p.atoms, &p.weights);
    let gaussian_ids = &p.gaussian_ids;
    let (new_row, book) = reference_used_codebook(&p.codebook, dim, m, atoms, weights);
    let used = book.len() / dim;
    let gram = gram
        .applies(used, atoms.len())
        .then(|| reference_gram(&book, dim));
    let rows: Vec<std::result::Result<Vec<(u32, f64)>, String>> = (0..gaussian_ids.len())
        .into_par_iter()
        .map(|i| {
            let row: Vec<(u32, f64)> = (offsets[i]..offsets[i + 1])
                .filter(|&e| weights[e] != 0.0)
                .map(|e| (new_row[atoms[e] as usize], f64::from(weights[e])))
                .collect();
            reference_row(row, &book, dim, gram.as_deref(), gaussian_ids[i])
        })
        .collect();
    let kept = rows
        .into_iter()
        .collect::<std::result::Result<Vec<_>, String>>()
        .map_err(|m| Error::Invalid(format!("mixture: {m}")))?;
    let n = kept.len();
    let keep = kept.iter().map(Vec::len).max().unwrap_or(0).max(1);
    let mut out_atoms = vec![UNUSED; n * keep];
    let mut out_weights = vec![0f32; n * keep];
    for (i, row) in kept.iter().enumerate() {
        for (s, &(a, w)) in row.iter().enumerate() {
            out_atoms[i * keep + s] = a;
            out_weights[i * keep + s] = w as f32;
        }
    }
    Ok(MixtureEmbeddings {
        codebook: book,
        keep,
        atoms: out_atoms,
        weights: out_weights,
        ..MixtureEmbeddings {
            dim,
            model_id: p.model_id,
            gaussian_ids: p.gaussian_ids,
            means: p.means,
            ..Default::default()
        }
    })
}

/// The two results as comparable bits: values by their bit patterns, errors by their message.
fn bits(r: &Result<MixtureEmbeddings>) -> std::result::Result<String, String> {
    let f32_bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    match r {
        Ok(m) => Ok(format!(
            "dim {} model {:?} keep {} codebook {:?} ids {:?} means {:?} atoms {:?} weights {:?}",
            m.dim,
            m.model_id,
            m.keep,
            f32_bits(&m.codebook),
            m.gaussian_ids,
            m.means
                .iter()
                .flatten()
                .map(|x| x.to_bits())
                .collect::<Vec<_>>(),
            m.atoms,
            f32_bits(&m.weights),
        )),
        Err(Error::Invalid(msg)) => Err(msg.clone()),
        Err(e) => Err(format!("not Invalid: {e:?}")),
    }
}

/// The build against the reference, bit for bit, with the norms from the sums, from the Gram
/// matrix, and from the one the build picks; the last's outcome.
fn assert_same(parts: SparseMixture, what: &str) -> std::result::Result<String, String> {
    for gram in [GramUse::Never, GramUse::Always] {
        let got = bits(&MixtureEmbeddings::from_sparse_with(parts.clone(), gram));
        let want = bits(&reference_from_sparse(parts.clone(), gram));
        assert_eq!(got, want, "{what}, {gram:?}");
    }
    let want = bits(&reference_from_sparse(parts.clone(), GramUse::WhenCheaper));
    let got = bits(&MixtureEmbeddings::from_sparse(parts));
    assert_eq!(got, want, "{what}, the build's pick");
    got
}

/// [`assert_same`] on the [`random_parts`] of seeds `first_seed + i` for `i` in `0..cases`
/// (labelled `seed {i}`); the build's outcomes, in that order.
fn assert_same_over_seeds(
    n: usize,
    m: usize,
    dim: usize,
    f: Flavour,
    first_seed: u64,
    cases: u64,
) -> Vec<std::result::Result<String, String>> {
    (0..cases)
        .map(|i| {
            assert_same(
                random_parts(n, m, dim, f, first_seed + i),
                &format!("seed {i}"),
            )
        })
        .collect()
}

/// What a random case may hold besides plain positive rows.
#[derive(Clone, Copy)]
struct Flavour {
    /// Longest row (entries, zeros included).
    keep: usize,
    /// Rows with no entry, or only zero weights (each one an error).
    empty: bool,
    /// A repeated atom among the non-zero weights of some row.
    repeat: bool,
    /// Opposite codebook rows mixed with equal weights (zero sum) or nearly equal rows
    /// (f16 overflow).
    cancel: bool,
    /// Negative and signed-zero weights.
    signs: bool,
}

/// Plain positive rows of up to 4 entries.
const PLAIN: Flavour = Flavour {
    keep: 4,
    empty: false,
    repeat: false,
    cancel: false,
    signs: false,
};

/// A random sparse mixture: `n` Gaussians over `m` codebook rows of width `dim`. Weights come
/// from a small set of values so that ties are common; codebook rows 0 and 1 are opposite and
/// rows 2 and 3 nearly opposite (after f16 rounding) in the cancelling cases.
fn random_parts(n: usize, m: usize, dim: usize, f: Flavour, seed: u64) -> SparseMixture {
    let mut r = SplitMix64::new(seed);
    let codebook = random_codebook(&mut r, m, dim, f, seed);
    let mut parts = SparseMixture {
        dim,
        model_id: format!("model-{seed}"),
        codebook,
        gaussian_ids: (0..n as u32).map(|i| 2 * i + (seed % 3) as u32).collect(),
        means: (0..n)
            .map(|i| [i as f32, -0.5, r.next_f64() as f32])
            .collect(),
        offsets: vec![0],
        ..Default::default()
    };
    for _ in 0..n {
        push_random_row(&mut parts, &mut r, m, f);
    }
    parts
}

/// `[m * dim]` values in `[-1, 1)`, with the cancelling rows (rows 0 and 1 summing to zero, rows
/// 2 and 3 to 1e-5, an f16 subnormal, in dimension 0) when `f.cancel`, and values on an f16
/// rounding tie, f16 subnormals and values that round to zero at places set by `seed`.
fn random_codebook(r: &mut SplitMix64, m: usize, dim: usize, f: Flavour, seed: u64) -> Vec<f32> {
    let mut codebook: Vec<f32> = (0..m * dim).map(|_| r.range(-1.0, 1.0) as f32).collect();
    if f.cancel && m >= 4 {
        for d in 0..dim {
            let v = if d == 0 { 0.0 } else { codebook[d] };
            codebook[d] = v;
            codebook[dim + d] = -v;
            codebook[2 * dim + d] = v;
            codebook[3 * dim + d] = if d == 0 { 1e-5 } else { -v };
        }
    }
    let edges = [
        1.0 + 2f32.powi(-11),
        -(1.0 + 3.0 * 2f32.powi(-11)),
        3e-6,
        -6e-8,
        1e-9,
    ];
    for (k, v) in edges.iter().enumerate() {
        codebook[(k * 31 + seed as usize) % (m * dim)] = *v;
    }
    codebook
}

/// Appends one random row over `m` codebook rows to `parts`: up to `f.keep` consecutive atoms
/// with tie-prone weights, and, as `f` allows, an empty or all-zero row, signed and zero
/// weights, a repeated atom, or a cancelling pair of rows with equal weights.
fn push_random_row(parts: &mut SparseMixture, r: &mut SplitMix64, m: usize, f: Flavour) {
    let ties = [0.25, 0.5, 1.0, 1.0, 2.0, 3.0];
    let len = if f.empty && r.next_u64().is_multiple_of(40) {
        0
    } else {
        1 + (r.next_u64() % f.keep as u64) as usize
    };
    let start = parts.atoms.len();
    let first = (r.next_u64() % m as u64) as u32;
    for t in 0..len {
        parts.atoms.push((first + t as u32) % m as u32);
        let u = r.next_u64();
        let w = if u.is_multiple_of(3) {
            r.range(0.01, 4.0) as f32
        } else {
            ties[(u >> 8) as usize % ties.len()]
        };
        // Zeros after a row's first entry, which keeps single-entry rows valid.
        parts.weights.push(match (f.signs, u % 29, t) {
            (true, 1, _) => -w,
            (true, 2, 1..) => -0.0,
            (_, 3, 1..) => 0.0,
            _ => w,
        });
    }
    let row = start..parts.atoms.len();
    if f.empty && len > 0 && r.next_u64().is_multiple_of(60) {
        parts.weights[row.clone()].iter_mut().for_each(|w| *w = 0.0);
    }
    if f.repeat && len >= 2 && r.next_u64().is_multiple_of(50) {
        parts.atoms[row.end - 1] = parts.atoms[row.start];
    }
    if f.cancel && len >= 2 && m >= 4 && r.next_u64().is_multiple_of(50) {
        let pair = if r.next_u64().is_multiple_of(2) {
            [0, 1]
        } else {
            [2, 3]
        };
        parts.atoms.truncate(row.start);
        parts.weights.truncate(row.start);
        parts.atoms.extend(pair);
        parts.weights.extend([1.5, 1.5]);
    }
    parts.offsets.push(parts.atoms.len());
}

#[test]
fn the_build_equals_the_reference_on_random_mixtures() {
    let (mut ok, mut errors) = (0, std::collections::BTreeSet::new());
    for case in 0..160u64 {
        let keep = 1 + (case % 8) as usize;
        let f = Flavour {
            keep,
            empty: case % 5 == 1,
            repeat: case % 5 == 2,
            cancel: case % 5 == 3,
            signs: case % 2 == 0,
        };
        let (n, m, dim) = (
            1 + (case * 37 % 300) as usize,
            8 + (case * 13 % 40) as usize,
            2 + (case * 7 % 32) as usize,
        );
        let parts = random_parts(n, m, dim, f, case);
        match assert_same(
            parts,
            &format!("case {case}: n {n} m {m} dim {dim} keep {keep}"),
        ) {
            Ok(_) => ok += 1,
            Err(msg) => {
                let kinds = ["repeats an atom", "sum to zero", "beyond the f16 range"];
                let kind = kinds.iter().find(|k| msg.contains(*k));
                errors.insert(*kind.unwrap_or_else(|| panic!("case {case}: {msg}")));
            }
        }
    }
    // The cases reach every outcome: built mixtures and the three row errors.
    assert!(ok > 50, "{ok} built");
    assert_eq!(errors.len(), 3, "{errors:?}");
}

#[test]
fn the_first_failing_gaussian_in_id_order_is_reported() {
    // Many failing rows spread over a large mixture: the reported one is the first of them
    // however the work is split.
    let f = Flavour {
        empty: true,
        repeat: true,
        cancel: true,
        signs: true,
        ..PLAIN
    };
    for got in assert_same_over_seeds(20_000, 24, 8, f, 1000, 4) {
        assert!(got.is_err());
    }
}

#[test]
fn long_rows_with_repeats_equal_the_reference() {
    // Rows longer than the inline duplicate check.
    let f = Flavour {
        keep: 48,
        repeat: true,
        signs: true,
        ..PLAIN
    };
    let _ = assert_same_over_seeds(300, 400, 6, f, 50, 6);
    let row: Vec<u32> = (0..40).map(|t| 7 * t).collect();
    let mut parts = SparseMixture {
        dim: 6,
        codebook: random_parts(1, 300, 6, f, 9).codebook,
        gaussian_ids: vec![4, 8],
        means: vec![[0.0; 3]; 2],
        offsets: vec![0, 40, 80],
        atoms: row.iter().chain(&row).copied().collect(),
        weights: (0..80).map(|t| 1.0 + (t % 9) as f32).collect(),
        ..Default::default()
    };
    parts.atoms[79] = parts.atoms[43];
    let err = assert_same(parts, "a long row repeating an atom");
    assert!(err.unwrap_err().contains("repeats an atom"));
}

#[test]
fn bad_parts_give_the_reference_messages() {
    let f = Flavour { keep: 3, ..PLAIN };
    let base = random_parts(30, 9, 5, f, 77);
    assert!(assert_same(base.clone(), "base").is_ok());
    type Edit = fn(&mut SparseMixture);
    let cases: [(&str, Edit); 13] = [
        ("dim 0", |p| p.dim = 0),
        ("ragged codebook", |p| {
            p.codebook.pop();
        }),
        ("short means", |p| {
            p.means.pop();
        }),
        ("offsets not ascending", |p| p.offsets[5] = p.offsets[7]),
        ("offsets past the atoms", |p| {
            *p.offsets.last_mut().unwrap() += 1
        }),
        ("short weights", |p| {
            p.weights.pop();
        }),
        ("repeated id", |p| p.gaussian_ids[20] = p.gaussian_ids[19]),
        ("NaN codebook", |p| p.codebook[17] = f32::NAN),
        ("infinite weight", |p| p.weights[11] = f32::INFINITY),
        ("atoms out of range", |p| (p.atoms[4], p.atoms[9]) = (12, 9)),
        ("codebook beyond f16", |p| {
            p.codebook.iter_mut().step_by(7).for_each(|v| *v *= 1e5)
        }),
        ("all weights zero", |p| p.weights.fill(0.0)),
        ("one row all zero", |p| {
            let row = p.offsets[3]..p.offsets[4];
            p.weights[row].fill(-0.0)
        }),
    ];
    for (what, edit) in cases {
        let mut p = base.clone();
        edit(&mut p);
        assert!(assert_same(p, what).is_err(), "{what}");
    }
    // Empty mixtures, with and without a codebook.
    for m in [0, 3] {
        let p = SparseMixture {
            dim: 4,
            codebook: vec![0.5; m * 4],
            offsets: vec![0],
            ..Default::default()
        };
        assert!(assert_same(p, "empty").is_ok());
    }
}

#[test]
fn norms_from_the_gram_matrix_agree_with_the_sums() {
    // The same rows normalised both ways: the same atoms, and weights that differ at most where
    // the f64 norms' last bits move an f16 rounding (one f16 step, seldom).
    let f = Flavour { keep: 6, ..PLAIN };
    let (mut weights, mut moved) = (0usize, 0usize);
    for seed in 0..6 {
        let parts = random_parts(4_000, 64, 48, f, 300 + seed);
        let gram = MixtureEmbeddings::from_sparse_with(parts.clone(), GramUse::Always).unwrap();
        let sums = MixtureEmbeddings::from_sparse_with(parts, GramUse::Never).unwrap();
        assert_eq!(gram.atoms, sums.atoms, "seed {seed}");
        for (&x, &y) in gram.weights.iter().zip(&sums.weights) {
            let step = f16::from_f32(x.abs().max(y.abs())).to_f32() * 2f32.powi(-10);
            assert!((x - y).abs() <= step, "seed {seed}: {x} against {y}");
            weights += 1;
            moved += usize::from(x != y);
        }
    }
    assert!(
        moved * 1000 <= weights,
        "{moved} of {weights} weights moved"
    );
}

/// Bit-for-bit equality of two stored forms (no text made of them: the timing's are large).
fn same_bits(a: &MixtureEmbeddings, b: &MixtureEmbeddings) -> bool {
    let f32_eq = |x: &[f32], y: &[f32]| {
        x.len() == y.len() && x.iter().zip(y).all(|(p, q)| p.to_bits() == q.to_bits())
    };
    (a.dim, &a.model_id, a.keep, &a.gaussian_ids, &a.atoms)
        == (b.dim, &b.model_id, b.keep, &b.gaussian_ids, &b.atoms)
        && f32_eq(&a.codebook, &b.codebook)
        && f32_eq(&a.weights, &b.weights)
        && f32_eq(a.means.as_flattened(), b.means.as_flattened())
}

/// Times the build of 3M Gaussians (`SLAG_MIXTURE_TIMING_N` to change) × 4 atoms over a
/// 512-wide codebook of 20,000 rows (`SLAG_MIXTURE_TIMING_M`; [`GramUse::WhenCheaper`] says
/// where the norms come from the Gram matrix) against the reference:
/// `cargo test -p slag-common --lib build_timing -- --ignored --nocapture` (with an optimised
/// build of this crate for figures that mean anything).
#[test]
#[ignore = "a timing, not a test"]
fn build_timing() {
    let setting = |name: &str, default: usize| {
        std::env::var(name)
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(default)
    };
    let (n, m) = (
        setting("SLAG_MIXTURE_TIMING_N", 3_000_000),
        setting("SLAG_MIXTURE_TIMING_M", 20_000),
    );
    let (dim, keep) = (512usize, 4usize);
    let mut r = SplitMix64::new(5);
    let mut parts = SparseMixture {
        dim,
        codebook: (0..m * dim).map(|_| r.range(-1.0, 1.0) as f32).collect(),
        gaussian_ids: (0..n as u32).collect(),
        means: vec![[0.0; 3]; n],
        offsets: Vec::with_capacity(n + 1),
        atoms: Vec::with_capacity(n * keep),
        weights: Vec::with_capacity(n * keep),
        ..Default::default()
    };
    parts.offsets.push(0);
    for _ in 0..n {
        let first = (r.next_u64() % m as u64) as u32;
        for t in 0..keep as u32 {
            parts.atoms.push((first + 97 * t) % m as u32);
            parts.weights.push(r.range(0.05, 3.0) as f32);
        }
        parts.offsets.push(parts.atoms.len());
    }
    // Seconds and peak resident growth (MiB, Linux) of one build.
    let mib = |bytes: Option<u64>| bytes.unwrap_or(0) as f64 / (1024.0 * 1024.0);
    let cpu = || crate::util::cpu_seconds().unwrap_or(0.0);
    let run = |build: &dyn Fn(SparseMixture) -> Result<MixtureEmbeddings>, parts: SparseMixture| {
        let _ = std::fs::write("/proc/self/clear_refs", "5"); // resets VmHWM
        let (before, cpu0) = (mib(crate::util::rss_bytes()), cpu());
        let t0 = std::time::Instant::now();
        let out = build(parts).unwrap();
        let s = t0.elapsed().as_secs_f64();
        let peak = mib(crate::util::peak_rss_bytes()) - before;
        (
            out,
            format!("{s:.2} s ({:.2} s CPU, +{peak:.0} MiB peak)", cpu() - cpu0),
        )
    };
    let (a, reference) = run(
        &|p| reference_from_sparse(p, GramUse::WhenCheaper),
        parts.clone(),
    );
    let (b, build) = run(&MixtureEmbeddings::from_sparse, parts);
    assert!(same_bits(&a, &b));
    println!(
        "{n} Gaussians x {keep} atoms, D {dim}, M {m}, {} threads: reference {reference}, \
         from_sparse {build}",
        rayon::current_num_threads()
    );
}

/// The reference padding: each row's non-zero entries, in order, then atom 0 and weight 0.
fn reference_padded(
    offsets: &[usize],
    atoms: &[u32],
    weights: &[f32],
    keep: usize,
) -> (Vec<u32>, Vec<f32>) {
    let (mut a, mut w) = (Vec::new(), Vec::new());
    for r in offsets.windows(2) {
        let row: Vec<usize> = (r[0]..r[1]).filter(|&e| weights[e] != 0.0).collect();
        a.extend(row.iter().map(|&e| atoms[e]));
        w.extend(row.iter().map(|&e| weights[e]));
        a.resize(a.len() + keep - row.len(), 0);
        w.resize(w.len() + keep - row.len(), 0.0);
    }
    (a, w)
}

#[test]
fn rows_padded_in_place_equal_the_reference_padding() {
    // Rows longer than `keep` (zeros among them: entries move forward), shorter (they move
    // backward), empty, and rows that already fill their slots (nothing moves).
    let mut r = SplitMix64::new(7);
    let below = |r: &mut SplitMix64, k: u64| r.next_u64() % k;
    for case in 0..200u64 {
        let keep = 1 + (case % 5) as usize;
        let full = case % 4 == 0;
        let n = (case % 37) as usize;
        let (mut offsets, mut atoms, mut weights) = (vec![0], Vec::new(), Vec::new());
        for _ in 0..n {
            let nonzero = if full {
                keep
            } else {
                below(&mut r, keep as u64 + 1) as usize
            };
            let zeros = if full { 0 } else { below(&mut r, 4) as usize };
            let mut row: Vec<f32> = (0..nonzero).map(|_| r.range(0.1, 2.0) as f32).collect();
            for _ in 0..zeros {
                let at = below(&mut r, row.len() as u64 + 1) as usize;
                row.insert(at, if below(&mut r, 2) == 0 { 0.0 } else { -0.0 });
            }
            atoms.extend(row.iter().map(|_| below(&mut r, 1000) as u32));
            weights.extend(row);
            offsets.push(atoms.len());
        }
        let expected = reference_padded(&offsets, &atoms, &weights, keep);
        pad_rows_in_place(offsets, &mut atoms, &mut weights, keep);
        assert_eq!(
            (atoms, weights),
            expected,
            "case {case}: n {n} keep {keep} full {full}"
        );
    }
}
