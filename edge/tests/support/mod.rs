//! Test fixtures for the edge: a synthetic grid scene cut into shards, an in-process shard server
//! (same routes as `slag-encoder serve`, with fault injection), text embedders without ONNX, and
//! the fetch-then-serve set-up the serve, view and fault tests share.
#![allow(dead_code, missing_docs, clippy::unwrap_used)]

use std::collections::{HashMap, HashSet};
use std::net::SocketAddr;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, RwLock};
use std::time::Duration;

use axum::body::{Body, Bytes};
use axum::extract::{Path, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use futures_util::StreamExt;
use slag_common::Result;
use slag_common::shards::{
    Aabb, Dtype, GroundFrame, MANIFEST_FORMAT, MANIFEST_VERSION, Manifest, SHARD_FORMAT_VERSION,
    ShardInput, TileInfo, encode_shard, shard_checksum,
};
use slag_edge::fetch::{Center, FetchParams, fetch};
use slag_edge::query::TextEmbedder;
use slag_edge::serve::AppState;
use slag_edge::store::EdgeStore;

/// Side of one tile on the ground (z-up, ground = world x, y).
pub const TILE: f32 = 10.0;

/// A grid scene: tile (i, j) covers `[i*10, i*10+9] × [j*10, j*10+9]`; its Gaussians point
/// mostly along basis direction `(i*ny + j) % (dim - 1)` (the last basis is "background").
pub struct TestScene {
    pub manifest: Manifest,
    pub shards: HashMap<u64, Vec<u8>>,
}

fn lcg(seed: &mut u64) -> f32 {
    *seed = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    ((*seed >> 40) as f32) / ((1u64 << 24) as f32)
}

/// Display columns derived from the ids: (log-scales, logit opacities, rotations, SH DC).
pub type Display = (Vec<[f32; 3]>, Vec<f32>, Vec<[f32; 4]>, Vec<[f32; 3]>);

pub fn display_attrs(ids: &[u32]) -> Display {
    let f = |id: u32| (id % 97) as f32 / 97.0;
    (
        ids.iter()
            .map(|&i| [-2.0 - f(i), -2.5, -3.0 + f(i)])
            .collect(),
        ids.iter().map(|&i| 3.0 * f(i) - 1.0).collect(),
        ids.iter()
            .map(|&i| {
                let q = [1.0, f(i), -0.5 * f(i), 0.25];
                let n = q.iter().map(|x| x * x).sum::<f32>().sqrt();
                q.map(|x| x / n)
            })
            .collect(),
        ids.iter().map(|&i| [f(i) - 0.5, 0.3, -0.2]).collect(),
    )
}

/// A grid scene's shape: (scene id, tiles along x, tiles along y, Gaussians per tile, vector
/// dimension, stored dtype, manifest generation).
pub struct Grid<'a>(
    pub &'a str,
    pub usize,
    pub usize,
    pub usize,
    pub usize,
    pub Dtype,
    pub u64,
);

pub fn grid_scene(
    scene: &str,
    nx: usize,
    ny: usize,
    per_tile: usize,
    dim: usize,
    dtype: Dtype,
    generation: u64,
) -> TestScene {
    grid_scene_with(Grid(scene, nx, ny, per_tile, dim, dtype, generation), None)
}

/// [`grid_scene`] whose shards carry geometric segments (shard format version 3): Gaussian id
/// `i` in segment `segment_of(i)`.
pub fn grid_scene_segmented(grid: Grid, segment_of: &dyn Fn(u32) -> u32) -> TestScene {
    grid_scene_with(grid, Some(segment_of))
}

fn grid_scene_with(grid: Grid, segment_of: Option<&dyn Fn(u32) -> u32>) -> TestScene {
    let Grid(scene, nx, ny, per_tile, dim, dtype, generation) = grid;
    let mut seed = 7 + generation;
    let mut tiles = Vec::new();
    let mut shards = HashMap::new();
    for i in 0..nx {
        for j in 0..ny {
            let id = (i * ny + j) as u64;
            let dir = (i * ny + j) % (dim - 1);
            let mut ids = Vec::new();
            let mut means = Vec::new();
            let mut vectors = Vec::new();
            for k in 0..per_tile {
                ids.push((id as usize * per_tile + k) as u32);
                means.push([
                    i as f32 * TILE + 9.0 * lcg(&mut seed),
                    j as f32 * TILE + 9.0 * lcg(&mut seed),
                    lcg(&mut seed),
                ]);
                let mut v: Vec<f32> = (0..dim).map(|_| 0.3 * (lcg(&mut seed) - 0.5)).collect();
                v[dir] += 0.5 + lcg(&mut seed);
                v[dim - 1] += 0.4 * lcg(&mut seed);
                let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
                vectors.extend(v.iter().map(|x| x / n));
            }
            let display = id.is_multiple_of(2).then(|| display_attrs(&ids));
            let segments: Option<Vec<u32>> =
                segment_of.map(|f| ids.iter().map(|&i| f(i)).collect());
            let bytes = encode_shard(&ShardInput {
                scene_id: scene,
                model: "color-clip",
                tile_id: id,
                dim,
                dtype,
                ids: &ids,
                means: &means,
                vectors: &vectors,
                // Even tiles carry display attributes (derived from the id), odd ones none.
                scales: display.as_ref().map(|d| d.0.as_slice()),
                opacities: display.as_ref().map(|d| d.1.as_slice()),
                rotations: display.as_ref().map(|d| d.2.as_slice()),
                sh_dc: display.as_ref().map(|d| d.3.as_slice()),
                segments: segments.as_deref(),
            })
            .unwrap();
            let lo = [i as f64 * TILE as f64, j as f64 * TILE as f64];
            let hi = [lo[0] + 9.0, lo[1] + 9.0];
            tiles.push(TileInfo {
                id,
                footprint: TileInfo::rect_ring(lo, hi),
                aabb: Aabb::of_points(means.iter().copied()).unwrap(),
                count: per_tile as u64,
                bytes: bytes.len() as u64,
                checksum: format!("{:08x}", shard_checksum(&bytes)),
                sha256: Some(slag_common::shards::signature::sha256_hex(&bytes)),
            });
            shards.insert(id, bytes);
        }
    }
    let manifest = Manifest {
        format: MANIFEST_FORMAT.into(),
        manifest_version: MANIFEST_VERSION,
        shard_format_version: if segment_of.is_some() {
            slag_common::shards::SEGMENTS_SHARD_FORMAT_VERSION
        } else {
            SHARD_FORMAT_VERSION
        },
        scene_id: scene.into(),
        generation,
        model: "color-clip".into(),
        dim: dim as u32,
        dtype,
        ground: GroundFrame::from_axis_name("z").unwrap(),
        frames: Default::default(),
        mixture: None,
        max_per_shard: per_tile as u64,
        total_gaussians: (nx * ny * per_tile) as u64,
        tiles,
    };
    TestScene { manifest, shards }
}

/// The in-process shard server's state and fault switches.
pub struct ServerState {
    pub scene: RwLock<TestScene>,
    /// Shard GETs seen.
    pub requests: AtomicUsize,
    /// Shard GETs that carried a Range header.
    pub range_requests: AtomicUsize,
    /// Tile → send only this many bytes of the next response, then break the connection.
    pub cut_next: Mutex<HashMap<u64, usize>>,
    /// Tiles served with a flipped byte (a corrupt copy on the server).
    pub corrupt: Mutex<HashSet<u64>>,
    /// Required bearer token.
    pub token: Option<String>,
    /// Stream every shard body in chunks of this many bytes with this pause before each.
    pub slow: Mutex<Option<(usize, std::time::Duration)>>,
    /// Tile → send this many bytes of every response, then stall (never finish, never close).
    pub stall: Mutex<HashMap<u64, usize>>,
    /// The body of `GET .../manifest.sig` (404 when `None`): a signature of the manifest's
    /// `to_json()` bytes, which the manifest route sends.
    pub signature: RwLock<Option<Vec<u8>>>,
    /// The body of `GET .../codebook` (404 when `None`): a mixture scene's codebook file.
    pub codebook: RwLock<Option<Vec<u8>>>,
}

pub struct ShardServer {
    pub url: String,
    pub state: Arc<ServerState>,
}

pub async fn shard_server(scene: TestScene, token: Option<String>) -> ShardServer {
    let (state, app) = shard_router(scene, token);
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr: SocketAddr = listener.local_addr().unwrap();
    tokio::spawn(async move {
        axum::serve(listener, app).await.unwrap();
    });
    ShardServer {
        url: format!("http://{addr}"),
        state,
    }
}

/// [`shard_server`] over HTTPS with `tls` (the servers' own loop, default limits); its URL is
/// `https://127.0.0.1:PORT`.
pub async fn shard_server_tls(
    scene: TestScene,
    tls: Arc<slag_common::tls::ServerTls>,
) -> ShardServer {
    let (state, app) = shard_router(scene, None);
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr: SocketAddr = listener.local_addr().unwrap();
    tokio::spawn(slag_common::http::serve_with_tls(
        listener,
        app,
        slag_common::http::ServerLimits::default(),
        Some(tls),
        std::future::pending(),
    ));
    ShardServer {
        url: format!("https://{addr}"),
        state,
    }
}

fn shard_router(scene: TestScene, token: Option<String>) -> (Arc<ServerState>, axum::Router) {
    let state = Arc::new(ServerState {
        scene: RwLock::new(scene),
        requests: AtomicUsize::new(0),
        range_requests: AtomicUsize::new(0),
        cut_next: Mutex::new(HashMap::new()),
        corrupt: Mutex::new(HashSet::new()),
        token,
        slow: Mutex::new(None),
        stall: Mutex::new(HashMap::new()),
        signature: RwLock::new(None),
        codebook: RwLock::new(None),
    });
    let app = axum::Router::new()
        .route("/v1/scenes/{scene}/manifest", get(manifest))
        .route("/v1/scenes/{scene}/manifest.sig", get(manifest_signature))
        .route("/v1/scenes/{scene}/codebook", get(codebook))
        .route("/v1/scenes/{scene}/shards/{id}", get(shard))
        .with_state(state.clone());
    (state, app)
}

fn authorized(state: &ServerState, headers: &HeaderMap) -> bool {
    match &state.token {
        None => true,
        Some(t) => {
            headers
                .get(header::AUTHORIZATION)
                .and_then(|v| v.to_str().ok())
                == Some(format!("Bearer {t}").as_str())
        }
    }
}

async fn manifest(
    State(state): State<Arc<ServerState>>,
    Path(scene): Path<String>,
    headers: HeaderMap,
) -> Response {
    if !authorized(&state, &headers) {
        return (StatusCode::UNAUTHORIZED, "token").into_response();
    }
    let s = state.scene.read().unwrap();
    if scene != s.manifest.scene_id {
        return (StatusCode::NOT_FOUND, "no such scene").into_response();
    }
    s.manifest.to_json().into_response()
}

async fn manifest_signature(
    State(state): State<Arc<ServerState>>,
    Path(scene): Path<String>,
) -> Response {
    let known = state.scene.read().unwrap().manifest.scene_id == scene;
    match state.signature.read().unwrap().clone() {
        Some(sig) if known => sig.into_response(),
        _ => (StatusCode::NOT_FOUND, "no signature").into_response(),
    }
}

async fn codebook(State(state): State<Arc<ServerState>>, Path(scene): Path<String>) -> Response {
    let known = state.scene.read().unwrap().manifest.scene_id == scene;
    match state.codebook.read().unwrap().clone() {
        Some(b) if known => b.into_response(),
        _ => (StatusCode::NOT_FOUND, "no codebook").into_response(),
    }
}

async fn shard(
    State(state): State<Arc<ServerState>>,
    Path((scene, id)): Path<(String, u64)>,
    headers: HeaderMap,
) -> Response {
    if !authorized(&state, &headers) {
        return (StatusCode::UNAUTHORIZED, "token").into_response();
    }
    state.requests.fetch_add(1, Ordering::SeqCst);
    let (mut bytes, etag) = {
        let s = state.scene.read().unwrap();
        if scene != s.manifest.scene_id {
            return (StatusCode::NOT_FOUND, "no such scene").into_response();
        }
        let Some(b) = s.shards.get(&id) else {
            return (StatusCode::NOT_FOUND, "no such shard").into_response();
        };
        (b.clone(), format!("\"{:08x}\"", shard_checksum(b)))
    };
    if state.corrupt.lock().unwrap().contains(&id) {
        let mid = bytes.len() / 2;
        bytes[mid] ^= 0x5a;
    }
    let mut start = 0usize;
    let mut status = StatusCode::OK;
    if let Some(r) = headers.get(header::RANGE).and_then(|v| v.to_str().ok()) {
        state.range_requests.fetch_add(1, Ordering::SeqCst);
        let if_range_ok = headers
            .get(header::IF_RANGE)
            .and_then(|v| v.to_str().ok())
            .is_none_or(|v| v == etag);
        if let Some(n) = r.strip_prefix("bytes=").and_then(|s| s.strip_suffix('-'))
            && let Ok(n) = n.parse::<usize>()
            && if_range_ok
            && n < bytes.len()
        {
            start = n;
            status = StatusCode::PARTIAL_CONTENT;
        }
    }
    let total = bytes.len();
    let body_bytes = Bytes::from(bytes[start..].to_vec());
    let cut = state.cut_next.lock().unwrap().remove(&id);
    let len = body_bytes.len();
    let stall = state.stall.lock().unwrap().get(&id).copied();
    let slow = *state.slow.lock().unwrap();
    let body = match (cut, stall, slow) {
        (None, Some(n), _) => {
            let first = body_bytes.slice(..n.min(len));
            let stream = futures_util::stream::iter(vec![Ok::<Bytes, std::io::Error>(first)])
                .chain(futures_util::stream::pending());
            Body::from_stream(stream)
        }
        (None, None, Some((chunk, pause))) => {
            let pieces: Vec<Bytes> = (0..len)
                .step_by(chunk.max(1))
                .map(|a| body_bytes.slice(a..(a + chunk.max(1)).min(len)))
                .collect();
            let stream = futures_util::stream::iter(pieces).then(move |b| async move {
                tokio::time::sleep(pause).await;
                Ok::<Bytes, std::io::Error>(b)
            });
            Body::from_stream(stream)
        }
        _ => match cut {
            Some(n) => {
                let first = body_bytes.slice(..n.min(len));
                // The error comes after a pause so the first part is flushed to the client before
                // the connection is aborted (hyper would otherwise drop its buffered write).
                let stream = futures_util::stream::iter(vec![
                    Ok::<Bytes, std::io::Error>(first),
                    Err(std::io::Error::other("injected connection drop")),
                ])
                .then(|item| async move {
                    if item.is_err() {
                        tokio::time::sleep(std::time::Duration::from_millis(300)).await;
                    }
                    item
                });
                Body::from_stream(stream)
            }
            None => Body::from(body_bytes),
        },
    };
    let mut resp = Response::builder()
        .status(status)
        .header(header::CONTENT_LENGTH, len)
        .header(header::ETAG, etag);
    if status == StatusCode::PARTIAL_CONTENT {
        resp = resp.header(
            header::CONTENT_RANGE,
            format!("bytes {start}-{}/{total}", total - 1),
        );
    }
    resp.body(body).unwrap()
}

/// Maps `"t<N>"` (and any prompt containing it) to basis vector N; the canonical negatives and
/// anything else to the last ("background") basis vector. Counts calls.
pub struct BasisEmbedder {
    pub dim: usize,
    pub calls: AtomicUsize,
}

impl BasisEmbedder {
    pub fn new(dim: usize) -> Self {
        BasisEmbedder {
            dim,
            calls: AtomicUsize::new(0),
        }
    }
    pub fn vector(&self, text: &str) -> Vec<f32> {
        let mut v = vec![0f32; self.dim];
        let n = text
            .strip_prefix('t')
            .and_then(|s| s.parse::<usize>().ok())
            .filter(|&n| n < self.dim - 1)
            .unwrap_or(self.dim - 1);
        v[n] = 1.0;
        v
    }
}

impl TextEmbedder for BasisEmbedder {
    fn embed(&self, texts: &[&str]) -> Result<Vec<Vec<f32>>> {
        self.calls.fetch_add(1, Ordering::SeqCst);
        Ok(texts.iter().map(|t| self.vector(t)).collect())
    }
    fn name(&self) -> String {
        "basis".into()
    }
    fn cached(&self) -> usize {
        0
    }
}

/// Fetches scene `grid` from the shard server at `url` (disc around the ground origin of
/// `radius`, 2 jobs, no retries) into a new store in a temporary folder.
pub async fn fetch_grid(url: &str, radius: f64) -> (tempfile::TempDir, EdgeStore) {
    let (dir, store) = temp_store();
    fetch(&store, &grid_fetch_params(url, radius))
        .await
        .unwrap();
    (dir, store)
}

/// Serves `state` on an ephemeral loopback port in the background; returns `http://ADDR`.
pub async fn serve_on_loopback(state: AppState) -> String {
    serve_shared_on_loopback(Arc::new(state)).await
}

/// [`serve_on_loopback`] for a state that something else (the ROS 2 node) shares.
pub async fn serve_shared_on_loopback(state: Arc<AppState>) -> String {
    let (tx, rx) = tokio::sync::oneshot::channel();
    tokio::spawn(async move {
        slag_edge::serve::serve(state, "127.0.0.1:0".parse().unwrap(), |a| {
            let _ = tx.send(a);
        })
        .await
        .unwrap();
    });
    format!("http://{}", rx.await.unwrap())
}

/// A [`BasisEmbedder`] whose prompts `t<N>` each wait for one [`Self::release`] before they are
/// embedded (anything else, e.g. the canonical negatives, passes at once); records the order in which
/// prompts entered. Lets a test hold a scan in progress and watch the queue behind it.
pub struct GateEmbedder {
    inner: BasisEmbedder,
    entered: Mutex<Vec<String>>,
    tokens: Mutex<usize>,
    cv: Condvar,
}

impl GateEmbedder {
    pub fn new(dim: usize) -> Self {
        GateEmbedder {
            inner: BasisEmbedder::new(dim),
            entered: Mutex::new(Vec::new()),
            tokens: Mutex::new(0),
            cv: Condvar::new(),
        }
    }
    /// A shared gate of `dim` and the guard that opens it for good when dropped
    /// ([`Self::open_on_drop`]).
    pub fn with_guard(dim: usize) -> (Arc<Self>, OpenOnDrop) {
        let gate = Arc::new(GateEmbedder::new(dim));
        let open = gate.open_on_drop();
        (gate, open)
    }
    /// Lets `n` more gated prompts through.
    pub fn release(&self, n: usize) {
        *self.tokens.lock().unwrap() += n;
        self.cv.notify_all();
    }
    /// A guard that opens the gate for good when dropped (also when a test panics: a runtime
    /// cannot shut down while a blocking task waits at the gate).
    pub fn open_on_drop(self: &Arc<Self>) -> OpenOnDrop {
        OpenOnDrop(self.clone())
    }
    /// Gated prompts in the order they reached the embedder.
    pub fn entered(&self) -> Vec<String> {
        self.entered.lock().unwrap().clone()
    }
}

/// See [`GateEmbedder::open_on_drop`].
pub struct OpenOnDrop(Arc<GateEmbedder>);

impl Drop for OpenOnDrop {
    fn drop(&mut self) {
        self.0.release(1 << 20);
    }
}

impl TextEmbedder for GateEmbedder {
    fn embed(&self, texts: &[&str]) -> Result<Vec<Vec<f32>>> {
        let gated = |t: &&&str| {
            t.strip_prefix('t')
                .is_some_and(|d| !d.is_empty() && d.bytes().all(|b| b.is_ascii_digit()))
        };
        for t in texts.iter().filter(gated) {
            self.entered.lock().unwrap().push(t.to_string());
            let mut tokens = self.tokens.lock().unwrap();
            while *tokens == 0 {
                tokens = self.cv.wait(tokens).unwrap();
            }
            *tokens -= 1;
        }
        self.inner.embed(texts)
    }
    fn name(&self) -> String {
        "gate".into()
    }
    fn cached(&self) -> usize {
        0
    }
}

/// Polls `cond` every 10 ms until it holds; panics with `what` after 30 s (a liveness bound, not
/// a speed check).
pub async fn wait_until(what: &str, mut cond: impl AsyncFnMut() -> bool) {
    let t0 = std::time::Instant::now();
    while !cond().await {
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "never happened: {what}"
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

/// The `slag-edge` binary as a command, not yet started: through `$SLAG_TEST_RUNNER` (e.g. qemu
/// under the cross build) when that is set and not blank. (Read with `option_env!` so that an
/// example may include these fixtures: cargo sets the variable for tests only.)
pub fn slag_edge_command() -> std::process::Command {
    let Some(bin) = option_env!("CARGO_BIN_EXE_slag-edge") else {
        panic!("the slag-edge binary is known to the tests of the slag-edge package only");
    };
    let runner = std::env::var("SLAG_TEST_RUNNER").unwrap_or_default();
    let mut parts = runner.split_whitespace();
    match parts.next() {
        Some(r) => {
            let mut c = std::process::Command::new(r);
            c.args(parts).arg(bin);
            c
        }
        None => std::process::Command::new(bin),
    }
}

/// A file under `../shared/fixtures` (e.g. `clip/clip-tokenizer.json`), as a string argument.
pub fn fixture(rel: &str) -> String {
    slag_common::paths::source_tree_shared_dir()
        .join("fixtures")
        .join(rel)
        .display()
        .to_string()
}

/// color-clip's text tower and the CLIP tokenizer (fixtures), as `[TEXT_MODEL, TOKENIZER]` of
/// [`text_model_args`]: a 512-d text tower, for scenes of 512-d embeddings.
pub fn color_clip_text_model() -> [String; 2] {
    [
        fixture("clip/color-clip-textual.onnx"),
        fixture("clip/clip-tokenizer.json"),
    ]
}

/// `true` when ONNX Runtime is not set up and the caller is to skip: only allowed with
/// `SLAG_SKIP_ORT` set; without it a missing `ORT_DYLIB_PATH` fails the test with the remedy.
pub fn skip_without_ort() -> bool {
    if std::env::var_os("ORT_DYLIB_PATH").is_some() {
        return false;
    }
    assert!(
        std::env::var_os("SLAG_SKIP_ORT").is_some(),
        "ORT_DYLIB_PATH is not set: run `. scripts/setup.sh` (or set SLAG_SKIP_ORT=1)"
    );
    true
}

/// A shard server of scene `grid` at 512-d (2 × 2 tiles of 10 f16 rows: color-clip's text tower
/// fits the stored embeddings) and [`color_clip_text_model`]; `None` where [`skip_without_ort`]
/// says to skip.
pub async fn clip_grid_server() -> Option<(ShardServer, [String; 2])> {
    if skip_without_ort() {
        return None;
    }
    let scene = grid_scene("grid", 2, 2, 10, 512, Dtype::F16, 1);
    Some((shard_server(scene, None).await, color_clip_text_model()))
}

/// The fetch parameters the tests start from: scene `grid` from `url`, a disc of `radius` around
/// the ground origin, 2 jobs, no retries, a 10 s timeout, no pruning, no token.
pub fn grid_fetch_params(url: &str, radius: f64) -> FetchParams {
    FetchParams {
        server: url.into(),
        ca_cert: None,
        scene: "grid".into(),
        center: Center::Ground([0.0, 0.0]),
        radius,
        prune: false,
        jobs: 2,
        retries: 0,
        timeout: Duration::from_secs(10),
        min_rate: slag_edge::fetch::DEFAULT_MIN_RATE,
        token: None,
        progress: false,
        trusted_keys: None,
        frame: Default::default(),
    }
}

/// The ids of the shards of scene `grid` in `store`, ascending.
pub fn stored_ids(store: &EdgeStore) -> Vec<u64> {
    let mut v: Vec<u64> = store
        .stored_shards("grid")
        .unwrap()
        .into_iter()
        .map(|s| s.0)
        .collect();
    v.sort_unstable();
    v
}

/// The path of tile `tile`'s shard of scene `grid` in `store`.
pub fn shard_path(store: &EdgeStore, tile: u64) -> std::path::PathBuf {
    let m = store.manifest("grid").unwrap().unwrap();
    let t = m.tiles.iter().find(|t| t.id == tile).unwrap();
    store.shard_path("grid", t).unwrap()
}

/// Opens the store, waiting for a dropped database's flusher thread to let go of its lock.
pub fn open_after_drop(root: &std::path::Path) -> EdgeStore {
    let t0 = std::time::Instant::now();
    loop {
        match EdgeStore::open(root) {
            Err(e)
                if e.to_string().contains("could not acquire lock")
                    && t0.elapsed() < Duration::from_secs(20) =>
            {
                std::thread::sleep(Duration::from_millis(50));
            }
            other => break other.unwrap(),
        }
    }
}

/// How many files the store at `root` holds in `partial/` (downloads not yet committed).
pub fn partial_files(root: &std::path::Path) -> usize {
    std::fs::read_dir(root.join("partial")).unwrap().count()
}

/// `slag-edge ARGS` ([`slag_edge_command`]) logging at `rust_log`, without the fault-injection
/// and shard-token variables of the test's own environment; not yet started.
pub fn slag_edge_with_log(args: &[&str], rust_log: &str) -> std::process::Command {
    let mut cmd = slag_edge_command();
    cmd.args(args)
        .env("RUST_LOG", rust_log)
        .env_remove("SLAG_FAULT_EXIT_AT")
        .env_remove("SLAG_FAULT_ENOSPC_AT")
        .env_remove("SLAG_FAULT_LIST")
        .env_remove("SLAG_SHARD_TOKEN");
    cmd
}

/// Runs `cmd` to completion on a blocking thread, so that the test's runtime keeps serving.
pub async fn output_blocking(mut cmd: std::process::Command) -> std::process::Output {
    tokio::task::spawn_blocking(move || cmd.output().unwrap())
        .await
        .unwrap()
}

/// Panics with `what` and the command's stderr unless it exited with status 0.
pub fn assert_success(out: &std::process::Output, what: &str) {
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{what}: {err}");
}

/// The command's stdout as JSON, once [`assert_success`] holds.
pub fn success_json(out: &std::process::Output) -> serde_json::Value {
    assert_success(out, "slag-edge failed");
    serde_json::from_slice(&out.stdout).unwrap()
}

/// `fetch --from URL --scene grid --center 0,0 --radius RADIUS --store STORE`.
pub fn fetch_args<'a>(url: &'a str, store: &'a str, radius: &'a str) -> Vec<&'a str> {
    let scene = ["--scene", "grid", "--center", "0,0", "--radius", radius];
    [&["fetch", "--from", url][..], &scene, &["--store", store]].concat()
}

/// `SUB --store STORE --scene SCENE --clip-textual TEXT_MODEL --tokenizer TOKENIZER` (check,
/// query, serve); `model` is `[TEXT_MODEL, TOKENIZER]`.
pub fn text_model_args<'a>(
    sub: &'a str,
    store: &'a str,
    scene: &'a str,
    model: [&'a str; 2],
) -> Vec<&'a str> {
    let [text_model, tokenizer] = model;
    let store = [sub, "--store", store, "--scene", scene];
    [
        &store[..],
        &["--clip-textual", text_model, "--tokenizer", tokenizer],
    ]
    .concat()
}

/// Sends `req` (a transport error fails the test).
pub async fn send(req: reqwest::RequestBuilder) -> reqwest::Response {
    req.send().await.unwrap()
}

/// Sends `req`; the answer's status and its body as JSON.
pub async fn send_json(req: reqwest::RequestBuilder) -> (u16, serde_json::Value) {
    let r = send(req).await;
    (r.status().as_u16(), r.json().await.unwrap())
}

/// The `error` message of a JSON error body.
pub fn error_message(body: &serde_json::Value) -> &str {
    body["error"].as_str().unwrap()
}

/// The ids of an answer's `matches`, in answer order.
pub fn match_ids(answer: &serde_json::Value) -> Vec<u32> {
    let matches = answer["matches"].as_array().unwrap();
    matches
        .iter()
        .map(|m| m["id"].as_u64().unwrap() as u32)
        .collect()
}

/// A response header that holds a number (`retry-after`, `x-slag-matches`).
pub fn header_number(r: &reqwest::Response, name: &str) -> u64 {
    r.headers()[name].to_str().unwrap().parse().unwrap()
}

/// The serve options most tests use: scene `grid`, the paper's threshold 0.28, a 10 s request
/// timeout, the bearer `token` when given, the approximate index when `hnsw`.
pub fn grid_serve_options(token: Option<&str>, hnsw: bool) -> slag_edge::serve::ServeOptions {
    slag_edge::serve::ServeOptions {
        token: token.map(str::to_string),
        threshold: 0.28,
        hnsw,
        request_timeout: Duration::from_secs(10),
        ..slag_edge::serve::ServeOptions::new("grid")
    }
}

/// Serves `store` with `embedder` and `options` on loopback ([`serve_on_loopback`]).
pub async fn serve_store(
    store: EdgeStore,
    embedder: Arc<dyn TextEmbedder>,
    options: slag_edge::serve::ServeOptions,
) -> String {
    serve_on_loopback(AppState::new(store, embedder, options).unwrap()).await
}

/// A new, empty edge store in a temporary folder (removed when the folder is dropped).
pub fn temp_store() -> (tempfile::TempDir, EdgeStore) {
    let dir = tempfile::tempdir().unwrap();
    let store = EdgeStore::open(dir.path()).unwrap();
    (dir, store)
}

/// Answers `raw` (validated as the CLI validates it, paper threshold 0.28) over `engine`'s
/// exact scan with a [`BasisEmbedder`] of `dim` and the canonical negatives; with `display`,
/// the engine's display attributes go into the answer.
pub fn exact_answer(
    engine: &slag_edge::engine::Engine,
    dim: usize,
    raw: slag_edge::query::RawQuery,
    display: bool,
) -> slag_edge::query::QueryAnswer {
    use slag_edge::query::{CANONICAL_NEGATIVES, Interface, QueryContext, run_query_framed};
    let text = BasisEmbedder::new(dim);
    let negatives = text.embed(&CANONICAL_NEGATIVES).unwrap();
    let q = raw.validate_for(0.28, Interface::Cli).unwrap();
    let display = display.then_some(&engine.display);
    let model = &engine.manifest.model;
    let cx = QueryContext {
        store: &engine.store,
        embedding_model: model,
        to_map: None,
        text: &text,
        negatives: &negatives,
        hnsw: None,
        display,
    };
    run_query_framed(&cx, &q).unwrap()
}

/// Overwrites the sled files under `root/db` (or only its data file `db`) with a repeating
/// garbage pattern of the same length.
pub fn damage_db(root: &std::path::Path, only_data: bool) {
    fn walk(p: &std::path::Path, only_data: bool) {
        for e in std::fs::read_dir(p).unwrap().flatten() {
            let path = e.path();
            if path.is_dir() {
                walk(&path, only_data);
            } else if !only_data || e.file_name() == "db" {
                let len = std::fs::metadata(&path).unwrap().len() as usize;
                let junk: Vec<u8> = (0..len.max(64)).map(|i| (i * 131 % 251) as u8).collect();
                std::fs::write(&path, junk).unwrap();
            }
        }
    }
    walk(&root.join("db"), only_data);
}
