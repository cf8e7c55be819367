//! The HNSW table of `slag-edge bench`: every approximate-index backend of
//! `slag_edge::scan::hnsw` on the same synthetic f32 store and the same queries, over a sweep of
//! search beams, so the backends can be read at equal recall.
//!
//! Per built index: build seconds, the index's bytes ([`ApproxIndex::memory_bytes`]) and the
//! growth of the process's resident set over the build (`VmRSS`, /proc/self/status; includes
//! allocator slack and, for Qdrant Edge, the pages of its scratch files it keeps in RAM). Per
//! (index, ef): the median query time and the mean and lowest recall@k against the exact f32 scan
//! of the same store. instant-distance fixes its beam at build time, so it is built once per ef;
//! Qdrant Edge is built once per `m` and searched with every ef. The queries are answered
//! round-robin over every (index, ef), so a change of machine load hits all of them alike.

use std::collections::HashSet;
use std::time::Instant;

use slag_common::shards::Dtype;
use slag_common::table::Table;

use slag_edge::scan::hnsw::{ApproxIndex, HnswBackend, HnswParams};
use slag_edge::scan::synthetic::random_centres;
use slag_edge::scan::{ScanRequest, VectorStore, scan};

use super::{BenchArgs, CLUSTERS, fmt_size, make_query, median};

/// Bytes per row a graph adds beside the row's f32 copy, for the memory guard (instant-distance
/// M = 32: 64 + upper-layer u32 links ≈ 260 B), with margin.
const GRAPH_BYTES_PER_ROW: f64 = 400.0;

/// f32 row copies Qdrant Edge's build grows the RSS by, for the memory guard (measured 3.2–3.4
/// at 100K × 512: docs/results/edge-hnsw.md), with margin.
const QDRANT_ROW_COPIES: f64 = 4.0;

/// One built index and what its build cost.
struct Built {
    label: String,
    index: ApproxIndex,
    build_s: f64,
    /// VmRSS after − before the build, bytes (`None` where /proc is unreadable).
    rss_delta: Option<i64>,
    /// Beams this index is searched with.
    efs: Vec<usize>,
}

/// Per (index, ef): query times (ms) and recalls.
#[derive(Default)]
struct Measured {
    ms: Vec<f64>,
    recall: Vec<f64>,
}

fn rss() -> Option<i64> {
    slag_common::util::rss_bytes().and_then(|b| i64::try_from(b).ok())
}

/// The backends of the table: `--hnsw-backends`, plus qdrant-edge with `--qdrant`.
pub(super) fn backends(args: &BenchArgs) -> Vec<HnswBackend> {
    let mut b = args.hnsw_backends.clone();
    if args.qdrant && !b.contains(&HnswBackend::QdrantEdge) {
        b.push(HnswBackend::QdrantEdge);
    }
    b.dedup();
    b
}

/// The beams of the sweep: `--hnsw-ef`, or top-k alone; sorted, deduplicated.
pub(super) fn efs(args: &BenchArgs) -> Vec<usize> {
    let mut e = if args.hnsw_ef.is_empty() {
        vec![args.top_k.max(1)]
    } else {
        args.hnsw_ef.clone()
    };
    e.sort_unstable();
    e.dedup();
    e
}

/// Builds `backend` with `params`, timing it and measuring the RSS growth.
fn build(
    store: &VectorStore,
    backend: HnswBackend,
    params: &HnswParams,
    label: String,
    efs: Vec<usize>,
) -> anyhow::Result<Built> {
    tracing::info!("bench: building {label} over {} rows", store.len());
    let before = rss();
    let t = Instant::now();
    let index = ApproxIndex::build(store, backend, params)?;
    let build_s = t.elapsed().as_secs_f64();
    let rss_delta = rss().zip(before).map(|(a, b)| a - b);
    Ok(Built {
        label,
        index,
        build_s,
        rss_delta,
        efs,
    })
}

/// ` (N segments)` for a Qdrant Edge index (its indexed segment plus its empty appendable one:
/// 2), empty for instant-distance.
fn segments_note(index: &ApproxIndex) -> String {
    match index {
        #[cfg(feature = "qdrant-edge")]
        ApproxIndex::QdrantEdge(q) => format!(" ({} segments)", q.segments()),
        _ => String::new(),
    }
}

/// Bytes the HNSW table needs (the f32 store and every index of the sweep) and the number of
/// indexes it builds, for the memory guard.
fn memory_need(args: &BenchArgs, efs: &[usize], backends: &[HnswBackend]) -> (usize, f64) {
    let n = args.hnsw_size;
    let row = n as f64 * (4 * args.dim) as f64;
    let (mut indexes, mut need) = (0usize, n as f64 * (4 * args.dim + 16) as f64);
    for b in backends {
        let (count, each) = match b {
            HnswBackend::InstantDistance => (efs.len(), row + n as f64 * GRAPH_BYTES_PER_ROW),
            HnswBackend::QdrantEdge => (args.hnsw_m.len(), QDRANT_ROW_COPIES * row),
        };
        indexes += count;
        need += count as f64 * each;
    }
    (indexes, need)
}

/// The HNSW section of the report (module doc), or a line saying why it was skipped.
pub(super) fn table(args: &BenchArgs, limit: f64) -> anyhow::Result<String> {
    let n = args.hnsw_size;
    let efs = efs(args);
    let backends = backends(args);
    let (indexes, need) = memory_need(args, &efs, &backends);
    if need > limit {
        return Ok(format!(
            "HNSW at {}: skipped, {indexes} indexes need {:.1} GB > limit {:.1} GB (fewer \
             --hnsw-ef / --hnsw-m values, or --hnsw-backends)\n",
            fmt_size(n),
            need / 1e9,
            limit / 1e9
        ));
    }
    let store = VectorStore::synthetic(n, args.dim, Dtype::F32, CLUSTERS, args.seed)?;
    let centres = random_centres(args.dim, CLUSTERS, args.seed);
    // Queries of their own (more than the scans' `--queries`: recall is a mean over them),
    // targeting the clusters round-robin.
    let qvecs: Vec<Vec<f32>> = (0..args.hnsw_queries.max(1))
        .map(|i| make_query(&centres, args.dim, i * 5 + 3, args.seed))
        .collect();
    let mut exact_ms = Vec::new();
    let mut exact: Vec<HashSet<usize>> = Vec::new();
    for q in &qvecs {
        let qs = [q.as_slice()];
        let t = Instant::now();
        let hits = scan(&store, &ScanRequest::top_k(&qs, args.top_k))?;
        exact_ms.push(t.elapsed().as_secs_f64() * 1e3);
        exact.push(hits.iter().map(|h| h.row).collect());
    }
    let mut built = build_all(args, &store, &backends, &efs)?;
    let measured = measure(args, &mut built, &qvecs, &exact)?;
    let rows = sweep_rows(&built, measured);
    let k = args.top_k;
    Ok(format!(
        "HNSW at equal recall ({} × {} f32 rows, {} queries answered round-robin over every \
         index and ef, top-{k}, recall@{k} against the exact f32 scan of the same rows; exact \
         scan median {:.2} ms on {} threads; index MB = the index's own bytes, RSS Δ = VmRSS \
         growth over the build):\n\n{}{}",
        fmt_size(n),
        args.dim,
        qvecs.len(),
        median(exact_ms),
        rayon::current_num_threads(),
        sweep_table(args, &rows),
        equal_recall(&rows, k)
    ))
}

/// Every index of the sweep: instant-distance once per ef, Qdrant Edge once per `m`.
fn build_all(
    args: &BenchArgs,
    store: &VectorStore,
    backends: &[HnswBackend],
    efs: &[usize],
) -> anyhow::Result<Vec<Built>> {
    let base = HnswParams {
        ef_construction: args.hnsw_ef_construction,
        seed: args.seed,
        scratch_dir: args.qdrant_dir.clone(),
        ..HnswParams::default()
    };
    let mut built = Vec::new();
    for &backend in backends {
        match backend {
            HnswBackend::InstantDistance => {
                for &ef in efs {
                    let p = HnswParams {
                        ef_search: ef,
                        ..base.clone()
                    };
                    let label = "instant-distance, M=32".into();
                    built.push(build(store, backend, &p, label, vec![ef])?);
                }
            }
            HnswBackend::QdrantEdge => {
                for &m in &args.hnsw_m {
                    let p = HnswParams {
                        m,
                        ef_search: efs.last().copied().unwrap_or(args.top_k),
                        ..base.clone()
                    };
                    let label = format!("qdrant-edge, m={m}");
                    let mut b = build(store, backend, &p, label, efs.to_vec())?;
                    b.label.push_str(&segments_note(&b.index));
                    built.push(b);
                }
            }
        }
    }
    Ok(built)
}

/// Warm-up (untimed), then every query round-robin over every (index, ef): per index, per ef,
/// the query times and recalls against `exact`.
fn measure(
    args: &BenchArgs,
    built: &mut [Built],
    qvecs: &[Vec<f32>],
    exact: &[HashSet<usize>],
) -> anyhow::Result<Vec<Vec<Measured>>> {
    let k = args.top_k;
    let mut measured: Vec<Vec<Measured>> = built
        .iter()
        .map(|b| b.efs.iter().map(|_| Measured::default()).collect())
        .collect();
    for b in built.iter_mut() {
        for &ef in &b.efs {
            b.index.set_ef_search(ef)?;
            b.index.query(&qvecs[0], k)?;
        }
    }
    for (q, want) in qvecs.iter().zip(exact) {
        for (b, m) in built.iter_mut().zip(&mut measured) {
            for (&ef, m) in b.efs.iter().zip(m.iter_mut()) {
                b.index.set_ef_search(ef)?;
                let t = Instant::now();
                let got = b.index.query(q, k)?;
                m.ms.push(t.elapsed().as_secs_f64() * 1e3);
                let found = got.iter().filter(|h| want.contains(&h.row)).count();
                m.recall.push(found as f64 / want.len().max(1) as f64);
            }
        }
    }
    Ok(measured)
}

/// One (index, ef) point of the sweep, summarised.
struct SweepRow {
    label: String,
    ef: usize,
    build_s: f64,
    /// The index's own bytes.
    bytes: usize,
    /// VmRSS growth over the build, bytes.
    rss_delta: Option<i64>,
    /// Median query time.
    ms: f64,
    /// Mean and lowest recall@k.
    mean: f64,
    min: f64,
}

/// The sweep's points, in build order and ef order within an index.
fn sweep_rows(built: &[Built], measured: Vec<Vec<Measured>>) -> Vec<SweepRow> {
    let mut rows = Vec::new();
    for (b, m) in built.iter().zip(measured) {
        for (&ef, m) in b.efs.iter().zip(m) {
            rows.push(SweepRow {
                label: b.label.clone(),
                ef,
                build_s: b.build_s,
                bytes: b.index.memory_bytes(),
                rss_delta: b.rss_delta,
                ms: median(m.ms),
                mean: m.recall.iter().sum::<f64>() / m.recall.len().max(1) as f64,
                min: m.recall.iter().copied().fold(f64::INFINITY, f64::min),
            });
        }
    }
    rows
}

/// The sweep table: one row per (index, ef).
fn sweep_table(args: &BenchArgs, rows: &[SweepRow]) -> Table {
    let k = args.top_k;
    let n = args.hnsw_size;
    let mut t = Table::new([
        "backend".to_string(),
        "ef_construction".into(),
        "ef_search".into(),
        "build s".into(),
        "index MB (B/row)".into(),
        "RSS Δ MB".into(),
        "query ms (median)".into(),
        format!("recall@{k} mean"),
        format!("recall@{k} min"),
    ]);
    for r in rows {
        t.row([
            r.label.clone(),
            args.hnsw_ef_construction.to_string(),
            r.ef.to_string(),
            format!("{:.1}", r.build_s),
            format!("{:.0} ({})", r.bytes as f64 / 1e6, r.bytes / n.max(1)),
            r.rss_delta
                .map_or_else(|| "n/a".into(), |d| format!("{:.0}", d as f64 / 1e6)),
            format!("{:.2}", r.ms),
            format!("{:.4}", r.mean),
            format!("{:.3}", r.min),
        ]);
    }
    t
}

/// For recall targets 0.99, 0.999 and 1: per index, the fastest sweep point reaching the target
/// (measured points only, nothing interpolated).
fn equal_recall(points: &[SweepRow], k: usize) -> String {
    let mut labels: Vec<&str> = points.iter().map(|p| p.label.as_str()).collect();
    labels.dedup();
    let mut t = Table::new(std::iter::once("target").chain(labels.iter().copied()));
    for target in [0.99, 0.999, 1.0] {
        let cells = labels.iter().map(|l| {
            points
                .iter()
                .filter(|p| p.label == *l && p.mean >= target)
                .min_by(|a, b| a.ms.total_cmp(&b.ms))
                .map_or_else(
                    || "not reached".into(),
                    |p| format!("{:.2} ms (ef {}, {:.4})", p.ms, p.ef, p.mean),
                )
        });
        t.row(std::iter::once(format!("≥ {target}")).chain(cells));
    }
    format!("\nFastest measured point per index at recall@{k} ≥ target (no interpolation):\n\n{t}")
}
