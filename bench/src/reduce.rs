//! `slag-bench reduce`: the reduction `E_k = Σ_i Σ_j a_kj E_j / Σ_i Σ_j a_kj` (the encoder's
//! serial tail after the last image) in its two loop orders, measured against each other in one
//! run, on a synthetic contribution store of the size of a real scene, plus the embeddings write.
//!
//! - *image-major*: for each image, every entry reads and writes its Gaussian's `D`-wide f64 row
//!   of a chunk-sized accumulator (the order spilled contributions need, since they stream from
//!   disk one image at a time);
//! - *Gaussian-block-major*: each task owns a block of Gaussians whose accumulator stays in cache
//!   while every image's entries of that block are added (the default for in-memory stores).
//!
//! Each order runs the encoder's tail as `encode` does ([`reduce_to_writer`]: the reduction with
//! the f16 write overlapped on a writer thread, then the file's finish); both must write the same
//! bytes, which the run checks before it prints a ratio.
//! With `--mixture-keep K` the tail with the mixture form is timed too (default loop order): the
//! embeddings' pass followed by the mixture's own pass, against the one pass that feeds both
//! ([`reduce_to_writer_with_mixture`]); the two must write the same bytes and gather the same
//! mixture, which the run checks.
//!
//! Store shape: `images` views, each with `entries_per_image` distinct Gaussians drawn uniformly
//! from `gaussians` (ids in `.ply` order carry no spatial order, so a view's ids are scattered),
//! each entry in one of `masks_per_image` masks, with random unit mask embeddings of width `dim`.

use anyhow::{Context, ensure};
use slag_common::embeddings::{EmbeddingsWriter, StoredPrecision};
use slag_common::mixture::SparseMixture;
use slag_common::table::Table;
use slag_encoder::aggregate::{
    ContributionStore, Entry, ImageContribution, ReduceParams, reduce_mixture_chunks,
    reduce_to_writer, reduce_to_writer_with_mixture,
};
use std::time::Instant;

/// Arguments of `slag-bench reduce`.
#[derive(Debug, Clone, clap::Args)]
pub struct ReduceArgs {
    /// Gaussians in the scene (N).
    #[arg(long, default_value_t = 500_000)]
    pub gaussians: u32,
    /// Views (images) contributing.
    #[arg(long, default_value_t = 100)]
    pub images: usize,
    /// Distinct Gaussians each view sees (`a_kj` entries per image).
    #[arg(long, default_value_t = 100_000)]
    pub entries_per_image: usize,
    /// SAM masks per image.
    #[arg(long, default_value_t = 55)]
    pub masks_per_image: u32,
    /// Embedding width D.
    #[arg(long, default_value_t = 512)]
    pub dim: usize,
    /// Runs of each loop order, alternated (the best of each is reported).
    #[arg(long, default_value_t = 2)]
    pub repeats: usize,
    /// f64 accumulator budget in MiB (as `slag-encoder encode --accumulator-memory-mb`).
    #[arg(long, default_value_t = 2048)]
    pub accumulator_memory_mb: usize,
    /// Skip the image-major loop (profiling the default one alone).
    #[arg(long)]
    pub block_major_only: bool,
    /// Also time the tail with the mixture form keeping this many `a_kj` per Gaussian
    /// (`encode --mixture-keep`), in the default loop order: two passes (`reduce_to_writer`, then
    /// `reduce_mixture_chunks`) against the one fused pass (`reduce_to_writer_with_mixture`),
    /// which must give the same embeddings bytes and mixture.
    #[arg(long, value_name = "S")]
    pub mixture_keep: Option<usize>,
    /// Seed of the synthetic store.
    #[arg(long, default_value_t = 7)]
    pub seed: u64,
}

/// SplitMix64: a small deterministic generator for the synthetic store.
struct SplitMix(u64);

impl SplitMix {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in [0, 1).
    fn unit(&mut self) -> f32 {
        (self.next() >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// The synthetic store (all in memory).
fn synthetic_store(
    a: &ReduceArgs,
    spill_dir: std::path::PathBuf,
) -> anyhow::Result<ContributionStore> {
    ensure!(
        a.gaussians > 0 && a.images > 0 && a.masks_per_image > 0 && a.dim > 0,
        "sizes must be positive"
    );
    ensure!(
        a.entries_per_image <= a.gaussians as usize,
        "--entries-per-image {} exceeds --gaussians {}",
        a.entries_per_image,
        a.gaussians
    );
    let mut rng = SplitMix(a.seed);
    let mut store = ContributionStore::new(usize::MAX, spill_dir);
    for _ in 0..a.images {
        let mut ids: Vec<u32> = (0..a.entries_per_image)
            .map(|_| (rng.next() % a.gaussians as u64) as u32)
            .collect();
        ids.sort_unstable();
        ids.dedup();
        let entries = ids
            .into_iter()
            .map(|gaussian| Entry {
                gaussian,
                mask: (rng.next() % a.masks_per_image as u64) as u32,
                weight: 0.01 + rng.unit(),
            })
            .collect();
        let mut mask_embeddings = Vec::with_capacity(a.masks_per_image as usize * a.dim);
        for _ in 0..a.masks_per_image {
            let row: Vec<f32> = (0..a.dim).map(|_| rng.unit() - 0.5).collect();
            let norm = row.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
            mask_embeddings.extend(row.iter().map(|v| v / norm));
        }
        store.push(ImageContribution {
            dim: a.dim,
            mask_embeddings,
            entries,
        })?;
    }
    Ok(store)
}

/// One order's encoder tail: reduction streamed into the f16 embeddings file, then its finish.
struct Tail {
    reduce_s: f64,
    tail_s: f64,
    finish_s: f64,
    observed: usize,
    chunks: usize,
}

fn tail(
    store: &ContributionStore,
    means: &[[f32; 3]],
    a: &ReduceArgs,
    params: ReduceParams,
    path: &std::path::Path,
) -> anyhow::Result<Tail> {
    let t = Instant::now();
    let writer = EmbeddingsWriter::create(path, a.dim, StoredPrecision::F16)?;
    let s = reduce_to_writer(store, means, a.dim, params, writer)?;
    let tail_s = t.elapsed().as_secs_f64();
    let observed = s.writer.len();
    let t = Instant::now();
    s.writer
        .finish("synthetic", a.gaussians as u64, "synthetic")?;
    Ok(Tail {
        reduce_s: s.reduce_s,
        tail_s,
        finish_s: t.elapsed().as_secs_f64(),
        observed,
        chunks: s.chunks,
    })
}

/// One run of the tail with the mixture form: the embeddings streamed to an f16 file and the
/// mixture's sparse parts (not the stored form's build, which both ways share).
struct MixtureTail {
    /// Seconds of the embeddings' reduction (for the fused pass: the shared reduction less the
    /// mixture's gathering, as `encode` reports `timings.reduce`).
    reduce_s: f64,
    /// Seconds that only the mixture costs (two passes: its whole pass; fused: gathering its
    /// kept `a_kj` between chunks, as `encode` reports `mixture_reduce_s` less the build).
    mixture_s: f64,
    /// Seconds from the start until the embeddings' rows are written and the sparse parts ready.
    total_s: f64,
    sparse: SparseMixture,
}

/// The tail with the mixture form, as two passes (`fused` false) or one.
fn mixture_tail(
    store: &ContributionStore,
    means: &[[f32; 3]],
    a: &ReduceArgs,
    params: ReduceParams,
    keep: usize,
    fused: bool,
    path: &std::path::Path,
) -> anyhow::Result<MixtureTail> {
    let t = Instant::now();
    let writer = EmbeddingsWriter::create(path, a.dim, StoredPrecision::F16)?;
    let (streamed, sparse, reduce_s, mixture_s) = if fused {
        let m = reduce_to_writer_with_mixture(store, means, a.dim, params, writer, keep, "m")?;
        let reduce_s = m.streamed.reduce_s - m.gather_s;
        (m.streamed, m.sparse, reduce_s, m.gather_s)
    } else {
        let s = reduce_to_writer(store, means, a.dim, params, writer)?;
        let reduce_s = s.reduce_s;
        let t = Instant::now();
        let (sparse, _) = reduce_mixture_chunks(store, means, a.dim, params, keep, "m")?;
        (s, sparse, reduce_s, t.elapsed().as_secs_f64())
    };
    let total_s = t.elapsed().as_secs_f64();
    streamed
        .writer
        .finish("synthetic", a.gaussians as u64, "synthetic")?;
    Ok(MixtureTail {
        reduce_s,
        mixture_s,
        total_s,
        sparse,
    })
}

/// The two-pass and the fused mixture tails measured against each other; returns the Markdown
/// table, after checking that both wrote the same embeddings and gathered the same mixture.
fn mixture_study(
    store: &ContributionStore,
    means: &[[f32; 3]],
    a: &ReduceArgs,
    params: ReduceParams,
    keep: usize,
    dir: &std::path::Path,
) -> anyhow::Result<String> {
    let ways = [(false, "two passes"), (true, "one fused pass")];
    let best = best_runs(
        a.repeats,
        &ways,
        |i, (fused, _)| {
            let path = dir.join(format!("mixture{i}.safetensors"));
            mixture_tail(store, means, a, params, keep, fused, &path)
        },
        |run| run.total_s,
    )?;
    ensure!(
        same_bytes(
            &dir.join("mixture0.safetensors"),
            &dir.join("mixture1.safetensors")
        )?,
        "the fused tail wrote other embeddings than the two passes"
    );
    ensure!(
        best[0].sparse == best[1].sparse,
        "the fused tail gathered another mixture than the two passes"
    );
    let atoms = best[1].sparse.atoms.len();
    let mut t =
        Table::with_header("tail | embeddings reduce s | mixture's own s | total s | speed-up")
            .right_from(1);
    for ((_, name), b) in ways.iter().zip(&best) {
        t.row([
            name.to_string(),
            format!("{:.2}", b.reduce_s),
            format!("{:.2}", b.mixture_s),
            format!("{:.2}", b.total_s),
            format!("{:.2}", best[0].total_s / b.total_s),
        ]);
    }
    Ok(format!(
        "mixture tail, keep {keep} ({atoms} kept a_kj), default loop order; both ways wrote the \
         same embeddings and gathered the same mixture; best of {} runs each\n\n{t}",
        a.repeats
    ))
}

/// The fastest of `repeats` runs of each of `ways` (by `seconds`), in the order of `ways`; the
/// ways take turns, one run of each per round, so that a slower stretch of the machine falls on
/// all of them. `run` gets a way's index and the way.
///
/// Errors: the first failed run's; no run at all (`repeats` 0 or no way).
fn best_runs<W: Copy, T>(
    repeats: usize,
    ways: &[W],
    mut run: impl FnMut(usize, W) -> anyhow::Result<T>,
    seconds: impl Fn(&T) -> f64,
) -> anyhow::Result<Vec<T>> {
    let mut best: Vec<Option<T>> = ways.iter().map(|_| None).collect();
    for _ in 0..repeats {
        for (i, &way) in ways.iter().enumerate() {
            let r = run(i, way)?;
            if best[i].as_ref().is_none_or(|b| seconds(&r) < seconds(b)) {
                best[i] = Some(r);
            }
        }
    }
    best.into_iter().collect::<Option<_>>().context("no run")
}

/// True when the two files hold the same bytes.
fn same_bytes(a: &std::path::Path, b: &std::path::Path) -> anyhow::Result<bool> {
    use std::io::Read;
    let (mut fa, mut fb) = (std::fs::File::open(a)?, std::fs::File::open(b)?);
    if fa.metadata()?.len() != fb.metadata()?.len() {
        return Ok(false);
    }
    let (mut ba, mut bb) = (vec![0u8; 1 << 24], vec![0u8; 1 << 24]);
    loop {
        let n = fa.read(&mut ba)?;
        if n == 0 {
            return Ok(true);
        }
        fb.read_exact(&mut bb[..n])?;
        if ba[..n] != bb[..n] {
            return Ok(false);
        }
    }
}

/// Runs the study; returns the Markdown table.
pub fn run(a: &ReduceArgs) -> anyhow::Result<String> {
    ensure!(a.repeats > 0, "--repeats must be at least 1");
    let dir = tempfile::tempdir().context("temporary folder for the embeddings files")?;
    let t = Instant::now();
    let store = synthetic_store(a, dir.path().join("spill"))?;
    let build_s = t.elapsed().as_secs_f64();
    let entries = store.entries_in_memory();
    let means: Vec<[f32; 3]> = (0..a.gaussians).map(|k| [k as f32, 0.0, 0.0]).collect();
    let base = ReduceParams {
        accumulator_budget_bytes: a.accumulator_memory_mb << 20,
        ..Default::default()
    };
    let orders: &[(bool, &str)] = if a.block_major_only {
        &[(false, "Gaussian-block-major (default)")]
    } else {
        &[
            (true, "image-major (spilled path)"),
            (false, "Gaussian-block-major (default)"),
        ]
    };
    let best = best_runs(
        a.repeats,
        orders,
        |i, (image_major, _)| {
            let path = dir.path().join(format!("order{i}.safetensors"));
            let params = ReduceParams {
                image_major,
                ..base
            };
            tail(&store, &means, a, params, &path)
        },
        |run| run.tail_s,
    )?;
    if orders.len() == 2 {
        ensure!(
            same_bytes(
                &dir.path().join("order0.safetensors"),
                &dir.path().join("order1.safetensors")
            )?,
            "the two loop orders wrote different embeddings: the reduction is not order-exact"
        );
    }
    let base_tail = best[0].tail_s;
    let mut t = Table::with_header("loop order | reduce s | reduce + overlapped write s | entries/s | speed-up | file finish s")
    .right_from(1);
    for ((_, name), b) in orders.iter().zip(&best) {
        t.row([
            name.to_string(),
            format!("{:.2}", b.reduce_s),
            format!("{:.2}", b.tail_s),
            format!("{:.3e}", entries as f64 / b.reduce_s),
            format!("{:.2}", base_tail / b.tail_s),
            format!("{:.2}", b.finish_s),
        ]);
    }
    let mut table = t.markdown();
    if let Some(keep) = a.mixture_keep {
        table += "\n";
        table += &mixture_study(&store, &means, a, base, keep, dir.path())?;
    }
    Ok(format!(
        "reduce: {} Gaussians ({} observed), {} images, {} a_kj entries, D = {}, {} chunk(s), \
         {} threads, f16 output; store built in {build_s:.1} s; best of {} runs each{}\n\n{table}",
        a.gaussians,
        best[0].observed,
        a.images,
        entries,
        a.dim,
        best[0].chunks,
        rayon::current_num_threads(),
        a.repeats,
        if orders.len() == 2 {
            "; both orders wrote the same bytes"
        } else {
            ""
        },
    ))
}
