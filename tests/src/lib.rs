//! Shared helpers for slag's end-to-end tests: fixture paths, CLI-equivalent argument parsing,
//! and the encode → partition → shard server → fetch → edge serve set-up ([`robot_path`]).

use std::path::PathBuf;
use std::sync::Arc;

use clap::Parser;
use slag_encoder::cli::encode::EncodeArgs;

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

#[derive(Parser)]
struct EncodeCli {
    #[command(flatten)]
    args: EncodeArgs,
}

/// Parses `slag-encoder encode` arguments exactly as the binary does.
pub fn encode_args(args: &[&str]) -> EncodeArgs {
    let argv = std::iter::once("encode").chain(args.iter().copied());
    match EncodeCli::try_parse_from(argv) {
        Ok(c) => c.args,
        Err(e) => panic!("bad test arguments: {e}"),
    }
}

/// Runs `slag-encoder encode` as the binary would on `scene` with the arguments of `line`
/// (whitespace-separated; `{F}` stands for `../shared/fixtures`), quietly, into `out`.
pub fn encode_line(
    scene: &std::path::Path,
    line: &str,
    out: &std::path::Path,
) -> anyhow::Result<slag_encoder::report::Report> {
    let fixtures = shared().join("fixtures").display().to_string();
    let mut argv: Vec<String> = ["--scene", &scene.display().to_string(), "--quiet", "--out"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    argv.push(out.display().to_string());
    argv.extend(line.split_whitespace().map(|t| t.replace("{F}", &fixtures)));
    let args = encode_args(&argv.iter().map(String::as_str).collect::<Vec<_>>());
    slag_encoder::cli::encode::run(&args)
}

/// What [`robot_path`] sets up: every server runs on the runtime it was given.
pub struct RobotPath {
    /// Temporary folder holding the encoder output, the shard store and the edge store.
    pub dir: tempfile::TempDir,
    /// The encoder's `embeddings.safetensors`.
    pub embeddings: PathBuf,
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
        scene: "snowmiku-mini".into(),
        center: slag_edge::fetch::Center::Ground([0.0, 0.0]),
        radius: 1e6,
        prune: false,
        jobs: 4,
        retries: 1,
        timeout: std::time::Duration::from_secs(30),
        token: None,
        progress: false,
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
    use slag_edge::serve::{AppState, ServeOptions};
    let dir = tempfile::tempdir().expect("temporary folder");
    let out = dir.path().join("enc");
    encode_line(
        &default_scene(),
        "--masks graph --clip-visual {F}/clip/color-clip-visual.onnx --every 2 --raster-scale 0.5",
        &out,
    )
    .expect("encode");
    let embeddings = out.join("embeddings.safetensors");
    let shard_store = dir.path().join("shards");
    slag_shards::cli::run_partition(&slag_shards::cli::PartitionArgs {
        embeddings: Some(embeddings.clone()),
        synthetic: None,
        store: shard_store.clone(),
        scene: "snowmiku-mini".into(),
        max_shard_mb: slag_shards::partition::DEFAULT_MAX_SHARD_MIB,
        // A count keeps this scene's tiling independent of the dtype under test.
        max_per_shard: Some(8000),
        report: None,
        up: None,
        cameras: Some(default_scene()),
        to_map: None,
        to_map_points: None,
        display_ply: display.then(|| default_scene().join("point_cloud.ply")),
        dtype: dtype.parse().expect("dtype"),
        qdrant_url: None,
        qdrant_collection: None,
        qdrant_batch: 256,
        qdrant_int8: false,
        qdrant_snapshot_per_tile: false,
        qdrant_api_key: None,
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
            manifest,
            shard_url,
            edge,
            fetched,
            edge_url,
        }
    })
}
