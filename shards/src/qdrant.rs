//! Upload of per-Gaussian embeddings to a Qdrant vector database (SLAG, "Vector Database and
//! Partitioning"), over gRPC with the official `qdrant-client` crate.
//!
//! What [`upload`] sends, in order:
//!
//! 1. `Qdrant.HealthCheck` (fails early, with the URL in the message, when nothing answers);
//! 2. for the main collection: `Collections.CollectionExists`, `Collections.Delete` when it
//!    exists (the collection is **recreated**, so a rerun replaces the old points instead of
//!    mixing generations), `Collections.Create` with one unnamed dense vector of size D, cosine
//!    distance and, when asked, scalar int8 quantisation (`ScalarType::Int8`, quantile 0.99,
//!    always in RAM);
//! 3. `Points.Upsert` (`wait = true`) in batches of at most `batch_size` points, ascending source
//!    row order. Point id = Gaussian id (the source `.ply` index, u32 widened to u64); vector = the
//!    f32 embedding row as the source holds it (unit norm); payload `id` (integer), `x`, `y`, `z`
//!    (double, world frame, scene units: the Gaussian mean) and `tile` (integer, the shard tile id
//!    of [`crate::partition`]).
//! 4. With `snapshot_per_tile`: Qdrant snapshots are per collection, so a per-partition snapshot
//!    (the paper's downloadable partitions) needs one collection per tile. Each tile gets its own
//!    collection `<collection>-tile-<id>` (same schema, recreated likewise) holding only its
//!    points, and then `Snapshots.Create` on it. The main collection still holds every point (for
//!    cloud-side queries), so this mode uploads every point twice.
//!
//! Tiles are recomputed with [`plan_tiles`] from the manifest's ground frame and
//! `max_per_shard` (the tiling is deterministic), and checked against the manifest's tile counts.
//!
//! **Testing status**: CI exercises the client path against a protocol-level test server
//! (`shards/tests/qdrant_upsert.rs`) built from `qdrant-client`'s own generated gRPC
//! server traits, which checks every request (collection schema, quantisation, batch sizes, ids,
//! payload fields, vectors, snapshots); a live server is too heavy for CI. Once, a Qdrant 1.18.3
//! server built from source took the snowmiku upload (119,792 points, 8 tile collections and
//! snapshots, one restored) and its REST API agreed with slag's files on every point, payload,
//! vector and snapshot (`docs/results/qdrant-live.md`, `scripts/lab/qdrant-live-check.py`). One server-side
//! detail: Qdrant keeps payloads as JSON text and reads them back with serde_json's default float
//! parser, so 31,065 of the 359,376 `x`/`y`/`z` doubles (8.6 %) came back one f64 ulp away from
//! the widened f32 sent; narrowed to f32 every one is the mean, bit for bit.

use std::collections::HashMap;
use std::time::Duration;

use qdrant_client::Qdrant;
use qdrant_client::qdrant::{
    CreateCollectionBuilder, Distance, PointStruct, QuantizationType, ScalarQuantizationBuilder,
    UpsertPointsBuilder, Value, VectorParamsBuilder,
};
use slag_common::shards::{GaussianSource, Manifest};
use slag_common::{Error, Result};

use crate::partition::{TilePlan, plan_tiles};

/// Parameters of [`upload`].
#[derive(Debug, Clone)]
pub struct QdrantParams {
    /// gRPC URL of the Qdrant server, e.g. `http://localhost:6334` (the gRPC port, not REST 6333).
    pub url: String,
    /// Collection name: 1-200 characters of `A-Z a-z 0-9 _ - .`. It is deleted and recreated.
    pub collection: String,
    /// Most points per `Upsert` request (≥ 1; default 256).
    pub batch_size: usize,
    /// Enable scalar int8 quantisation in the collection config (Qdrant keeps the f32 originals
    /// and an int8 copy for search).
    pub quantize_int8: bool,
    /// Also create one collection per tile (`<collection>-tile-<id>`) and one snapshot of each.
    pub snapshot_per_tile: bool,
    /// API key sent as the `api-key` header (Qdrant Cloud / servers with auth enabled).
    pub api_key: Option<String>,
}

impl QdrantParams {
    /// Parameters with the defaults: batch 256, no quantisation, no per-tile snapshots, no key.
    pub fn new(url: impl Into<String>, collection: impl Into<String>) -> QdrantParams {
        QdrantParams {
            url: url.into(),
            collection: collection.into(),
            batch_size: 256,
            quantize_int8: false,
            snapshot_per_tile: false,
            api_key: None,
        }
    }
}

/// What [`upload`] did.
#[derive(Debug, Clone, PartialEq)]
pub struct UploadSummary {
    /// Main collection name.
    pub collection: String,
    /// Points upserted into the main collection (= observed Gaussians).
    pub points: u64,
    /// `Upsert` requests sent to the main collection.
    pub batches: u64,
    /// Per-tile collections `(tile id, name)`, empty unless `snapshot_per_tile`.
    pub tile_collections: Vec<(u64, String)>,
    /// Snapshot names the server returned, one per tile collection (same order).
    pub snapshots: Vec<String>,
}

fn valid_collection(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= 200
        && name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-' || b == b'.')
}

/// Uploads every Gaussian of `src` (partitioned as `manifest` says) to Qdrant; see the module
/// doc for the exact requests. Runs the async client on its own current-thread tokio runtime, so
/// call it from synchronous code (not from inside a tokio runtime).
///
/// Errors: invalid parameters ([`Error::Param`]: empty/unsafe collection name, batch size 0), a
/// manifest that does not match `src` ([`Error::Mismatch`]: other dim, count or tiling), and
/// every failed request ([`Error::Network`]): the message names the URL and the operation and
/// says what to check (server running, gRPC port 6334, API key). Connection attempts time out after 5 s and requests after 60 s, so an
/// unreachable server gives an error rather than a hang.
pub fn upload(
    src: &impl GaussianSource,
    manifest: &Manifest,
    params: &QdrantParams,
) -> Result<UploadSummary> {
    if !valid_collection(&params.collection) {
        return Err(Error::param(
            "collection",
            format!("{:?}", params.collection),
            "a Qdrant collection name of 1-200 characters of A-Z a-z 0-9 _ - .",
        ));
    }
    if params.batch_size == 0 {
        return Err(Error::param("batch_size", 0, "at least 1 point per upsert"));
    }
    if let Some(x) = &manifest.mixture {
        // Qdrant holds one dense vector per point; a mixture scene's shards hold codebook
        // mixtures, and uploading reconstructions would give Qdrant other rows than the robot's.
        return Err(Error::param(
            "qdrant_url",
            format!("a mixture scene ({} slots per Gaussian)", x.slots),
            "a dense partition for Qdrant (Qdrant stores dense vectors): partition the \
             embeddings file, not the mixture, into the scene you upload",
        ));
    }
    let (n, d) = (src.ids().len(), src.dim());
    if src.means().len() != n || manifest.total_gaussians != n as u64 || manifest.dim as usize != d
    {
        return Err(Error::mismatch(
            slag_common::Mismatched::Scene,
            format!(
                "manifest ({} Gaussians, dim {}) does not match the embeddings ({n} ids, {} \
                 means, dim {d}); upload the embeddings the shards were made from",
                manifest.total_gaussians,
                manifest.dim,
                src.means().len()
            ),
        ));
    }
    if d == 0 {
        return Err(Error::param("dim", 0, "an embedding width of at least 1"));
    }
    let plans = plan_tiles(
        src.means(),
        &manifest.ground,
        usize::try_from(manifest.max_per_shard).unwrap_or(usize::MAX),
    )?;
    let same = plans.len() == manifest.tiles.len()
        && plans
            .iter()
            .zip(&manifest.tiles)
            .all(|(p, t)| p.id == t.id && p.rows.len() as u64 == t.count);
    if !same {
        return Err(Error::mismatch(
            slag_common::Mismatched::Scene,
            "the manifest's tiles do not match a re-tiling of the embeddings; upload the \
             embeddings the shards were made from",
        ));
    }
    let mut tile_of = vec![0u64; n];
    for p in &plans {
        for &r in &p.rows {
            tile_of[r as usize] = p.id;
        }
    }
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|e| Error::internal(format!("cannot start a tokio runtime for Qdrant: {e}")))?;
    rt.block_on(upload_async(src, &plans, &tile_of, params))
}

/// Error for a failed Qdrant request `op`.
fn request_error(url: &str, op: &str, e: impl std::fmt::Display) -> Error {
    Error::network(
        url,
        format!(
            "Qdrant {op} failed: {e}. Check that the server is running and reachable, that the \
             URL is its gRPC endpoint (port 6334 by default, not the REST port 6333) and that \
             the API key (api_key, or QDRANT_API_KEY) is right"
        ),
    )
}

async fn upload_async(
    src: &impl GaussianSource,
    plans: &[TilePlan],
    tile_of: &[u64],
    params: &QdrantParams,
) -> Result<UploadSummary> {
    let url = params.url.as_str();
    let mut builder = Qdrant::from_url(url)
        .connect_timeout(Duration::from_secs(5))
        .timeout(Duration::from_secs(60))
        .skip_compatibility_check();
    if let Some(key) = &params.api_key {
        builder = builder.api_key(key.clone());
    }
    let client = builder
        .build()
        .map_err(|e| request_error(url, "connecting", e))?;
    client
        .health_check()
        .await
        .map_err(|e| request_error(url, "health check", e))?;

    let all: Vec<u32> = (0..src.ids().len() as u32).collect();
    let batches =
        upload_collection(&client, src, &params.collection, &all, tile_of, params).await?;
    let mut summary = UploadSummary {
        collection: params.collection.clone(),
        points: all.len() as u64,
        batches,
        tile_collections: Vec::new(),
        snapshots: Vec::new(),
    };
    if params.snapshot_per_tile {
        for p in plans {
            let name = format!("{}-tile-{}", params.collection, p.id);
            upload_collection(&client, src, &name, &p.rows, tile_of, params).await?;
            let snap = client
                .create_snapshot(name.as_str())
                .await
                .map_err(|e| request_error(url, &format!("snapshot of {name}"), e))?;
            summary.snapshots.push(
                snap.snapshot_description
                    .map(|s| s.name)
                    .unwrap_or_default(),
            );
            summary.tile_collections.push((p.id, name));
        }
    }
    Ok(summary)
}

/// (Re)creates collection `name` and upserts source rows `rows`; returns the number of batches.
async fn upload_collection(
    client: &Qdrant,
    src: &impl GaussianSource,
    name: &str,
    rows: &[u32],
    tile_of: &[u64],
    params: &QdrantParams,
) -> Result<u64> {
    let url = params.url.as_str();
    let d = src.dim();
    let exists = client
        .collection_exists(name)
        .await
        .map_err(|e| request_error(url, &format!("checking collection {name}"), e))?;
    if exists {
        client
            .delete_collection(name)
            .await
            .map_err(|e| request_error(url, &format!("deleting old collection {name}"), e))?;
    }
    let mut create = CreateCollectionBuilder::new(name)
        .vectors_config(VectorParamsBuilder::new(d as u64, Distance::Cosine));
    if params.quantize_int8 {
        create = create.quantization_config(
            ScalarQuantizationBuilder::default()
                .r#type(QuantizationType::Int8.into())
                .quantile(0.99)
                .always_ram(true),
        );
    }
    client
        .create_collection(create)
        .await
        .map_err(|e| request_error(url, &format!("creating collection {name}"), e))?;

    let (ids, means) = (src.ids(), src.means());
    let mut batches = 0u64;
    for chunk in rows.chunks(params.batch_size) {
        let points: Vec<PointStruct> = chunk
            .iter()
            .map(|&r| {
                let r = r as usize;
                let mut v = vec![0.0f32; d];
                src.vector_into(r, &mut v);
                let m = means[r];
                let payload: HashMap<&str, Value> = HashMap::from([
                    ("id", Value::from(i64::from(ids[r]))),
                    ("x", Value::from(f64::from(m[0]))),
                    ("y", Value::from(f64::from(m[1]))),
                    ("z", Value::from(f64::from(m[2]))),
                    ("tile", Value::from(tile_of[r] as i64)),
                ]);
                PointStruct::new(u64::from(ids[r]), v, payload)
            })
            .collect();
        client
            .upsert_points(UpsertPointsBuilder::new(name, points).wait(true))
            .await
            .map_err(|e| request_error(url, &format!("upserting points into {name}"), e))?;
        batches += 1;
    }
    Ok(batches)
}
