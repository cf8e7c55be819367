//! The scan benchmark behind `slag-edge bench`: exact scan vs memory-bandwidth floor vs the naive
//! baseline, per store size and dtype, plus an HNSW table (`hnsw_table.rs`: every
//! approximate-index backend over a sweep of search beams), a mixture table (`mixture_table.rs`),
//! an objects table (`objects_table.rs`) and, with `--qdrant`, Qdrant Edge side by side
//! (`qdrant_cmp.rs`). All ratios come from one run on one machine.
//!
//! Part of the `slag-edge` binary, not of the `slag_edge` library: it measures the library's
//! scans from outside, through their public API.

use std::collections::HashSet;
use std::time::Instant;

use rayon::prelude::*;
use slag_common::shards::{Dtype, StoredVectors};
use slag_common::table::Table;

use slag_edge::scan::hnsw::HnswBackend;
use slag_edge::scan::kernels::{self, SimdLevel};
use slag_edge::scan::synthetic::{normal, random_centres};
use slag_edge::scan::{
    CHUNK_ROWS, Combiner, ScanRequest, VectorStore, lerf_relevancy, naive_scan_f32, scan,
};

mod hnsw_table;
mod mixture_table;
mod objects_table;
#[cfg(feature = "qdrant-edge")]
mod qdrant_cmp;

/// Clusters of the synthetic store (directions; each query targets one of them).
const CLUSTERS: usize = 64;

/// Options of the scan benchmark (`slag-edge bench`).
#[derive(clap::Args, Debug, Clone)]
pub struct BenchArgs {
    /// Store sizes in Gaussians (suffix K = 1e3, M = 1e6), comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "1M,2M,4M,8M", value_parser = parse_size)]
    pub sizes: Vec<usize>,
    /// Stored vector types to measure (f32, f16, i8), comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "f32,f16,i8")]
    pub dtypes: Vec<Dtype>,
    /// Embedding width D.
    #[arg(long, default_value_t = 512)]
    pub dim: usize,
    /// k of the top-k queries the bench times (a workload size, not the answer's `--top-k`).
    #[arg(long = "k", value_name = "K", default_value_t = 1000)]
    pub top_k: usize,
    /// Cosine threshold of the threshold query (the paper's 0.28).
    #[arg(long, default_value_t = 0.28)]
    pub threshold: f32,
    /// Timed runs per measurement (the median is reported); each run uses a different query.
    #[arg(long, default_value_t = 5)]
    pub queries: usize,
    /// Rayon threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Skip any store (or index) that would need more than this many GB (1e9 bytes). Default:
    /// 75 % of MemAvailable from /proc/meminfo (8 GB when it cannot be read).
    #[arg(long)]
    pub max_memory_gb: Option<f64>,
    /// Seed of the synthetic store and queries.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Store size of the HNSW table (0 = no HNSW table). Build time grows ~N log N: on a 2-core
    /// machine instant-distance takes about two minutes for 100K × 512 and well over ten for 1M,
    /// so the default is 100K.
    #[arg(long, default_value = "100K", value_parser = parse_size)]
    pub hnsw_size: usize,
    /// HNSW ef_construction (both backends).
    #[arg(long, default_value_t = 100)]
    pub hnsw_ef_construction: usize,
    /// Approximate-index backends of the HNSW table (instant-distance, qdrant-edge),
    /// comma-separated; `--qdrant` adds qdrant-edge. qdrant-edge needs a binary built with
    /// `--features qdrant-edge`.
    #[arg(long, value_delimiter = ',', default_value = "instant-distance", value_parser = parse_backend)]
    pub hnsw_backends: Vec<HnswBackend>,
    /// Search beams (ef) of the HNSW table, comma-separated, each at least --top-k (default:
    /// --top-k). instant-distance is built once per ef (its beam is fixed at build time), Qdrant
    /// Edge once per --hnsw-m and searched with each.
    #[arg(long, value_delimiter = ',')]
    pub hnsw_ef: Vec<usize>,
    /// Qdrant Edge graph degrees (m, links per node; layer 0 keeps 2m), comma-separated.
    /// instant-distance's M is fixed at 32.
    #[arg(long, value_delimiter = ',', default_value = "16")]
    pub hnsw_m: Vec<usize>,
    /// Queries of the HNSW table (recall is their mean; the time their median).
    #[arg(long, default_value_t = 50)]
    pub hnsw_queries: usize,
    /// Skip the naive single-thread baseline for stores above this size (it is slow).
    #[arg(long, default_value = "8M", value_parser = parse_size)]
    pub naive_max: usize,
    /// Also run Qdrant Edge 0.9.0 on the same rows and queries (exact f32 / f16, scalar int8 with
    /// and without rescoring, HNSW), alternating with slag's scans. Needs a binary built with
    /// `--features qdrant-edge` (Rust >= 1.96); refused otherwise.
    #[arg(long)]
    pub qdrant: bool,
    /// Scratch folder for the Qdrant Edge shards (removed afterwards). Default: a folder in the
    /// system temp dir.
    #[arg(long)]
    pub qdrant_dir: Option<std::path::PathBuf>,
    /// Oversampling of Qdrant's int8 search with rescoring (it rescores `k × oversampling`
    /// candidates on the f32 originals).
    #[arg(long, default_value_t = 1.0)]
    pub qdrant_oversampling: f64,
    /// Codebook rows of the mixture table (a synthetic mixture store per size, against f16 and
    /// int8 copies of the same Gaussians); 0 = no mixture table.
    #[arg(long, default_value_t = 4000)]
    pub mixture_atoms: usize,
    /// Slots per Gaussian S of the mixture table (kept per Gaussian, as `encode --mixture-keep`).
    #[arg(
        long = "mixture-keep",
        alias = "mixture-slots",
        value_name = "S",
        default_value_t = 8
    )]
    pub mixture_slots: usize,
    /// Matching Gaussians of the objects table (grouping a query's matches into objects);
    /// 0 = no objects table.
    #[arg(long, default_value = "100K", value_parser = parse_size)]
    pub objects_matches: usize,
}

impl Default for BenchArgs {
    fn default() -> Self {
        BenchArgs {
            sizes: vec![1_000_000, 2_000_000, 4_000_000, 8_000_000],
            dtypes: vec![Dtype::F32, Dtype::F16, Dtype::I8],
            dim: 512,
            top_k: 1000,
            threshold: 0.28,
            queries: 5,
            threads: None,
            max_memory_gb: None,
            seed: 1,
            hnsw_size: 100_000,
            hnsw_ef_construction: 100,
            hnsw_backends: vec![HnswBackend::InstantDistance],
            hnsw_ef: Vec::new(),
            hnsw_m: vec![16],
            hnsw_queries: 50,
            naive_max: 8_000_000,
            qdrant: false,
            qdrant_dir: None,
            qdrant_oversampling: 1.0,
            mixture_atoms: 4000,
            mixture_slots: 8,
            objects_matches: 100_000,
        }
    }
}

/// Parses `1M`, `500K`, `2000000` into a count.
fn parse_size(s: &str) -> Result<usize, String> {
    let t = s.trim();
    let (num, mul) = match t.chars().last() {
        Some('k' | 'K') => (&t[..t.len() - 1], 1_000.0),
        Some('m' | 'M') => (&t[..t.len() - 1], 1_000_000.0),
        _ => (t, 1.0),
    };
    let v: f64 = num
        .parse()
        .map_err(|_| format!("size {s:?} is not a number like 1M, 500K or 2000000"))?;
    if !(v >= 0.0 && v.is_finite()) {
        return Err(format!("size {s:?} must be a non-negative number"));
    }
    Ok((v * mul).round() as usize)
}

/// Parses an approximate-index backend name ([`HnswBackend::from_name`]).
fn parse_backend(s: &str) -> Result<HnswBackend, String> {
    HnswBackend::from_name(s).map_err(|e| e.to_string())
}

fn mem_available_bytes() -> Option<f64> {
    slag_common::util::mem_available_bytes().map(|b| b as f64)
}

fn cpu_name() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|t| {
            t.lines()
                .find(|l| l.starts_with("model name") || l.starts_with("Model"))
                .and_then(|l| l.split(':').nth(1))
                .map(|s| s.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into())
}

fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn fmt_size(n: usize) -> String {
    if n >= 1_000_000 && n.is_multiple_of(1_000_000) {
        format!("{}M", n / 1_000_000)
    } else if n >= 1000 && n.is_multiple_of(1000) {
        format!("{}K", n / 1000)
    } else {
        n.to_string()
    }
}

fn dtype_name(d: Dtype) -> &'static str {
    match d {
        Dtype::F32 => "f32",
        Dtype::F16 => "f16",
        Dtype::I8 => "int8",
    }
}

/// Wrapping sum of the bytes viewed as `u64` words (4 independent accumulators so the adds
/// vectorise): a plain read of every byte, the floor any scan of them must pay.
fn read_words(bytes: &[u8]) -> u64 {
    let (head, words, tail) = bytemuck::pod_align_to::<u8, u64>(bytes);
    let mut acc = [0u64; 4];
    for c in words.chunks_exact(4) {
        for l in 0..4 {
            acc[l] = acc[l].wrapping_add(c[l]);
        }
    }
    let rest = words.chunks_exact(4).remainder();
    let edge = head.iter().chain(tail).map(|&b| b as u64).sum::<u64>();
    acc.iter().chain(rest).fold(edge, |a, &b| a.wrapping_add(b))
}

/// The stored vector bytes of `store` (and int8 scales) as byte slices.
fn vector_byte_slices(store: &VectorStore) -> Vec<&[u8]> {
    match store.vectors() {
        StoredVectors::F32(v) => vec![bytemuck::cast_slice(v)],
        StoredVectors::F16(v) => vec![bytemuck::cast_slice(v)],
        StoredVectors::I8 { q, scales } => {
            vec![bytemuck::cast_slice(q), bytemuck::cast_slice(scales)]
        }
    }
}

/// Best-of-3 time (ms) of a parallel read of every vector byte, split in the scan's chunks.
fn floor_ms(store: &VectorStore) -> f64 {
    let chunk = (CHUNK_ROWS * store.dtype().bytes_per_vector(store.dim())).max(4096);
    let slices = vector_byte_slices(store);
    let mut best = f64::INFINITY;
    let mut sink = 0u64;
    for _ in 0..3 {
        let t = Instant::now();
        for s in &slices {
            sink = sink.wrapping_add(
                s.par_chunks(chunk)
                    .map(read_words)
                    .reduce(|| 0, u64::wrapping_add),
            );
        }
        best = best.min(t.elapsed().as_secs_f64() * 1e3);
    }
    std::hint::black_box(sink);
    best
}

/// Unit query `i`: cluster centre `i mod CLUSTERS` blended with noise (cos ≈ 0.9 to the centre),
/// so the 0.28 threshold keeps roughly one cluster.
fn make_query(centres: &[f32], dim: usize, i: usize, seed: u64) -> Vec<f32> {
    let c = i % CLUSTERS;
    let mut s = seed ^ 0x0005_1EE7 ^ (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    let mut q: Vec<f32> = centres[c * dim..(c + 1) * dim]
        .iter()
        .map(|&x| x + 0.5 * normal(&mut s) / (dim as f32).sqrt())
        .collect();
    let n = q.iter().map(|x| x * x).sum::<f32>().sqrt();
    q.iter_mut().for_each(|x| *x /= n);
    q
}

/// Random unit "canonical phrase" embeddings for the LERF rows.
fn negatives(dim: usize, seed: u64) -> Vec<Vec<f32>> {
    let mut s = seed ^ 0xBAD0;
    (0..4)
        .map(|_| {
            let mut v: Vec<f32> = (0..dim).map(|_| normal(&mut s)).collect();
            let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
            v.iter_mut().for_each(|x| *x /= n);
            v
        })
        .collect()
}

struct Row {
    size: usize,
    dtype: Dtype,
    bpg: usize,
    gb: f64,
    gen_s: f64,
    floor: f64,
    topk: f64,
    thr: f64,
    thr_hits: usize,
    lerf: f64,
    naive: Option<f64>,
    /// Mean IoU of this store's top-k row sets with the f32 store's (same synthetic rows).
    agree_f32: Option<f64>,
}

/// |a ∩ b| / |a ∪ b| of two row sets (1 for two empty sets).
fn iou(a: &HashSet<usize>, b: &HashSet<usize>) -> f64 {
    let inter = a.intersection(b).count();
    let union = a.len() + b.len() - inter;
    if union == 0 {
        1.0
    } else {
        inter as f64 / union as f64
    }
}

/// Runs the benchmark (see [`BenchArgs`]) and returns a Markdown report: machine, settings, one
/// table row per (size, dtype) and an HNSW table. Sizes or dtypes that would exceed the memory
/// guard are listed as skipped, not attempted.
///
/// Columns: bytes/Gaussian (vectors + id + mean); floor = best-of-3 parallel read of the vector
/// bytes; top-k / threshold / LERF = median wall time of `queries` exact scans (Q = 1, 1, 5);
/// GB/s = vector bytes / time; ÷floor = scan time / floor time (1.0 = at the bandwidth floor);
/// naive = single-thread [`naive_scan_f32`] on the f32 store of the same size (median of up to
/// 3 runs; its top-k must equal the scan's, else the benchmark fails); speed-up = naive / top-k;
/// top-k IoU vs f32 = mean over queries of the IoU between this dtype's top-k rows and the f32
/// store's (same synthetic rows, quantised), `n/a` when f32 was not run at that size.
///
/// Errors: invalid settings (dim 0, no sizes, bad thread count) or a scan error.
pub fn run_bench(args: &BenchArgs) -> anyhow::Result<String> {
    anyhow::ensure!(args.dim > 0, "--dim must be at least 1");
    anyhow::ensure!(args.queries > 0, "--queries must be at least 1");
    anyhow::ensure!(!args.sizes.is_empty(), "--sizes needs at least one size");
    anyhow::ensure!(
        args.threshold.is_finite(),
        "--threshold must be a finite cosine"
    );
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(args.threads.unwrap_or(0))
        .build()?;
    anyhow::ensure!(
        !args.qdrant || cfg!(feature = "qdrant-edge"),
        "--qdrant needs slag-edge built with `--features qdrant-edge` (Rust >= 1.96): \
         cargo build --release -p slag-edge --features qdrant-edge"
    );
    anyhow::ensure!(
        args.qdrant_oversampling >= 1.0 && args.qdrant_oversampling.is_finite(),
        "--qdrant-oversampling must be a finite number >= 1"
    );
    if args.hnsw_size > 0 {
        for b in hnsw_table::backends(args) {
            anyhow::ensure!(
                b.available(),
                "--hnsw-backends {b} needs slag-edge built with `--features qdrant-edge` \
                 (Rust >= 1.96): cargo build --release -p slag-edge --features qdrant-edge"
            );
        }
        let efs = hnsw_table::efs(args);
        anyhow::ensure!(
            efs.first().is_some_and(|&e| e >= args.top_k.max(1)),
            "--hnsw-ef {efs:?}: every ef must be at least --top-k {} (an HNSW search returns \
             at most ef rows)",
            args.top_k
        );
        anyhow::ensure!(
            args.hnsw_m.iter().all(|&m| m >= 2) && !args.hnsw_m.is_empty(),
            "--hnsw-m: give one or more graph degrees, each at least 2"
        );
        anyhow::ensure!(
            args.hnsw_ef_construction >= 1,
            "--hnsw-ef-construction must be at least 1"
        );
    }
    pool.install(|| run_inner(args))
}

/// What every table of one run shares: the memory guard, the synthetic clusters and queries,
/// and the dtypes in measuring order.
struct Workload {
    /// Memory guard, bytes.
    limit: f64,
    /// Cluster centres of the synthetic stores (`CLUSTERS × dim`).
    centres: Vec<f32>,
    /// The timed unit queries (`--queries` of them).
    qvecs: Vec<Vec<f32>>,
    /// The LERF negatives.
    negs: Vec<Vec<f32>>,
    /// `--dtypes`, f32 first (the naive baseline runs on it), each once.
    dtypes: Vec<Dtype>,
}

impl Workload {
    fn new(args: &BenchArgs) -> Self {
        let dim = args.dim;
        let limit = args
            .max_memory_gb
            .map(|g| g * 1e9)
            .unwrap_or_else(|| mem_available_bytes().map_or(8e9, |m| 0.75 * m));
        let centres = random_centres(dim, CLUSTERS, args.seed);
        let qvecs: Vec<Vec<f32>> = (0..args.queries)
            .map(|i| make_query(&centres, dim, i * 7 + 1, args.seed))
            .collect();
        let mut dtypes = args.dtypes.clone();
        dtypes.sort_by_key(|d| d.code());
        dtypes.dedup();
        Workload {
            limit,
            centres,
            qvecs,
            negs: negatives(dim, args.seed),
            dtypes,
        }
    }
}

fn run_inner(args: &BenchArgs) -> anyhow::Result<String> {
    let w = Workload::new(args);
    let scans = scan_rows(args, &w)?;
    let mut out = settings_text(args, w.limit);
    out.push_str(&scan_table(&scans.rows).markdown());
    if !scans.skipped.is_empty() {
        out.push_str("\nSkipped (memory guard): ");
        out.push_str(&scans.skipped.join("; "));
        out.push('\n');
    }
    if !scans.qdrant.is_empty() {
        out.push('\n');
        out.push_str(&qdrant_table(args, &scans.qdrant));
    }
    if args.mixture_atoms > 0 {
        out.push('\n');
        out.push_str(&mixture_table::mixture_table(
            &mixture_table::MixtureBench {
                sizes: &args.sizes,
                dim: args.dim,
                atoms: args.mixture_atoms,
                slots: args.mixture_slots,
                dense: &w.dtypes,
                top_k: args.top_k,
                threshold: args.threshold,
                centres: &w.centres,
                clusters: CLUSTERS,
                seed: args.seed,
                qvecs: &w.qvecs,
                negs: &w.negs,
                limit: w.limit,
            },
        )?);
    }
    out.push('\n');
    out.push_str(&kernel_table(args, &w.dtypes)?);
    if args.hnsw_size > 0 {
        out.push('\n');
        out.push_str(&hnsw_table::table(args, w.limit)?);
    }
    if args.objects_matches > 0 {
        out.push('\n');
        out.push_str(&objects_table::table(args)?);
    }
    Ok(out)
}

/// The measured scan rows of every (size, dtype), the Qdrant Edge rows beside them (`--qdrant`)
/// and the (size, dtype) pairs the memory guard skipped.
struct ScanRows {
    rows: Vec<Row>,
    qdrant: Vec<QRow>,
    skipped: Vec<String>,
}

/// Measures every (size, dtype) of `args` that fits the memory guard (f32 first at each size:
/// its top-k sets are the others' reference and its store runs the naive baseline).
fn scan_rows(args: &BenchArgs, w: &Workload) -> anyhow::Result<ScanRows> {
    let mut out = ScanRows {
        rows: Vec::new(),
        qdrant: Vec::new(),
        skipped: Vec::new(),
    };
    for &size in &args.sizes {
        let mut naive: Option<f64> = None;
        let mut f32_sets: Option<Vec<HashSet<usize>>> = None;
        for &dtype in &w.dtypes {
            let need = size as f64 * (dtype.bytes_per_vector(args.dim) + 16) as f64;
            if need > w.limit {
                out.skipped.push(format!(
                    "{} {}: needs {:.1} GB > limit {:.1} GB",
                    fmt_size(size),
                    dtype_name(dtype),
                    need / 1e9,
                    w.limit / 1e9
                ));
                continue;
            }
            tracing::info!("bench: generating {} {}", fmt_size(size), dtype_name(dtype));
            let t = Instant::now();
            let store = VectorStore::synthetic(size, args.dim, dtype, CLUSTERS, args.seed)?;
            let gen_s = t.elapsed().as_secs_f64();
            let floor = floor_ms(&store);
            let timed = time_scans(args, w, &store)?;
            let sets = top_k_sets(args, &w.qvecs, &store)?;
            if dtype == Dtype::F32 && size <= args.naive_max {
                naive = Some(naive_ms(args, &w.qvecs, &store, &sets)?);
            }
            let agree_f32 = if dtype == Dtype::F32 {
                Some(1.0)
            } else {
                mean_iou(&sets, f32_sets.as_deref().unwrap_or(&[]))
            };
            if dtype == Dtype::F32 {
                f32_sets = Some(sets);
            }
            // Without the feature `run_bench` has refused `--qdrant` already.
            #[cfg(feature = "qdrant-edge")]
            if args.qdrant {
                let exact = f32_sets.as_deref().unwrap_or(&[]);
                out.qdrant.extend(qdrant::exact_rows(
                    args, size, dtype, &store, &w.qvecs, exact,
                )?);
            }
            out.rows.push(Row {
                size,
                dtype,
                bpg: store.bytes_per_gaussian(),
                gb: store.vector_bytes() as f64 / 1e9,
                gen_s,
                floor,
                topk: timed.topk,
                thr: timed.thr,
                thr_hits: timed.thr_hits,
                lerf: timed.lerf,
                naive,
                agree_f32,
            });
        }
    }
    Ok(out)
}

/// Median times (ms) of one store's top-k, threshold and LERF scans, and the threshold's hits.
struct ScanTimes {
    topk: f64,
    thr: f64,
    thr_hits: usize,
    lerf: f64,
}

/// Times the top-k, threshold and LERF scans of `store`, each over every query of `w`.
fn time_scans(args: &BenchArgs, w: &Workload, store: &VectorStore) -> anyhow::Result<ScanTimes> {
    let time_q = |f: &dyn Fn(&[f32]) -> anyhow::Result<usize>| -> anyhow::Result<(f64, usize)> {
        let mut ts = Vec::new();
        let mut hits = Vec::new();
        for q in &w.qvecs {
            let t = Instant::now();
            hits.push(f(q)?);
            ts.push(t.elapsed().as_secs_f64() * 1e3);
        }
        Ok((
            median(ts),
            median(hits.iter().map(|&h| h as f64).collect()) as usize,
        ))
    };
    let (topk, _) = time_q(&|q| {
        let qs = [q];
        Ok(scan(store, &ScanRequest::top_k(&qs, args.top_k))?.len())
    })?;
    let (thr, thr_hits) = time_q(&|q| {
        let qs = [q];
        Ok(scan(store, &ScanRequest::threshold(&qs, args.threshold))?.len())
    })?;
    let lerf_fn: Combiner<'_> = &lerf_relevancy;
    let negs = &w.negs;
    let (lerf, _) = time_q(&|q| {
        let qs: [&[f32]; 5] = [q, &negs[0], &negs[1], &negs[2], &negs[3]];
        let req = ScanRequest {
            queries: &qs,
            top_k: Some(args.top_k),
            threshold: None,
            bbox: None,
            combine: Some(lerf_fn),
        };
        Ok(scan(store, &req)?.len())
    })?;
    Ok(ScanTimes {
        topk,
        thr,
        thr_hits,
        lerf,
    })
}

/// The top-k row set of each query on `store` (untimed): correctness and quantisation agreement.
fn top_k_sets(
    args: &BenchArgs,
    qvecs: &[Vec<f32>],
    store: &VectorStore,
) -> anyhow::Result<Vec<HashSet<usize>>> {
    Ok(qvecs
        .iter()
        .map(|q| {
            let qs = [q.as_slice()];
            scan(store, &ScanRequest::top_k(&qs, args.top_k))
                .map(|h| h.iter().map(|x| x.row).collect())
        })
        .collect::<Result<_, _>>()?)
}

/// Median time (ms) of the single-thread naive scan over up to 3 queries; fails when its top-k
/// differs from the scan's (`sets`).
fn naive_ms(
    args: &BenchArgs,
    qvecs: &[Vec<f32>],
    store: &VectorStore,
    sets: &[HashSet<usize>],
) -> anyhow::Result<f64> {
    let runs = args.queries.min(3);
    let mut ts = Vec::new();
    for (i, q) in qvecs.iter().take(runs).enumerate() {
        let t = Instant::now();
        let hits = std::hint::black_box(naive_scan_f32(store, q, args.top_k)?);
        ts.push(t.elapsed().as_secs_f64() * 1e3);
        let naive_set = hits.iter().map(|h| h.row).collect();
        anyhow::ensure!(
            iou(&naive_set, &sets[i]) == 1.0,
            "the f32 scan and the naive scan disagree on query {i}'s top-{}",
            args.top_k
        );
    }
    Ok(median(ts))
}

/// The report's opening: machine, SIMD level and settings.
fn settings_text(args: &BenchArgs, limit: f64) -> String {
    format!(
        "Machine: {} ({}), {} rayon threads, MemAvailable {:.1} GB, memory guard {:.1} GB\n\n\
         SIMD level of the scans: {:?} (SLAG_SCAN_SIMD=baseline forces the portable loops).\n\n\
         Settings: D = {}, top-k = {}, threshold = {}, {} timed queries (median), seed {}, \
         {CLUSTERS}-cluster synthetic unit rows; LERF = 5 queries (prompt + 4 negatives) in one \
         pass, top-k of lerf_relevancy.\n\n",
        cpu_name(),
        std::env::consts::ARCH,
        rayon::current_num_threads(),
        mem_available_bytes().unwrap_or(f64::NAN) / 1e9,
        limit / 1e9,
        kernels::simd_level(),
        args.dim,
        args.top_k,
        args.threshold,
        args.queries,
        args.seed
    )
}

/// `x` to 4 decimals, `n/a` when absent.
fn opt4(x: Option<f64>) -> String {
    x.map_or_else(|| "n/a".to_string(), |v| format!("{v:.4}"))
}

/// The scan table: one row per measured (size, dtype) (columns: [`run_bench`]).
fn scan_table(rows: &[Row]) -> Table {
    let mut t = Table::with_header(
        "N | dtype | B/Gaussian | vectors GB | gen s | floor ms (GB/s) | top-k ms | GB/s | ÷floor | thr ms (hits) | LERF Q=5 ms | ÷floor | naive f32 ms (same N) | speed-up | top-k IoU vs f32",
    );
    for r in rows {
        let (naive_s, speed) = match r.naive {
            Some(x) => (format!("{x:.0}"), format!("{:.1}×", x / r.topk)),
            None => ("n/a".into(), "n/a".into()),
        };
        t.row([
            fmt_size(r.size),
            dtype_name(r.dtype).into(),
            r.bpg.to_string(),
            format!("{:.2}", r.gb),
            format!("{:.1}", r.gen_s),
            format!("{:.1} ({:.1})", r.floor, r.gb / (r.floor / 1e3)),
            format!("{:.1}", r.topk),
            format!("{:.1}", r.gb / (r.topk / 1e3)),
            format!("{:.2}", r.topk / r.floor),
            format!("{:.1} ({})", r.thr, r.thr_hits),
            format!("{:.1}", r.lerf),
            format!("{:.2}", r.lerf / r.floor),
            naive_s,
            speed,
            opt4(r.agree_f32),
        ]);
    }
    t
}

/// One side-by-side measurement of slag and Qdrant Edge on the same rows and queries.
struct QRow {
    size: usize,
    /// slag's stored type of this row.
    dtype: Dtype,
    /// Qdrant Edge's configuration.
    label: String,
    /// Qdrant Edge upsert + optimise seconds, and its segment count.
    build_s: f64,
    segments: usize,
    /// Medians over the queries, answered alternately.
    slag_ms: f64,
    qdrant_ms: f64,
    /// Mean top-k IoU against slag's exact f32 answer on the same rows (`None` without f32).
    slag_iou: Option<f64>,
    qdrant_iou: Option<f64>,
}

fn qdrant_table(args: &BenchArgs, rows: &[QRow]) -> String {
    let mut t = Table::with_header(
        "N | slag dtype | slag top-k ms | Qdrant Edge | Qdrant ms | Qdrant ÷ slag | slag IoU | Qdrant IoU | Qdrant build s (segments)",
    );
    for r in rows {
        t.row([
            fmt_size(r.size),
            dtype_name(r.dtype).into(),
            format!("{:.1}", r.slag_ms),
            r.label.clone(),
            format!("{:.1}", r.qdrant_ms),
            format!("{:.2}×", r.qdrant_ms / r.slag_ms),
            opt4(r.slag_iou),
            opt4(r.qdrant_iou),
            format!("{:.1} ({})", r.build_s, r.segments),
        ]);
    }
    format!(
        "Qdrant Edge 0.9.0 side by side (same rows, same {} queries, top-{}, answered \
         alternately; Dot distance on unit rows; Qdrant's search pool and slag's rayon pool \
         both {} threads; IoU = mean top-k IoU against slag's exact f32 answer):\n\n{t}",
        args.queries,
        args.top_k,
        rayon::current_num_threads()
    )
}

/// Mean IoU of `sets[i]` with `exact[i]` (`None` when `exact` is empty).
fn mean_iou(sets: &[HashSet<usize>], exact: &[HashSet<usize>]) -> Option<f64> {
    (!exact.is_empty()).then(|| {
        sets.iter().zip(exact).map(|(a, b)| iou(a, b)).sum::<f64>() / sets.len().max(1) as f64
    })
}

#[cfg(feature = "qdrant-edge")]
mod qdrant {
    //! The Qdrant Edge rows of the report (see `super::qdrant_cmp`).
    use std::collections::HashSet;
    use std::time::Instant;

    use slag_common::shards::Dtype;

    use slag_edge::scan::{ScanRequest, VectorStore, scan};

    use super::qdrant_cmp::{self, Kind};
    use super::{BenchArgs, CLUSTERS, QRow, mean_iou, median};

    fn base(args: &BenchArgs) -> std::path::PathBuf {
        args.qdrant_dir.clone().unwrap_or_else(|| {
            std::env::temp_dir().join(format!("slag-qdrant-bench-{}", std::process::id()))
        })
    }

    /// Builds Qdrant Edge `kind` over `qrows` (two segments: the thread count of the bench).
    fn build(
        args: &BenchArgs,
        size: usize,
        qrows: &VectorStore,
        kind: Kind,
    ) -> anyhow::Result<qdrant_cmp::Shard> {
        let threads = rayon::current_num_threads();
        let label = kind.label(args.qdrant_oversampling);
        tracing::info!("bench: building {label} over {size} rows");
        qdrant_cmp::build(
            &base(args),
            &format!("exact-{size}"),
            qrows,
            kind,
            threads.max(1),
            threads,
            args.qdrant_oversampling,
        )
    }

    /// slag's exact top-k on `store` and Qdrant Edge's search on `shard`, alternately.
    #[allow(clippy::too_many_arguments)]
    fn side_by_side(
        args: &BenchArgs,
        size: usize,
        dtype: Dtype,
        store: &VectorStore,
        shard: &qdrant_cmp::Shard,
        label: String,
        qvecs: &[Vec<f32>],
        exact: &[HashSet<usize>],
    ) -> anyhow::Result<QRow> {
        let k = args.top_k;
        // Warm-up (untimed) on both sides.
        let q0 = [qvecs[0].as_slice()];
        scan(store, &ScanRequest::top_k(&q0, k))?;
        shard.search(&qvecs[0], k)?;
        let (mut ts, mut tq, mut ss, mut sq) = (vec![], vec![], vec![], vec![]);
        for q in qvecs {
            let qs = [q.as_slice()];
            let t = Instant::now();
            let a = scan(store, &ScanRequest::top_k(&qs, k))?;
            ts.push(t.elapsed().as_secs_f64() * 1e3);
            let t = Instant::now();
            let b = shard.search(q, k)?;
            tq.push(t.elapsed().as_secs_f64() * 1e3);
            ss.push(a.iter().map(|h| h.row).collect::<HashSet<usize>>());
            sq.push(b.into_iter().collect::<HashSet<usize>>());
        }
        Ok(QRow {
            size,
            dtype,
            label,
            build_s: shard.build_s,
            segments: shard.segments(),
            slag_ms: median(ts),
            qdrant_ms: median(tq),
            slag_iou: mean_iou(&ss, exact),
            qdrant_iou: mean_iou(&sq, exact),
        })
    }

    /// The Qdrant Edge rows for slag's `dtype` store of `size` rows: f32 → exact f32, f16 →
    /// exact f16 (the same halves), int8 → scalar int8 with and without rescoring (one shard)
    /// over the f32 rows the int8 store was quantised from.
    pub(super) fn exact_rows(
        args: &BenchArgs,
        size: usize,
        dtype: Dtype,
        store: &VectorStore,
        qvecs: &[Vec<f32>],
        exact: &[HashSet<usize>],
    ) -> anyhow::Result<Vec<QRow>> {
        let o = args.qdrant_oversampling;
        match dtype {
            Dtype::F32 | Dtype::F16 => {
                let kind = if dtype == Dtype::F32 {
                    Kind::F32
                } else {
                    Kind::F16
                };
                let shard = build(args, size, store, kind)?;
                let row = side_by_side(
                    args,
                    size,
                    dtype,
                    store,
                    &shard,
                    kind.label(o),
                    qvecs,
                    exact,
                )?;
                Ok(vec![row])
            }
            Dtype::I8 => {
                let f32_rows =
                    VectorStore::synthetic(size, store.dim(), Dtype::F32, CLUSTERS, args.seed)?;
                let mut shard = build(args, size, &f32_rows, Kind::Int8 { rescore: true })?;
                drop(f32_rows);
                let mut out = Vec::new();
                for rescore in [true, false] {
                    shard.set_rescore(rescore, o);
                    let label = Kind::Int8 { rescore }.label(o);
                    out.push(side_by_side(
                        args, size, dtype, store, &shard, label, qvecs, exact,
                    )?);
                }
                Ok(out)
            }
        }
    }
}

/// Time (s) of one single-thread pass of the chunk kernel over `store` at `level` (`out` is the
/// `[N][Q]` output, reused).
fn kernel_pass<const Q: usize>(
    store: &VectorStore,
    qs: &kernels::Queries<'_, Q>,
    level: SimdLevel,
    out: &mut Vec<[f32; Q]>,
) -> f64 {
    out.resize(store.len(), [0.0; Q]);
    let t = Instant::now();
    let span = kernels::RowSpan {
        d: store.dim(),
        start: 0,
        end: store.len(),
        keep: None,
    };
    kernels::scan_chunk_at::<Q>(level, store.vectors(), span, qs, out);
    let e = t.elapsed().as_secs_f64();
    std::hint::black_box(&out);
    e
}

/// Single-thread kernel throughput on a cache-resident block (≈1 MiB of f32 rows), every
/// dtype × Q ∈ {1, 5} × available [`SimdLevel`]: the compute ceiling, independent of DRAM.
fn kernel_table(args: &BenchArgs, dtypes: &[Dtype]) -> anyhow::Result<String> {
    let dim = args.dim;
    let n = ((1usize << 20) / (4 * dim)).max(64);
    let levels = SimdLevel::available_levels();
    let centres = random_centres(dim, CLUSTERS, args.seed);
    let qv: Vec<Vec<f32>> = (0..5)
        .map(|i| make_query(&centres, dim, i, args.seed))
        .collect();
    let q1 = kernels::Queries::new([qv[0].as_slice()]);
    let q5 = kernels::Queries::new([&qv[0], &qv[1], &qv[2], &qv[3], &qv[4]].map(|v| v.as_slice()));
    let mut t = Table::new(["dtype", "Q", "SIMD", "ns/row", "row GB/s"]);
    for &dtype in dtypes {
        let store = VectorStore::synthetic(n, dim, dtype, CLUSTERS, args.seed)?;
        let bytes = store.vector_bytes() as f64;
        for q in [1usize, 5] {
            for &level in &levels {
                let mut best = f64::INFINITY;
                let (mut o1, mut o5) = (Vec::new(), Vec::new());
                for _ in 0..5 {
                    let mut t = 0.0;
                    for _ in 0..20 {
                        t += match q {
                            1 => kernel_pass::<1>(&store, &q1, level, &mut o1),
                            _ => kernel_pass::<5>(&store, &q5, level, &mut o5),
                        };
                    }
                    best = best.min(t / 20.0);
                }
                t.row([
                    dtype_name(dtype).to_string(),
                    q.to_string(),
                    format!("{level:?}"),
                    format!("{:.1}", best * 1e9 / n as f64),
                    format!("{:.1}", bytes / best / 1e9),
                ]);
            }
        }
    }
    Ok(format!(
        "Kernel ceiling (1 thread, {n} rows × {dim} resident in cache, best of 5 × 20 passes):\n\n{t}"
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The benchmark from a test binary:
    /// `SLAG_BENCH_ARGS="--sizes 1M,2M" cargo test --workspace --bin slag-edge \
    ///   --config 'profile.dev.package.slag-edge.opt-level=3' -- --ignored bench_from_env --nocapture`.
    #[test]
    #[ignore = "benchmark: generates gigabyte stores; run explicitly"]
    fn bench_from_env() {
        use clap::Parser;
        #[derive(clap::Parser)]
        struct Cli {
            #[command(flatten)]
            args: BenchArgs,
        }
        let extra = std::env::var("SLAG_BENCH_ARGS").unwrap_or_default();
        let argv = std::iter::once("bench").chain(extra.split_whitespace());
        let cli = Cli::try_parse_from(argv).expect("SLAG_BENCH_ARGS");
        println!("{}", run_bench(&cli.args).expect("bench"));
    }

    #[test]
    fn sizes_parse_with_suffixes() {
        assert_eq!(parse_size("1M"), Ok(1_000_000));
        assert_eq!(parse_size("500K"), Ok(500_000));
        assert_eq!(parse_size("1.5M"), Ok(1_500_000));
        assert_eq!(parse_size("42"), Ok(42));
        assert!(parse_size("big").is_err());
        assert!(parse_size("-1M").is_err());
    }

    #[test]
    fn floor_read_sums_every_byte_once() {
        let bytes: Vec<u8> = (0..1001u32).map(|i| (i % 251) as u8).collect();
        // Word sum of the aligned middle + byte sum of the edges: compare against an
        // independent split at every offset.
        for off in 0..8 {
            let s = &bytes[off..];
            let (h, w, t) = bytemuck::pod_align_to::<u8, u64>(s);
            let want = w
                .iter()
                .fold(0u64, |a, &b| a.wrapping_add(b))
                .wrapping_add(h.iter().chain(t).map(|&b| b as u64).sum::<u64>());
            assert_eq!(read_words(s), want);
        }
    }

    #[test]
    fn tiny_bench_produces_a_table() {
        let args = BenchArgs {
            sizes: vec![3000],
            dim: 32,
            top_k: 10,
            queries: 2,
            threads: Some(2),
            hnsw_size: 500,
            hnsw_ef_construction: 20,
            hnsw_ef: vec![20, 10],
            hnsw_queries: 4,
            objects_matches: 40_000,
            ..BenchArgs::default()
        };
        let md = run_bench(&args).expect("bench");
        assert!(md.contains("| 3K | f32 |"), "{md}");
        // The objects table: the 20 boxes (the strays are suppressed).
        assert!(md.contains("| 40K | 20 | "), "{md}");
        assert!(md.contains("| 3K | f16 |"));
        assert!(md.contains("| 3K | int8 |"));
        // One instant-distance build per ef, sorted.
        let a = md
            .find("| instant-distance, M=32 | 20 | 10 |")
            .expect("ef 10 row");
        let b = md
            .find("| instant-distance, M=32 | 20 | 20 |")
            .expect("ef 20 row");
        assert!(a < b, "{md}");
        assert!(md.contains("| ≥ 0.99 |"), "{md}");
        // A beam below top-k is refused before anything runs.
        let e = run_bench(&BenchArgs {
            hnsw_ef: vec![5],
            ..args.clone()
        })
        .expect_err("ef < k");
        assert!(e.to_string().contains("--hnsw-ef"), "{e}");
        let skipped = run_bench(&BenchArgs {
            max_memory_gb: Some(1e-6),
            hnsw_size: 0,
            objects_matches: 0,
            ..args
        })
        .expect("bench");
        assert!(
            skipped.contains("Skipped (memory guard): 3K f32"),
            "{skipped}"
        );
    }

    #[test]
    fn tiny_bench_has_a_mixture_table_against_the_same_gaussians() {
        let md = run_bench(&BenchArgs {
            sizes: vec![3000],
            dim: 32,
            top_k: 10,
            queries: 2,
            threads: Some(2),
            hnsw_size: 0,
            mixture_atoms: 600,
            mixture_slots: 4,
            objects_matches: 0,
            ..BenchArgs::default()
        })
        .expect("bench");
        assert!(md.contains("| 3000 | mixture S=4 |"), "{md}");
        assert!(md.contains("| 3000 | f16 | 80 | 80 |"), "{md}");
        assert!(md.contains("| 3000 | int8 | 52 | 52 |"), "{md}");
        // f16 copies of the same Gaussians agree with the mixture's exact answer.
        let f16_row = md
            .lines()
            .find(|l| l.starts_with("| 3000 | f16 |"))
            .expect("row");
        let iou: f64 = f16_row
            .trim_end_matches(" |")
            .rsplit("| ")
            .next()
            .and_then(|v| v.trim().parse().ok())
            .expect("IoU");
        assert!(iou > 0.8, "{f16_row}");
    }
}
