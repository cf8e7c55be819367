//! Shared helpers for slag's end-to-end tests: fixture paths, the tests' encode settings as
//! typed [`EncodeConfig`]s, and the encode → partition → shard server → fetch → edge serve
//! set-up ([`robot_path`]).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use slag_encoder::config::{EncodeConfig, MasksConfig};
use slag_encoder::pipeline::Encoder;
use slag_encoder::report::Report;

/// `../shared` (or `$SLAG_SHARED`).
pub fn shared() -> PathBuf {
    slag_common::paths::source_tree_shared_dir()
}

/// A file under `../shared/fixtures`.
pub fn fixture(rel: &str) -> PathBuf {
    shared().join("fixtures").join(rel)
}

/// The embedded default scene shipped in the repository.
pub fn default_scene() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join("data")
        .join("snowmiku-mini")
}

/// color-clip's visual tower, `fixtures/clip/color-clip-visual.onnx`.
pub fn color_clip_visual() -> PathBuf {
    fixture("clip/color-clip-visual.onnx")
}

/// The tests' usual encode of `scene` into `out`: graph masks and color-clip, every training
/// view (`--views all`: the tests count and compare the views encoded), no progress bars, the
/// dense embeddings beside the default outputs (the tests read `E_k` rows), every other setting
/// at the command line's default. Change fields before [`encode`].
pub fn graph_config(scene: &Path, out: &Path) -> EncodeConfig {
    let mut c = EncodeConfig::new(scene, color_clip_visual(), out);
    c.masks = MasksConfig::graph();
    c.scene.views.mode = slag_encoder::views::SelectionMode::All;
    c.output.progress = false;
    c.output.dense = true;
    c
}

/// color-sam masks (`fixtures/sam-amg`) on a `points_per_side`² grid with the reference filters
/// (predicted IoU 0.8, stability 0.5), as the encoder's tests and the trade study use them.
pub fn color_sam(points_per_side: u32) -> MasksConfig {
    let mut m = MasksConfig::sam(
        fixture("sam-amg/color-sam-encoder.onnx"),
        fixture("sam-amg/color-sam-decoder.onnx"),
    );
    m.sam.points_per_side = points_per_side;
    m.sam.pred_iou_thresh = 0.8;
    m.sam.stability_score_thresh = 0.5;
    m
}

/// An encode of `scene` into `out` through real-architecture models with random weights: the
/// CLIP visual tower `clip_visual`, SAM `[encoder, decoder]` on an 8 × 8 point grid with every
/// filter off (random weights predict low IoU), every `every`-th view (all of them encoded) at
/// raster scale 0.25, no progress bars, the dense embeddings beside the default outputs.
pub fn random_weights_config(
    scene: PathBuf,
    clip_visual: PathBuf,
    sam: [PathBuf; 2],
    every: usize,
    out: &Path,
) -> EncodeConfig {
    let mut config = EncodeConfig::new(scene, clip_visual, out);
    let [encoder, decoder] = sam;
    config.masks = MasksConfig::sam(encoder, decoder);
    config.masks.sam.points_per_side = 8;
    config.masks.sam.pred_iou_thresh = 0.0;
    config.masks.sam.stability_score_thresh = 0.0;
    config.scene.every = every;
    config.scene.views.mode = slag_encoder::views::SelectionMode::All;
    config.raster.scale = 0.25;
    config.output.progress = false;
    config.output.dense = true;
    config
}

/// Runs `config` as `slag-encoder encode` does: checked by [`Encoder::new`], then run.
pub fn encode(config: EncodeConfig) -> anyhow::Result<Report> {
    Ok(Encoder::new(config)?.run()?)
}

/// What [`robot_path`] sets up: every server runs on the runtime it was given.
pub struct RobotPath {
    /// Temporary folder holding the encoder output, the shard store and the edge store.
    pub dir: tempfile::TempDir,
    /// The encoder's `embeddings.safetensors`.
    pub embeddings: PathBuf,
    /// The encoder's `mixture.safetensors` when the shards are mixtures ([`Shards::Mixture`]).
    pub mixture: Option<PathBuf>,
    /// The partitioned scene's manifest (as the shard server holds it).
    pub manifest: slag_common::shards::Manifest,
    /// Base URL of the shard server (`slag-encoder serve`).
    pub shard_url: String,
    /// The robot's store, filled by one fetch of the whole scene.
    pub edge: slag_edge::store::EdgeStore,
    /// What that fetch did.
    pub fetched: slag_edge::fetch::FetchSummary,
    /// Base URL of `slag-edge serve` over `edge`.
    pub edge_url: String,
}

/// The fetch parameters of [`robot_path`]: scene `snowmiku-mini` from `shard_url`, a disc of
/// radius 1e6 around the ground origin (the whole scene), 4 jobs, 1 retry, 30 s timeout.
pub fn robot_fetch_params(shard_url: &str) -> slag_edge::fetch::FetchParams {
    slag_edge::fetch::FetchParams {
        server: shard_url.into(),
        ca_cert: None,
        scene: "snowmiku-mini".into(),
        center: slag_edge::fetch::Center::Ground([0.0, 0.0]),
        radius: 1e6,
        prune: false,
        jobs: 4,
        retries: 1,
        timeout: std::time::Duration::from_secs(30),
        min_rate: slag_edge::fetch::DEFAULT_MIN_RATE,
        token: None,
        progress: false,
        trusted_keys: None,
        frame: Default::default(),
    }
}

/// The whole robot path on the embedded scene, as the binaries run it: encode snowmiku-mini
/// (graph masks + color-clip, every 2nd view, raster scale 0.5) → `partition` (8000 per shard,
/// `dtype`, `--display-ply` of the scene's `.ply` when `display` is set) → `slag-encoder serve` →
/// `slag-edge fetch` of every tile ([`robot_fetch_params`]) → `slag-edge serve` with the
/// color-clip text tower, the paper threshold and `request_timeout`, serving the web viewer from
/// `web_dir` when given. The servers are spawned on `rt`. Panics on any failure (test helper).
pub fn robot_path(
    rt: &tokio::runtime::Runtime,
    dtype: &str,
    display: bool,
    request_timeout: std::time::Duration,
    web_dir: Option<PathBuf>,
) -> RobotPath {
    robot_path_with(
        rt,
        Shards::Dense { dtype, display },
        request_timeout,
        web_dir,
    )
}

/// What [`robot_path_with`] partitions.
#[derive(Debug, Clone, Copy)]
pub enum Shards<'a> {
    /// The embeddings file, as `dtype` shards, with the display columns when `display`.
    Dense {
        /// `f32`, `f16` or `int8`.
        dtype: &'a str,
        /// Pass `--display-ply`.
        display: bool,
    },
    /// Encode with `--mixture-keep keep` and partition `mixture.safetensors`
    /// (`partition --embeddings`, cut to `slots` with `--mixture-keep` when given).
    Mixture {
        /// `encode --mixture-keep`.
        keep: usize,
        /// `partition --mixture-keep`.
        slots: Option<usize>,
    },
}

/// [`robot_path`] with the partition chosen by `shards` (dense or mixture).
pub fn robot_path_with(
    rt: &tokio::runtime::Runtime,
    shards: Shards<'_>,
    request_timeout: std::time::Duration,
    web_dir: Option<PathBuf>,
) -> RobotPath {
    use slag_edge::serve::{AppState, ServeOptions};
    let dir = tempfile::tempdir().expect("temporary folder");
    let out = dir.path().join("enc");
    let mut config = graph_config(&default_scene(), &out);
    config.scene.every = 2;
    config.raster.scale = 0.5;
    let (dtype, display, mixture_slots) = match shards {
        Shards::Dense { dtype, display } => (dtype, display, None),
        Shards::Mixture { keep, slots } => {
            config.aggregate.mixture_keep = Some(keep);
            ("f16", false, slots)
        }
    };
    let mixture = matches!(shards, Shards::Mixture { .. }).then(|| out.join("mixture.safetensors"));
    encode(config).expect("encode");
    let embeddings = out.join("embeddings.safetensors");
    let shard_store = dir.path().join("shards");
    slag_shards::stage::partition(&slag_shards::stage::PartitionConfig {
        input: slag_shards::stage::PartitionInput::Embeddings(
            mixture.clone().unwrap_or_else(|| embeddings.clone()),
        ),
        mixture_keep: mixture_slots,
        store: shard_store.clone(),
        scene: "snowmiku-mini".into(),
        // A count keeps this scene's tiling independent of the dtype under test.
        cap: slag_shards::partition::ShardCap::Gaussians(8000),
        report: None,
        up: None,
        cameras: Some(default_scene()),
        to_map: None,
        display_ply: display.then(|| default_scene().join("point_cloud.ply")),
        dtype: dtype.parse().expect("dtype"),
        segments: slag_shards::stage::SegmentsChoice::Beside,
        qdrant: None,
        signing_key: None,
        allow_readable_key: false,
        start_generation: None,
    })
    .expect("partition");
    rt.block_on(async {
        let store = slag_shards::store::ShardStore::open(&shard_store).expect("shard store");
        let manifest = store
            .manifest("snowmiku-mini")
            .expect("manifest")
            .expect("a partitioned scene");
        let (tx, rx) = tokio::sync::oneshot::channel();
        tokio::spawn(slag_shards::serve::serve(
            store,
            "127.0.0.1:0".parse().expect("address"),
            move |a| {
                let _ = tx.send(a);
            },
        ));
        let shard_url = format!("http://{}", rx.await.expect("shard server"));
        let edge = slag_edge::store::EdgeStore::open(&dir.path().join("edge")).expect("edge store");
        let fetched = slag_edge::fetch::fetch(&edge, &robot_fetch_params(&shard_url))
            .await
            .expect("fetch");
        let text = slag_common::text::TextEncoder::new(
            &fixture("clip/color-clip-textual.onnx"),
            &fixture("clip/clip-tokenizer.json"),
            slag_common::onnx::ExecutionProvider::Cpu,
        )
        .expect("text encoder");
        let state = AppState::new(
            edge.clone(),
            Arc::new(slag_edge::query::OnnxTextEmbedder::new(
                text,
                "color-clip-textual".into(),
            )),
            ServeOptions {
                request_timeout,
                ..ServeOptions::new("snowmiku-mini")
            },
        )
        .expect("edge state")
        .with_web_dir(web_dir);
        let (tx, rx) = tokio::sync::oneshot::channel();
        tokio::spawn(slag_edge::serve::serve(
            Arc::new(state),
            "127.0.0.1:0".parse().expect("address"),
            move |a| {
                let _ = tx.send(a);
            },
        ));
        let edge_url = format!("http://{}", rx.await.expect("edge server"));
        RobotPath {
            dir,
            embeddings,
            mixture,
            manifest,
            shard_url,
            edge,
            fetched,
            edge_url,
        }
    })
}

/// The runtime the end-to-end tests spawn their servers on: multi-threaded, 2 workers, I/O and
/// timers enabled.
pub fn test_runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("a tokio runtime")
}

/// Sends `req` and asserts the answer's status is `status`; returns the response (a transport
/// error fails the test).
pub async fn send_expecting(req: reqwest::RequestBuilder, status: u16) -> reqwest::Response {
    let r = req.send().await.expect("the request reaches the server");
    assert_eq!(r.status().as_u16(), status, "{}", r.url());
    r
}
