//! Storage and index points of the study, and the footprint table ("model only what a scene
//! requires").

use std::path::Path;
use std::time::Instant;

use anyhow::Context;
use slag_common::embeddings::{Embeddings, StoredPrecision};
use slag_common::shards::Dtype;
use slag_edge::scan::hnsw::HnswIndex;
use slag_edge::scan::{ScanRequest, VectorStore, scan};
use slag_shards::partition::{PartitionParams, UpChoice, partition};

use super::{EvalContext, Row, sets};

/// Knobs of the storage and index sweep.
#[derive(Debug, Clone)]
pub struct StorageOptions {
    /// Timed repetitions of each prompt's query.
    pub repeats: usize,
    /// k of the exact-vs-HNSW comparison.
    pub index_top_k: usize,
    /// HNSW `ef_construction`.
    pub hnsw_ef_construction: usize,
    /// Rows given to HNSW (`None` = all).
    pub hnsw_rows: Option<usize>,
}

/// Bytes per Gaussian held in memory by a scan store of `dtype` rows of width `dim`: the row
/// (int8: + 4 B scale) + 4 B id + 12 B mean (as [`VectorStore::bytes_per_gaussian`]).
pub fn bytes_per_gaussian_of(dtype: Dtype, dim: usize) -> f64 {
    (dtype.bytes_per_vector(dim) + 16) as f64
}

/// The rows of `emb` in a scan store of `dtype`, quantised exactly as the shard codec does
/// ([`VectorStore::push_f32_rows`]), and the seconds it took.
///
/// Errors: non-finite rows, inconsistent embeddings.
pub fn store_of(emb: &Embeddings, dtype: Dtype) -> anyhow::Result<(VectorStore, f64)> {
    let t = Instant::now();
    let mut store = VectorStore::new(emb.dim, dtype)?;
    store.push_f32_rows(&emb.ids, &emb.means, &emb.vectors)?;
    Ok((store, t.elapsed().as_secs_f64()))
}

/// Median of `v` (NaN when empty).
pub fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    let m = v.len() / 2;
    if v.len() % 2 == 1 {
        v[m]
    } else {
        0.5 * (v[m - 1] + v[m])
    }
}

fn ids_of(store: &VectorStore, hits: &[slag_edge::scan::Hit]) -> Vec<u32> {
    let mut ids: Vec<u32> = hits.iter().map(|h| store.ids()[h.row]).collect();
    ids.sort_unstable();
    ids
}

/// Exact threshold scan (`cos >= threshold`) of every prompt on `store`: median latency in ms
/// over prompts × `repeats` (after one untimed run per prompt), and each prompt's matched ids
/// (ascending).
///
/// Errors: a prompt of the wrong width.
pub fn scan_latency(
    store: &VectorStore,
    prompts: &[Vec<f32>],
    threshold: f32,
    repeats: usize,
) -> anyhow::Result<(f64, Vec<Vec<u32>>)> {
    let mut times = Vec::new();
    let mut answers = Vec::new();
    for q in prompts {
        let qs = [q.as_slice()];
        let req = ScanRequest::threshold(&qs, threshold);
        answers.push(ids_of(store, &scan(store, &req)?));
        for _ in 0..repeats {
            let t = Instant::now();
            let hits = scan(store, &req)?;
            times.push(t.elapsed().as_secs_f64() * 1e3);
            std::hint::black_box(hits);
        }
    }
    Ok((median(times), answers))
}

/// `emb` with its rows replaced by `vectors` (same ids, means, weights).
fn with_vectors(emb: &Embeddings, vectors: Vec<f32>) -> Embeddings {
    Embeddings {
        vectors,
        ..emb.clone()
    }
}

/// Storage points on the baseline's f32 embeddings: f32, f16, int8 scan stores.
///
/// Errors: as [`store_of`], [`scan_latency`], [`EvalContext::colour_miou`].
pub fn storage_rows(
    ctx: &EvalContext,
    emb: &Embeddings,
    template: &Row,
    o: &StorageOptions,
) -> anyhow::Result<Vec<Row>> {
    let exact = sets::threshold_sets(emb, &ctx.prompts, ctx.threshold)?;
    let mut rows = Vec::new();
    for (name, dtype) in [
        ("f32", Dtype::F32),
        ("f16", Dtype::F16),
        ("int8", Dtype::I8),
    ] {
        eprintln!("storage {name}");
        let (store, build_s) = store_of(emb, dtype)?;
        let (ms, answer) = scan_latency(&store, &ctx.prompts, ctx.threshold, o.repeats)?;
        let deq = with_vectors(emb, store.vectors().to_f32(emb.dim));
        let miou = ctx.colour_miou(&deq)?;
        let row = Row {
            point: format!("store-{name}"),
            knob: "dtype".into(),
            storage: name.into(),
            build_s,
            bytes_per_gaussian: store.bytes_per_gaussian() as f64,
            query_ms: ms,
            ..template.clone()
        };
        rows.push(row.scanned_storage(ctx, miou, sets::mean_iou(&answer, &exact)));
    }
    Ok(rows)
}

impl Row {
    /// This row as a `storage` point, a stored form of the rows queried by the exact threshold
    /// scan: its colour mIoU and `(mean IoU, prompts averaged)` of its answers at
    /// `ctx.threshold` against the exact f32 answers.
    pub(super) fn scanned_storage(
        self,
        ctx: &EvalContext,
        colour_miou: Option<f64>,
        (iou, prompts): (f64, usize),
    ) -> Row {
        Row {
            section: "storage".into(),
            index: "scan".into(),
            colour_miou,
            held_out_miou: None,
            iou,
            set_iou: iou,
            iou_kind: format!("f32 cos>={}", ctx.threshold),
            iou_prompts: prompts,
            ..self
        }
    }
}

/// Index points: the exact f32 top-k scan vs an HNSW index over the same rows (every n-th row
/// of `emb` when `hnsw_rows` is set), top-k sets compared per prompt.
///
/// Errors: scan or index errors.
pub fn index_rows(
    ctx: &EvalContext,
    emb: &Embeddings,
    template: &Row,
    o: &StorageOptions,
) -> anyhow::Result<Vec<Row>> {
    let n = emb.len();
    let take = o.hnsw_rows.unwrap_or(n).clamp(1, n.max(1));
    let stride = n.div_ceil(take).max(1);
    let rows_idx: Vec<usize> = (0..n).step_by(stride).collect();
    let d = emb.dim;
    let sub = Embeddings {
        ids: rows_idx.iter().map(|&i| emb.ids[i]).collect(),
        means: rows_idx.iter().map(|&i| emb.means[i]).collect(),
        vectors: rows_idx
            .iter()
            .flat_map(|&i| emb.vectors[i * d..(i + 1) * d].iter().copied())
            .collect(),
        total_weights: rows_idx.iter().map(|&i| emb.total_weights[i]).collect(),
        ..emb.clone()
    };
    let (store, _) = store_of(&sub, Dtype::F32)?;
    let k = o.index_top_k.min(store.len()).max(1);
    eprintln!("index: {} rows, top-{k}", store.len());
    // Exact top-k: the ids and the k-th best score of each prompt.
    let mut exact_times = Vec::new();
    let mut exact = Vec::new();
    let mut kth = Vec::new();
    for q in &ctx.prompts {
        let qs = [q.as_slice()];
        let req = ScanRequest::top_k(&qs, k);
        let hits = scan(&store, &req)?;
        kth.push(hits.last().map_or(f32::NEG_INFINITY, |h| h.score));
        exact.push(ids_of(&store, &hits));
        for _ in 0..o.repeats {
            let t = Instant::now();
            std::hint::black_box(scan(&store, &req)?);
            exact_times.push(t.elapsed().as_secs_f64() * 1e3);
        }
    }
    // HNSW.
    let t = Instant::now();
    let index = HnswIndex::build(&store, o.hnsw_ef_construction, k, 0x5eed)?;
    let build_s = t.elapsed().as_secs_f64();
    eprintln!("index: HNSW built in {build_s:.1} s");
    let mut hnsw_times = Vec::new();
    let mut approx = Vec::new();
    let mut recalls = Vec::new();
    for (q, &s_k) in ctx.prompts.iter().zip(&kth) {
        let hits = index.query(q, k)?;
        // Tie-aware recall: a returned row counts when it scores at least the exact k-th best
        // (color-clip rows are mixtures of 12 prototypes, so many rows tie at the k-th score and
        // which of them fill the last places is arbitrary).
        let good = hits.iter().filter(|h| h.score >= s_k - RECALL_EPS).count();
        recalls.push(good.min(k) as f64 / k as f64);
        approx.push(ids_of(&store, &hits));
        for _ in 0..o.repeats {
            let t = Instant::now();
            std::hint::black_box(index.query(q, k)?);
            hnsw_times.push(t.elapsed().as_secs_f64() * 1e3);
        }
    }
    let (set_iou, np) = sets::mean_iou(&approx, &exact);
    let recall = recalls.iter().sum::<f64>() / recalls.len().max(1) as f64;
    let base_bpg = store.bytes_per_gaussian() as f64;
    let common = Row {
        section: "index".into(),
        knob: "index".into(),
        storage: "f32".into(),
        observed: store.len(),
        colour_miou: None,
        held_out_miou: None,
        iou_kind: format!("f32 top-{k} recall, ties counted"),
        ..template.clone()
    };
    Ok(vec![
        Row {
            point: format!("index-scan-top{k}"),
            index: "scan".into(),
            build_s: 0.0,
            bytes_per_gaussian: base_bpg,
            query_ms: median(exact_times),
            iou: 1.0,
            set_iou: 1.0,
            iou_prompts: ctx.prompts.len(),
            ..common.clone()
        },
        Row {
            point: format!("index-hnsw-top{k}"),
            index: "hnsw".into(),
            build_s,
            bytes_per_gaussian: base_bpg + index.memory_bytes() as f64 / store.len() as f64,
            query_ms: median(hnsw_times),
            iou: recall,
            set_iou,
            iou_prompts: np,
            ..common
        },
    ])
}

/// Score slack of the tie-aware recall (HNSW reports `1 − (1 − x·q)`, a few ulps from `x·q`).
const RECALL_EPS: f32 = 1e-5;

/// `f32`, `f16` or `int8`.
pub fn dtype_name(d: Dtype) -> &'static str {
    match d {
        Dtype::F32 => "f32",
        Dtype::F16 => "f16",
        Dtype::I8 => "int8",
    }
}

/// One line of the footprint table.
#[derive(Debug, Clone, serde::Serialize)]
pub struct FootprintRow {
    /// What is stored.
    pub form: String,
    /// Gaussians it holds.
    pub gaussians: usize,
    /// Total bytes.
    pub bytes: u64,
    /// Files or shards, with sizes where there are several.
    pub detail: String,
}

/// The footprint of the baseline run: a dense `N × D` f32 tensor over every Gaussian of the
/// `.ply` vs the observed-only embeddings file (f32, f16) and the shards at f32/f16/int8
/// (`slag_shards::partition` with the CLI default of 16384 Gaussians per shard, up axis from the
/// cameras).
///
/// Errors: I/O in `work`, partition errors.
pub fn footprint(
    ctx: &EvalContext,
    scene: &Path,
    emb: &Embeddings,
    work: &Path,
) -> anyhow::Result<Vec<FootprintRow>> {
    let d = emb.dim;
    let mut rows = vec![FootprintRow {
        form: format!("dense N×{d} f32, every Gaussian of the .ply"),
        gaussians: ctx.scene_gaussians,
        bytes: (ctx.scene_gaussians * d * 4) as u64,
        detail: "one tensor".into(),
    }];
    for (name, p) in [("f32", StoredPrecision::F32), ("f16", StoredPrecision::F16)] {
        let path = work.join(format!("footprint-{name}.safetensors"));
        emb.write(&path, p)?;
        let bytes = std::fs::metadata(&path)
            .with_context(|| format!("{}", path.display()))?
            .len();
        rows.push(FootprintRow {
            form: format!("embeddings.safetensors, observed only, {name}"),
            gaussians: emb.len(),
            bytes,
            detail: "ids, means, vectors, total weights".into(),
        });
        std::fs::remove_file(&path).ok();
    }
    let views = slag_common::camera::load_views(scene)?;
    let ups: Vec<[f64; 3]> = views
        .iter()
        .map(|v| (-v.world_to_camera.rotation.row(1)).to_array())
        .collect();
    for dtype in [Dtype::F32, Dtype::F16, Dtype::I8] {
        let params = PartitionParams {
            scene_id: "study".into(),
            max_per_shard: 16384,
            up: UpChoice::CameraUps(ups.clone()),
            dtype,
            to_map: None,
        };
        let (m, shards) = partition(emb, &params)?;
        let mut sizes: Vec<u64> = shards.iter().map(|(_, b)| b.len() as u64).collect();
        sizes.sort_unstable();
        let total: u64 = sizes.iter().sum();
        let mib = |b: u64| b as f64 / (1u64 << 20) as f64;
        rows.push(FootprintRow {
            form: format!("shards, {}, max 16384 per shard", dtype_name(dtype)),
            gaussians: m.total_gaussians as usize,
            bytes: total,
            detail: format!(
                "{} shards, {:.2} / {:.2} / {:.2} MiB min / median / max",
                sizes.len(),
                mib(*sizes.first().unwrap_or(&0)),
                mib(sizes.get(sizes.len() / 2).copied().unwrap_or(0)),
                mib(*sizes.last().unwrap_or(&0)),
            ),
        });
    }
    Ok(rows)
}
