//! The mixture rows of `slag-edge bench`: a synthetic mixture store (a codebook of `A` atoms in
//! the benchmark's clusters, `S` slots per Gaussian) against f16 and int8 stores holding the
//! same Gaussians (each mixture row reconstructed, then stored densely), timed in one run.

use std::collections::HashSet;
use std::time::Instant;

use rayon::prelude::*;
use slag_common::shards::Dtype;
use slag_common::table::Table;
use slag_edge::scan::synthetic::synthetic_mixture;
use slag_edge::scan::{Combiner, ScanRequest, VectorStore, lerf_relevancy, scan};

use super::{dtype_name, median};

/// Rows copied per block.
const BLOCK: usize = 1 << 16;

/// The same rows as `mix` (reconstructed, unit norm) in a dense store of `dtype`.
fn dense_copy(mix: &VectorStore, dtype: Dtype) -> anyhow::Result<VectorStore> {
    let (n, d) = (mix.len(), mix.dim());
    let mut store = VectorStore::new(d, dtype)?;
    store.reserve(n)?;
    for start in (0..n).step_by(BLOCK) {
        let end = (start + BLOCK).min(n);
        let flat: Vec<f32> = (start..end)
            .into_par_iter()
            .flat_map_iter(|i| mix.row_f32(i).unwrap_or_default())
            .collect();
        store.push_f32_rows(&mix.ids()[start..end], &mix.means()[start..end], &flat)?;
    }
    Ok(store)
}

/// Median times (ms) of top-k, threshold (with its median hit count) and LERF (Q = 5) scans of
/// `store`, and the top-k row sets.
struct Timed {
    topk: f64,
    thr: f64,
    thr_hits: usize,
    lerf: f64,
    sets: Vec<HashSet<usize>>,
}

fn time_store(
    store: &VectorStore,
    qvecs: &[Vec<f32>],
    negs: &[Vec<f32>],
    top_k: usize,
    threshold: f32,
) -> anyhow::Result<Timed> {
    let (mut topk, mut thr, mut lerf, mut hits, mut sets) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let lerf_fn: Combiner<'_> = &lerf_relevancy;
    for q in qvecs {
        let qs = [q.as_slice()];
        let t = Instant::now();
        let h = scan(store, &ScanRequest::top_k(&qs, top_k))?;
        topk.push(t.elapsed().as_secs_f64() * 1e3);
        sets.push(h.iter().map(|x| x.row).collect());
        let t = Instant::now();
        hits.push(scan(store, &ScanRequest::threshold(&qs, threshold))?.len() as f64);
        thr.push(t.elapsed().as_secs_f64() * 1e3);
        let q5: [&[f32]; 5] = [q, &negs[0], &negs[1], &negs[2], &negs[3]];
        let t = Instant::now();
        std::hint::black_box(scan(
            store,
            &ScanRequest {
                combine: Some(lerf_fn),
                ..ScanRequest::top_k(&q5, top_k)
            },
        )?);
        lerf.push(t.elapsed().as_secs_f64() * 1e3);
    }
    Ok(Timed {
        topk: median(topk),
        thr: median(thr),
        thr_hits: median(hits) as usize,
        lerf: median(lerf),
        sets,
    })
}

/// Settings of [`mixture_table`].
pub(super) struct MixtureBench<'a> {
    pub sizes: &'a [usize],
    pub dim: usize,
    pub atoms: usize,
    pub slots: usize,
    pub dense: &'a [Dtype],
    pub top_k: usize,
    pub threshold: f32,
    pub centres: &'a [f32],
    pub clusters: usize,
    pub seed: u64,
    pub qvecs: &'a [Vec<f32>],
    pub negs: &'a [Vec<f32>],
    /// Memory guard, bytes.
    pub limit: f64,
}

/// The Markdown table of the mixture rows: per size, the mixture store and f16 / int8 copies of
/// its Gaussians, with bytes per Gaussian on disk (shard rows + the codebook file amortised) and
/// in memory, median scan times, ratios to the mixture's times and top-k IoU against the
/// mixture's (exact) answer.
pub(super) fn mixture_table(b: &MixtureBench<'_>) -> anyhow::Result<String> {
    let mut t = Table::with_header(
        "N | form | disk B/Gaussian | memory B/Gaussian | gen s | top-k ms | ÷ mix | thr ms (hits) | ÷ mix | LERF Q=5 ms | top-k IoU vs mixture",
    );
    for &n in b.sizes {
        for row in size_rows(b, n)? {
            t.row(row);
        }
    }
    Ok(format!(
        "Mixture rows (codebook of {} atoms × D = {}, S = {} slots, {} clusters; f16 / int8 = the \
         same Gaussians reconstructed and stored densely; disk B/Gaussian = shard row + codebook \
         file / N, memory = scan store + codebook / N; ÷ mix = time / the mixture's time; IoU = \
         top-k rows against the mixture's):\n\n{t}",
        b.atoms, b.dim, b.slots, b.clusters
    ))
}

/// The table rows of size `n`: the mixture, then each dense copy that fits the memory guard (one
/// row saying so when the mixture itself does not fit).
fn size_rows(b: &MixtureBench<'_>, n: usize) -> anyhow::Result<Vec<Vec<String>>> {
    let (a, d, s) = (b.atoms as f64, b.dim as f64, b.slots as f64);
    let need = n as f64 * (16.0 + 8.0 * s) + a * d * 4.0;
    if need > b.limit {
        let mut row = vec![
            n.to_string(),
            "mixture".into(),
            "skipped: memory guard".into(),
        ];
        row.resize(11, String::new());
        return Ok(vec![row]);
    }
    anyhow::ensure!(
        b.clusters > 0 && b.atoms >= b.clusters * b.slots,
        "--mixture-atoms {} must be at least {} clusters × {} slots",
        b.atoms,
        b.clusters,
        b.slots
    );
    let t = Instant::now();
    let mix = synthetic_mixture(n, b.dim, b.atoms, b.slots, b.centres, b.clusters, b.seed)?;
    let gen_s = t.elapsed().as_secs_f64();
    let m = time_store(&mix, b.qvecs, b.negs, b.top_k, b.threshold)?;
    let nf = n.max(1) as f64;
    let mut rows = vec![vec![
        n.to_string(),
        format!("mixture S={}", b.slots),
        format!("{:.1}", 16.0 + 6.0 * s + a * d * 2.0 / nf),
        format!("{:.1}", mix.bytes_per_gaussian() as f64 + a * d * 4.0 / nf),
        format!("{gen_s:.1}"),
        format!("{:.2}", m.topk),
        "1".into(),
        format!("{:.2} ({})", m.thr, m.thr_hits),
        "1".into(),
        format!("{:.2}", m.lerf),
        "1".into(),
    ]];
    for &dtype in b.dense {
        let need = n as f64 * (dtype.bytes_per_vector(b.dim) + 16) as f64;
        if dtype == Dtype::F32 || need > b.limit {
            continue;
        }
        let t = Instant::now();
        let dense = dense_copy(&mix, dtype)?;
        let gen_s = t.elapsed().as_secs_f64();
        let r = time_store(&dense, b.qvecs, b.negs, b.top_k, b.threshold)?;
        let iou = r
            .sets
            .iter()
            .zip(&m.sets)
            .map(|(x, y)| {
                let i = x.intersection(y).count();
                i as f64 / (x.len() + y.len() - i).max(1) as f64
            })
            .sum::<f64>()
            / r.sets.len().max(1) as f64;
        let bpg = dense.bytes_per_gaussian();
        rows.push(vec![
            n.to_string(),
            dtype_name(dtype).into(),
            bpg.to_string(),
            bpg.to_string(),
            format!("{gen_s:.1}"),
            format!("{:.2}", r.topk),
            format!("{:.2}", r.topk / m.topk),
            format!("{:.2} ({})", r.thr, r.thr_hits),
            format!("{:.2}", r.thr / m.thr),
            format!("{:.2}", r.lerf),
            format!("{iou:.4}"),
        ]);
    }
    Ok(rows)
}
