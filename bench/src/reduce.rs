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
//! Both give the same f64 sums bit for bit; the run checks that before it prints a ratio.
//! Store shape: `images` views, each with `entries_per_image` distinct Gaussians drawn uniformly
//! from `gaussians` (ids in `.ply` order carry no spatial order, so a view's ids are scattered),
//! each entry in one of `masks_per_image` masks, with random unit mask embeddings of width `dim`.

use anyhow::{Context, ensure};
use slag_common::embeddings::{EmbeddingsWriter, StoredPrecision};
use slag_encoder::aggregate::{ContributionStore, Entry, ImageContribution, ReduceParams, reduce};
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

/// Runs the study; returns the Markdown table.
pub fn run(a: &ReduceArgs) -> anyhow::Result<String> {
    ensure!(a.repeats > 0, "--repeats must be at least 1");
    let dir = tempfile::tempdir().context("temporary folder for the embeddings write")?;
    let t = Instant::now();
    let store = synthetic_store(a, dir.path().join("spill"))?;
    let build_s = t.elapsed().as_secs_f64();
    let entries = store.entries_in_memory();
    let base = ReduceParams {
        accumulator_budget_bytes: a.accumulator_memory_mb << 20,
        ..Default::default()
    };
    let (mut best_image, mut best_block) = (f64::INFINITY, f64::INFINITY);
    let mut results = None;
    for _ in 0..a.repeats {
        for image_major in [true, false] {
            let t = Instant::now();
            let r = reduce(
                &store,
                a.gaussians as usize,
                a.dim,
                ReduceParams {
                    image_major,
                    ..base
                },
            )?;
            let s = t.elapsed().as_secs_f64();
            if image_major {
                best_image = best_image.min(s);
            } else {
                best_block = best_block.min(s);
            }
            match &results {
                None => results = Some(r),
                Some(first) => ensure!(
                    *first == r,
                    "the two loop orders disagree: the reduction is not order-exact"
                ),
            }
        }
    }
    let r = results.context("no run")?;
    // The write as the encoder does it: f16 rows in ascending id order, then the file's assembly.
    let t = Instant::now();
    let path = dir.path().join("embeddings.safetensors");
    let mut w = EmbeddingsWriter::create(&path, a.dim, StoredPrecision::F16)?;
    let means = vec![[0f32; 3]; r.ids.len()];
    w.push(&r.ids, &means, &r.vectors, &r.total_weights)?;
    let push_s = t.elapsed().as_secs_f64();
    let t = Instant::now();
    w.finish("synthetic", a.gaussians as u64, "synthetic")?;
    let finish_s = t.elapsed().as_secs_f64();
    let bytes = std::fs::metadata(&path).map(|m| m.len()).unwrap_or(0);
    let threads = rayon::current_num_threads();
    Ok(format!(
        "reduce: {} Gaussians ({} observed), {} images, {} a_kj entries, D = {}, {} chunk(s), \
         {threads} threads; store built in {build_s:.1} s; best of {} runs each, same f64 sums bit for bit\n\n\
         | loop order | s | entries/s | speed-up |\n|---|---:|---:|---:|\n\
         | image-major (spilled path) | {best_image:.2} | {:.3e} | 1.00 |\n\
         | Gaussian-block-major (default) | {best_block:.2} | {:.3e} | {:.2} |\n\n\
         write (f16, {:.0} MiB): rows {push_s:.2} s, file assembly + fsync {finish_s:.2} s\n",
        a.gaussians,
        r.ids.len(),
        a.images,
        entries,
        a.dim,
        r.chunks,
        a.repeats,
        entries as f64 / best_image,
        entries as f64 / best_block,
        best_image / best_block,
        bytes as f64 / (1 << 20) as f64,
    ))
}
