//! Qdrant upload ([`slag_shards::qdrant::upload`]) against a protocol-level test server.
//!
//! A live Qdrant server is too heavy for CI (it was checked once by hand: docs/results/qdrant-live.md), so
//! this test serves the gRPC services `qdrant-client` talks to (`Qdrant`, `Collections`,
//! `Points`, `Snapshots`) with the client crate's own generated server traits, records every
//! request, enforces the ordering a real server enforces (no upsert/snapshot into a missing
//! collection, no create over an existing one, API key), and the tests compare the recorded
//! requests with the source embeddings and the shard tiling.

mod support;

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::{Arc, Mutex, MutexGuard};

use qdrant_client::qdrant::{
    self as q, collections_server::Collections, collections_server::CollectionsServer,
    points_server::Points, points_server::PointsServer, qdrant_server::Qdrant as QdrantService,
    qdrant_server::QdrantServer, snapshots_server::Snapshots, snapshots_server::SnapshotsServer,
};
use slag_common::embeddings::Embeddings;
use slag_common::shards::synthetic::SyntheticScene;
use slag_common::shards::{Dtype, Manifest, decode_shard};
use slag_shards::partition::partition;
use slag_shards::qdrant::{QdrantParams, upload};
use tonic::transport::Server;
use tonic::transport::server::TcpIncoming;
use tonic::{Request, Response, Status};

/// Everything the server received, plus protocol violations it detected.
#[derive(Default, Debug)]
struct Log {
    /// `(method, collection)` of every request, in arrival order.
    calls: Vec<(&'static str, String)>,
    creates: Vec<q::CreateCollection>,
    deleted: Vec<String>,
    upserts: Vec<q::UpsertPoints>,
    snapshots: Vec<String>,
    /// Collections that currently exist on the "server".
    existing: BTreeSet<String>,
    /// Requests a real server would reject.
    violations: Vec<String>,
}

/// What a real server requires of the collection a call names.
#[derive(Clone, Copy)]
enum Collection {
    Exists,
    Absent,
}

#[derive(Clone)]
struct Mock {
    log: Arc<Mutex<Log>>,
    api_key: Option<String>,
}

impl Mock {
    fn new(existing: &[&str], api_key: Option<&str>) -> Mock {
        let log = Log {
            existing: existing.iter().map(|s| s.to_string()).collect(),
            ..Log::default()
        };
        Mock {
            log: Arc::new(Mutex::new(log)),
            api_key: api_key.map(str::to_string),
        }
    }

    /// Checks the `api-key` header, records the call.
    fn enter<T>(&self, req: &Request<T>, method: &'static str, coll: &str) -> Result<(), Status> {
        if let Some(key) = &self.api_key {
            let got = req.metadata().get("api-key").and_then(|v| v.to_str().ok());
            if got != Some(key.as_str()) {
                return Err(Status::unauthenticated("wrong or missing api-key"));
            }
        }
        let mut log = self.log.lock().expect("log");
        log.calls.push((method, coll.to_string()));
        Ok(())
    }

    fn violation(&self, msg: String) -> Status {
        self.log.lock().expect("log").violations.push(msg.clone());
        Status::failed_precondition(msg)
    }

    /// [`Self::enter`] for a call on collection `name`, then the log, locked, when `name` is as
    /// the call `requires`; else the violation "`action` missing (or existing) collection
    /// `name`" is recorded and answered as a real server would.
    fn enter_collection<T>(
        &self,
        req: &Request<T>,
        method: &'static str,
        name: &str,
        requires: Collection,
        action: &str,
    ) -> Result<MutexGuard<'_, Log>, Status> {
        self.enter(req, method, name)?;
        let log = self.log.lock().expect("log");
        let unmet = match requires {
            Collection::Exists => (!log.existing.contains(name)).then_some("missing"),
            Collection::Absent => log.existing.contains(name).then_some("existing"),
        };
        if let Some(state) = unmet {
            drop(log);
            return Err(self.violation(format!("{action} {state} collection {name}")));
        }
        Ok(log)
    }
}

/// `impl $trait for Mock` with the given real methods and every other method answering
/// `unimplemented` (the generated traits have no default methods).
macro_rules! service {
    ($tr:path, { $($real:tt)* }, $($name:ident($req:ident) -> $resp:ident;)*) => {
        #[tonic::async_trait]
        impl $tr for Mock {
            $($real)*
            $(
                async fn $name(&self, _r: Request<q::$req>) -> Result<Response<q::$resp>, Status> {
                    Err(Status::unimplemented(stringify!($name)))
                }
            )*
        }
    };
}

service!(QdrantService, {
    async fn health_check(
        &self,
        r: Request<q::HealthCheckRequest>,
    ) -> Result<Response<q::HealthCheckReply>, Status> {
        self.enter(&r, "health_check", "")?;
        Ok(Response::new(q::HealthCheckReply {
            title: "slag protocol test server".into(),
            version: "1.16.0".into(),
            commit: None,
        }))
    }
},);

service!(Collections, {
    async fn collection_exists(
        &self,
        r: Request<q::CollectionExistsRequest>,
    ) -> Result<Response<q::CollectionExistsResponse>, Status> {
        let name = r.get_ref().collection_name.clone();
        self.enter(&r, "collection_exists", &name)?;
        let exists = self.log.lock().expect("log").existing.contains(&name);
        Ok(Response::new(q::CollectionExistsResponse {
            result: Some(q::CollectionExists { exists }),
            time: 0.0,
        }))
    }
    async fn delete(
        &self,
        r: Request<q::DeleteCollection>,
    ) -> Result<Response<q::CollectionOperationResponse>, Status> {
        let name = r.get_ref().collection_name.clone();
        let mut log =
            self.enter_collection(&r, "delete_collection", &name, Collection::Exists, "delete of")?;
        log.existing.remove(&name);
        log.deleted.push(name);
        Ok(Response::new(q::CollectionOperationResponse { result: true, time: 0.0 }))
    }
    async fn create(
        &self,
        r: Request<q::CreateCollection>,
    ) -> Result<Response<q::CollectionOperationResponse>, Status> {
        let name = r.get_ref().collection_name.clone();
        let requires = Collection::Absent;
        let mut log =
            self.enter_collection(&r, "create_collection", &name, requires, "create over")?;
        log.existing.insert(name.clone());
        log.creates.push(r.into_inner());
        Ok(Response::new(q::CollectionOperationResponse { result: true, time: 0.0 }))
    }
},
    get(GetCollectionInfoRequest) -> GetCollectionInfoResponse; list(ListCollectionsRequest) -> ListCollectionsResponse; update(UpdateCollection) -> CollectionOperationResponse; update_aliases(ChangeAliases) -> CollectionOperationResponse; list_collection_aliases(ListCollectionAliasesRequest) -> ListAliasesResponse; list_aliases(ListAliasesRequest) -> ListAliasesResponse; collection_cluster_info(CollectionClusterInfoRequest) -> CollectionClusterInfoResponse; update_collection_cluster_setup(UpdateCollectionClusterSetupRequest) -> UpdateCollectionClusterSetupResponse; create_shard_key(CreateShardKeyRequest) -> CreateShardKeyResponse; delete_shard_key(DeleteShardKeyRequest) -> DeleteShardKeyResponse; list_shard_keys(ListShardKeysRequest) -> ListShardKeysResponse;
);

service!(Points, {
    async fn upsert(
        &self,
        r: Request<q::UpsertPoints>,
    ) -> Result<Response<q::PointsOperationResponse>, Status> {
        let name = r.get_ref().collection_name.clone();
        let mut log =
            self.enter_collection(&r, "upsert", &name, Collection::Exists, "upsert into")?;
        log.upserts.push(r.into_inner());
        Ok(Response::new(q::PointsOperationResponse {
            result: Some(q::UpdateResult {
                operation_id: Some(log.upserts.len() as u64),
                status: q::UpdateStatus::Completed.into(),
            }),
            time: 0.0,
            usage: None,
        }))
    }
},
    delete(DeletePoints) -> PointsOperationResponse; get(GetPoints) -> GetResponse; update_vectors(UpdatePointVectors) -> PointsOperationResponse; delete_vectors(DeletePointVectors) -> PointsOperationResponse; set_payload(SetPayloadPoints) -> PointsOperationResponse; overwrite_payload(SetPayloadPoints) -> PointsOperationResponse; delete_payload(DeletePayloadPoints) -> PointsOperationResponse; clear_payload(ClearPayloadPoints) -> PointsOperationResponse; create_field_index(CreateFieldIndexCollection) -> PointsOperationResponse; delete_field_index(DeleteFieldIndexCollection) -> PointsOperationResponse; create_vector_name(CreateVectorNameRequest) -> PointsOperationResponse; delete_vector_name(DeleteVectorNameRequest) -> PointsOperationResponse; search(SearchPoints) -> SearchResponse; search_batch(SearchBatchPoints) -> SearchBatchResponse; search_groups(SearchPointGroups) -> SearchGroupsResponse; scroll(ScrollPoints) -> ScrollResponse; recommend(RecommendPoints) -> RecommendResponse; recommend_batch(RecommendBatchPoints) -> RecommendBatchResponse; recommend_groups(RecommendPointGroups) -> RecommendGroupsResponse; discover(DiscoverPoints) -> DiscoverResponse; discover_batch(DiscoverBatchPoints) -> DiscoverBatchResponse; count(CountPoints) -> CountResponse; update_batch(UpdateBatchPoints) -> UpdateBatchResponse; query(QueryPoints) -> QueryResponse; query_batch(QueryBatchPoints) -> QueryBatchResponse; query_groups(QueryPointGroups) -> QueryGroupsResponse; facet(FacetCounts) -> FacetResponse; search_matrix_pairs(SearchMatrixPoints) -> SearchMatrixPairsResponse; search_matrix_offsets(SearchMatrixPoints) -> SearchMatrixOffsetsResponse;
);

service!(Snapshots, {
    async fn create(
        &self,
        r: Request<q::CreateSnapshotRequest>,
    ) -> Result<Response<q::CreateSnapshotResponse>, Status> {
        let name = r.get_ref().collection_name.clone();
        let mut log =
            self.enter_collection(&r, "create_snapshot", &name, Collection::Exists, "snapshot of")?;
        log.snapshots.push(name.clone());
        Ok(Response::new(q::CreateSnapshotResponse {
            snapshot_description: Some(q::SnapshotDescription {
                name: format!("{name}.snapshot"),
                creation_time: None,
                size: 0,
                checksum: None,
            }),
            time: 0.0,
        }))
    }
},
    list(ListSnapshotsRequest) -> ListSnapshotsResponse; delete(DeleteSnapshotRequest) -> DeleteSnapshotResponse; create_full(CreateFullSnapshotRequest) -> CreateSnapshotResponse; list_full(ListFullSnapshotsRequest) -> ListSnapshotsResponse; delete_full(DeleteFullSnapshotRequest) -> DeleteSnapshotResponse;
);

/// Serves `mock` on 127.0.0.1:<free port>; returns the runtime (keep it alive) and the URL.
fn start(mock: &Mock) -> (tokio::runtime::Runtime, String) {
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    let incoming = rt
        .block_on(async { TcpIncoming::bind(([127, 0, 0, 1], 0).into()) })
        .expect("bind");
    let addr = incoming.local_addr().expect("local addr");
    rt.spawn(
        Server::builder()
            .add_service(QdrantServer::new(mock.clone()))
            .add_service(CollectionsServer::new(mock.clone()))
            .add_service(PointsServer::new(mock.clone()))
            .add_service(SnapshotsServer::new(mock.clone()))
            .serve_with_incoming(incoming),
    );
    (rt, format!("http://{addr}"))
}

const DIM: usize = 16;

/// ~1000 synthetic Gaussians (ids 0, 2, 4, …) tiled into ≤ 300 per tile; returns the embeddings,
/// the manifest and each Gaussian id's tile taken from the decoded shards.
fn scene() -> (Embeddings, Manifest, HashMap<u32, u64>) {
    let emb = SyntheticScene::new(1000, DIM, 5, 100.0, 11).to_embeddings();
    let params = support::z_up_params("qtest", 300, Dtype::F16);
    let (m, shards) = partition(&emb, &params).expect("partition");
    assert!(m.tiles.len() >= 4, "{} tiles", m.tiles.len());
    let mut tile_of = HashMap::new();
    for (tile, bytes) in &shards {
        for id in decode_shard(bytes).expect("decode").ids {
            assert!(tile_of.insert(id, *tile).is_none());
        }
    }
    (emb, m, tile_of)
}

fn dense(p: &q::PointStruct) -> Vec<f32> {
    let v = match p.vectors.as_ref().and_then(|v| v.vectors_options.as_ref()) {
        Some(q::vectors::VectorsOptions::Vector(v)) => v,
        other => panic!("expected one unnamed vector, got {other:?}"),
    };
    match &v.vector {
        Some(q::vector::Vector::Dense(d)) => d.data.clone(),
        None => {
            #[allow(deprecated)]
            let data = v.data.clone();
            data
        }
        other => panic!("expected a dense vector, got {other:?}"),
    }
}

fn num_id(p: &q::PointStruct) -> u64 {
    match p.id.as_ref().and_then(|i| i.point_id_options.as_ref()) {
        Some(q::point_id::PointIdOptions::Num(n)) => *n,
        other => panic!("expected a numeric point id, got {other:?}"),
    }
}

fn int(p: &q::PointStruct, k: &str) -> i64 {
    match p.payload.get(k).and_then(|v| v.kind.as_ref()) {
        Some(q::value::Kind::IntegerValue(i)) => *i,
        other => panic!("payload {k}: expected an integer, got {other:?}"),
    }
}

fn double(p: &q::PointStruct, k: &str) -> f64 {
    match p.payload.get(k).and_then(|v| v.kind.as_ref()) {
        Some(q::value::Kind::DoubleValue(x)) => *x,
        other => panic!("payload {k}: expected a double, got {other:?}"),
    }
}

/// Cosine, size DIM, and the scalar int8 config iff `int8`.
fn check_schema(c: &q::CreateCollection, int8: bool) {
    let vp = match c.vectors_config.as_ref().and_then(|v| v.config.as_ref()) {
        Some(q::vectors_config::Config::Params(p)) => p,
        other => panic!(
            "{}: expected one unnamed vector config, got {other:?}",
            c.collection_name
        ),
    };
    assert_eq!(vp.size, DIM as u64);
    assert_eq!(vp.distance, i32::from(q::Distance::Cosine));
    assert!(vp.quantization_config.is_none());
    match c
        .quantization_config
        .as_ref()
        .and_then(|q| q.quantization.as_ref())
    {
        Some(q::quantization_config::Quantization::Scalar(s)) => {
            assert!(int8, "{}: quantisation not asked for", c.collection_name);
            assert_eq!(s.r#type, i32::from(q::QuantizationType::Int8));
        }
        None => assert!(!int8, "{}: int8 quantisation missing", c.collection_name),
        other => panic!("unexpected quantisation {other:?}"),
    }
}

/// Checks every point of `upserts` against the source; returns the ids, in upload order.
fn check_points(
    upserts: &[&q::UpsertPoints],
    batch: usize,
    emb: &Embeddings,
    tile_of: &HashMap<u32, u64>,
) -> Vec<u32> {
    let row_of: HashMap<u32, usize> = emb.ids.iter().enumerate().map(|(r, &id)| (id, r)).collect();
    let mut ids = Vec::new();
    for u in upserts {
        assert!(
            !u.points.is_empty() && u.points.len() <= batch,
            "batch of {}",
            u.points.len()
        );
        assert_eq!(u.wait, Some(true));
        for p in &u.points {
            let id = u32::try_from(num_id(p)).expect("id in u32");
            let r = row_of[&id];
            let keys: BTreeSet<&str> = p.payload.keys().map(String::as_str).collect();
            assert_eq!(keys, BTreeSet::from(["id", "tile", "x", "y", "z"]));
            assert_eq!(int(p, "id"), i64::from(id));
            assert_eq!(int(p, "tile"), tile_of[&id] as i64);
            for (k, a) in ["x", "y", "z"].into_iter().zip(0..3) {
                assert_eq!(double(p, k), f64::from(emb.means[r][a]), "{k} of {id}");
            }
            assert_eq!(dense(p), emb.vector(r), "vector of {id}");
            ids.push(id);
        }
    }
    ids
}

#[test]
fn upserts_every_gaussian_once_with_schema_payload_and_vectors() {
    let (emb, m, tile_of) = scene();
    let mock = Mock::new(&["slag-test"], Some("secret"));
    let (_rt, url) = start(&mock);
    let mut params = QdrantParams::new(url, "slag-test");
    params.batch_size = 64;
    params.api_key = Some("secret".into());
    let s = upload(&emb, &m, &params).expect("upload");

    let log = mock.log.lock().expect("log");
    assert!(log.violations.is_empty(), "{:?}", log.violations);
    assert_eq!(log.calls[0].0, "health_check");
    // The old collection was deleted, then created again, before any point was sent.
    assert_eq!(log.deleted, ["slag-test"]);
    let order: Vec<&str> = log.calls.iter().map(|c| c.0).take(4).collect();
    assert_eq!(
        order,
        [
            "health_check",
            "collection_exists",
            "delete_collection",
            "create_collection"
        ]
    );
    assert_eq!(log.creates.len(), 1);
    assert_eq!(log.creates[0].collection_name, "slag-test");
    check_schema(&log.creates[0], false);
    assert!(log.snapshots.is_empty());

    let ups: Vec<&q::UpsertPoints> = log.upserts.iter().collect();
    assert!(ups.iter().all(|u| u.collection_name == "slag-test"));
    assert_eq!(ups.len(), emb.len().div_ceil(64));
    let ids = check_points(&ups, 64, &emb, &tile_of);
    assert_eq!(ids, emb.ids, "every Gaussian exactly once, in source order");
    assert_eq!(s.points, emb.len() as u64);
    assert_eq!(s.batches, ups.len() as u64);
    assert!(s.tile_collections.is_empty() && s.snapshots.is_empty());
}

#[test]
fn int8_quantisation_and_one_collection_and_snapshot_per_tile() {
    let (emb, m, tile_of) = scene();
    let mock = Mock::new(&[], None);
    let (_rt, url) = start(&mock);
    let mut params = QdrantParams::new(url, "scene");
    params.batch_size = 100;
    params.quantize_int8 = true;
    params.snapshot_per_tile = true;
    let s = upload(&emb, &m, &params).expect("upload");

    let log = mock.log.lock().expect("log");
    assert!(log.violations.is_empty(), "{:?}", log.violations);
    assert!(log.deleted.is_empty());
    let names: Vec<String> = std::iter::once("scene".to_string())
        .chain(m.tiles.iter().map(|t| format!("scene-tile-{}", t.id)))
        .collect();
    let created: Vec<&str> = log
        .creates
        .iter()
        .map(|c| c.collection_name.as_str())
        .collect();
    assert_eq!(created, names);
    log.creates.iter().for_each(|c| check_schema(c, true));
    assert_eq!(log.snapshots, names[1..]);
    assert_eq!(
        s.snapshots,
        names[1..]
            .iter()
            .map(|n| format!("{n}.snapshot"))
            .collect::<Vec<_>>()
    );
    assert_eq!(
        s.tile_collections,
        m.tiles
            .iter()
            .zip(&names[1..])
            .map(|(t, n)| (t.id, n.clone()))
            .collect::<Vec<_>>()
    );

    // Main collection: everything once.
    let main: Vec<&q::UpsertPoints> = log
        .upserts
        .iter()
        .filter(|u| u.collection_name == "scene")
        .collect();
    assert_eq!(check_points(&main, 100, &emb, &tile_of), emb.ids);
    // Each tile collection: exactly that tile's Gaussians, and its snapshot after its upserts.
    let mut by_tile: BTreeMap<u64, Vec<u32>> = BTreeMap::new();
    for (&id, &t) in &tile_of {
        by_tile.entry(t).or_default().push(id);
    }
    for t in &m.tiles {
        let name = format!("scene-tile-{}", t.id);
        let ups: Vec<&q::UpsertPoints> = log
            .upserts
            .iter()
            .filter(|u| u.collection_name == name)
            .collect();
        let mut ids = check_points(&ups, 100, &emb, &tile_of);
        assert_eq!(ids.len() as u64, t.count);
        ids.sort_unstable();
        let want = by_tile.get_mut(&t.id).expect("tile");
        want.sort_unstable();
        assert_eq!(&ids, want, "tile {}", t.id);
        let last_upsert = log
            .calls
            .iter()
            .rposition(|c| c.0 == "upsert" && c.1 == name);
        let snap = log
            .calls
            .iter()
            .position(|c| c.0 == "create_snapshot" && c.1 == name);
        assert!(last_upsert < snap, "snapshot of {name} before its points");
    }
}

#[test]
fn wrong_api_key_is_a_typed_error() {
    let (emb, m, _) = scene();
    let mock = Mock::new(&[], Some("secret"));
    let (_rt, url) = start(&mock);
    let mut params = QdrantParams::new(url.clone(), "c");
    params.api_key = Some("wrong".into());
    match upload(&emb, &m, &params) {
        Err(e @ slag_common::Error::Network { .. }) => {
            let msg = e.to_string();
            assert!(msg.contains(&url) && msg.contains("API key"), "{msg}");
        }
        other => panic!("expected Error::Network, got {other:?}"),
    }
    assert!(mock.log.lock().expect("log").creates.is_empty());
}

#[test]
fn unreachable_server_is_a_typed_error() {
    let (emb, m, _) = scene();
    // A port that was free a moment ago and is now closed: connection refused.
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("port")
        .port();
    let url = format!("http://127.0.0.1:{port}");
    match upload(&emb, &m, &QdrantParams::new(url.clone(), "c")) {
        Err(e @ slag_common::Error::Network { .. }) => {
            let msg = e.to_string();
            assert!(msg.contains(&url) && msg.contains("6334"), "{msg}");
        }
        other => panic!("expected Error::Network, got {other:?}"),
    }
}

#[test]
fn bad_parameters_and_mismatched_manifest_are_rejected_before_connecting() {
    let (emb, m, _) = scene();
    let url = "http://127.0.0.1:9"; // never contacted
    let mut p = QdrantParams::new(url, "c");
    p.batch_size = 0;
    assert!(matches!(
        upload(&emb, &m, &p),
        Err(slag_common::Error::Param {
            name: "batch_size",
            ..
        })
    ));
    let p = QdrantParams::new(url, "a/b");
    assert!(matches!(
        upload(&emb, &m, &p),
        Err(slag_common::Error::Param {
            name: "collection",
            ..
        })
    ));
    let other = SyntheticScene::new(900, DIM, 5, 100.0, 11).to_embeddings();
    let p = QdrantParams::new(url, "c");
    match upload(&other, &m, &p) {
        Err(e @ slag_common::Error::Mismatch { .. }) => {
            assert!(e.to_string().contains("manifest"), "{e}")
        }
        other => panic!("expected Error::Mismatch, got {other:?}"),
    }
}
