//! `slag-edge`: the robot-side runtime (Jetson Orin, aarch64).
//!
//! - `slag-edge fetch --from URL --scene S --center X,Y --radius 50 [--prune]`: download the shards
//!   around the robot into the local sled store;
//! - `slag-edge serve --listen 0.0.0.0:8080 [--config edge.toml] [--hnsw [--hnsw-backend
//!   instant-distance|qdrant-edge]]`: answer `GET /query?text=chair`;
//!   With `--ros2` a ROS 2 node answers prompts beside HTTP (`slag_edge::ros2`);
//! - `slag-edge query --text chair`: the same answer on the command line, no server;
//! - `slag-edge check`: config + ONNX Runtime + store, without serving;
//! - `slag-edge bench`: scan kernels against the memory-bandwidth floor, and the HNSW backends at
//!   equal recall.

mod bench;

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use clap::{Args, Parser, Subcommand, ValueEnum};
use slag_common::cli::EpArg;
use slag_common::cli::server::{DEFAULT_EDGE_LISTEN, ServerArgs};
use slag_common::similarity::PAPER_THRESHOLD;
use slag_common::text::TextEncoder;
use slag_edge::config::{ServeConfig, read_token};
use slag_edge::fetch::{Center, FetchParams};
use slag_edge::query::{FrameChoice, Interface, OnnxTextEmbedder, RawQuery, TextEmbedder};
use slag_edge::serve::{AppState, HnswBackend, ServeOptions};
use slag_edge::store::EdgeStore;

/// The Rust heap of `slag-edge`: jemalloc with background purging (pages freed after a large
/// answer go back to the kernel within its decay time, about 10 s, even when no request follows;
/// glibc malloc kept them). ONNX Runtime and other C/C++ libraries keep the system allocator.
/// See docs/guide/robot-limits.md, "Memory".
#[cfg(target_os = "linux")]
#[global_allocator]
static ALLOCATOR: tikv_jemallocator::Jemalloc = tikv_jemallocator::Jemalloc;

/// slag-edge: download the shards around the robot and answer text queries over HTTP.
#[derive(Parser)]
#[command(version, about)]
struct Cli {
    #[command(flatten)]
    global: slag_common::cli::process::GlobalArgs,
    #[command(subcommand)]
    command: Command,
}

/// Frame of coordinates given to or printed by a command.
#[derive(Debug, Clone, Copy, Default, ValueEnum)]
enum FrameArg {
    /// The map frame (metres) when the scene's manifest has a scene-to-map transform, else the
    /// scene frame.
    #[default]
    Auto,
    /// The robot's map frame (metres); an error when the manifest has no transform.
    Map,
    /// The scene (reconstruction) frame, scene units.
    Scene,
}

impl From<FrameArg> for FrameChoice {
    fn from(f: FrameArg) -> Self {
        match f {
            FrameArg::Auto => FrameChoice::Auto,
            FrameArg::Map => FrameChoice::Map,
            FrameArg::Scene => FrameChoice::Scene,
        }
    }
}

#[derive(Subcommand)]
enum Command {
    /// Download the shards within a radius into the local store.
    Fetch(FetchArgs),
    /// Serve text queries over HTTP.
    Serve(ServeArgs),
    /// Answer one query from the local store on the command line (JSON, as GET /query).
    Query(QueryArgs),
    /// Check a deployment without serving: config, ONNX Runtime + text model (one prompt), store
    /// and scene load; prints a JSON report, exits non-zero on the first problem.
    Check(ServeArgs),
    /// Benchmark the scan kernels (f32/f16/int8, top-k, threshold, LERF) against the
    /// memory-bandwidth floor of the same bytes and a naive f32 scan; prints a Markdown table.
    Bench(bench::BenchArgs),
}

#[derive(Args)]
struct FetchArgs {
    /// Shard server base URL (`slag-encoder serve`), e.g. http://10.0.0.2:8090.
    #[arg(long = "from", value_name = "URL")]
    server: String,
    /// Scene id.
    #[arg(long, value_name = "NAME")]
    scene: String,
    /// Disc centre. With a map frame (the manifest has a scene-to-map transform): X,Y or X,Y,Z
    /// in the robot's map frame, metres. Without: X,Y on the manifest's ground plane, or X,Y,Z
    /// in the scene frame.
    #[arg(long, allow_hyphen_values = true)]
    center: Center,
    /// Disc radius: metres with a map frame, else scene units.
    #[arg(long, default_value_t = 50.0)]
    radius: f64,
    /// Frame of --center and --radius.
    #[arg(long, value_enum, default_value_t = FrameArg::Auto)]
    frame: FrameArg,
    /// Also evict stored shards outside the disc.
    #[arg(long)]
    prune: bool,
    /// Store folder (sled database + partial downloads).
    #[arg(long, value_name = "DIR", default_value = "slag-store")]
    store: PathBuf,
    /// Parallel downloads.
    #[arg(long, default_value_t = 4)]
    jobs: usize,
    /// Retries per shard after a transient failure.
    #[arg(long, default_value_t = 3)]
    retries: u32,
    /// Connect / idle-read timeout per request, seconds; also the grace before --min-rate counts.
    #[arg(long, default_value_t = 30.0)]
    timeout: f64,
    /// Least mean rate of every transfer, bytes per second: after --timeout, a file (manifest,
    /// signature, tile) slower than this is cut off, so each file has a deadline that grows with
    /// its size (a tile cut off resumes on the retry). The default, 16 KiB/s, is a few percent of
    /// a slow LTE link. 0: no deadline.
    #[arg(long, value_name = "BYTES_PER_S", default_value_t = slag_edge::fetch::DEFAULT_MIN_RATE)]
    min_rate: u64,
    /// File whose first line is the shard server's bearer token (as `serve
    /// --shard-token-file`); without it, env SLAG_SHARD_TOKEN.
    #[arg(long, value_name = "FILE")]
    shard_token_file: Option<PathBuf>,
    /// The shard server's bearer token itself: the older form of --shard-token-file, still
    /// accepted (noted as deprecated; a token on the command line shows in the process list).
    #[arg(long, env = "SLAG_SHARD_TOKEN", hide = true, hide_env_values = true)]
    token: Option<String>,
    /// The publisher's Ed25519 public key (PEM, `manifest-key.pub.pem` of `slag-shards
    /// keygen`): refuse a manifest it did not sign, a tile whose SHA-256 differs from the signed
    /// manifest, and an older generation than the store holds. Repeat it, or put several PEM
    /// blocks in one file, to trust several keys (a key rotation). Without it, unsigned maps are
    /// accepted.
    #[arg(long, value_name = "FILE")]
    trusted_key: Vec<PathBuf>,
    /// A private CA's certificate (PEM; several may follow each other) to trust for an https://
    /// --from, in addition to the built-in public roots.
    #[arg(long, value_name = "FILE")]
    ca_cert: Option<PathBuf>,
    /// Print the summary as JSON.
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
struct ServeArgs {
    /// TOML config (keys = these flags' long names with `_`); flags override it.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Store folder written by `fetch`.
    #[arg(long, value_name = "DIR")]
    store: Option<PathBuf>,
    /// Scene id.
    #[arg(long, value_name = "NAME")]
    scene: Option<String>,
    /// Where to listen, the bearer token clients must send, TLS and the connection limits
    /// (the flags the shard server shares).
    #[command(flatten)]
    server: ServerArgs,
    /// CLIP text tower ONNX (input_ids i64[B,77] → f32[B,D]) of the model that made the shards.
    #[arg(long = "clip-textual", alias = "text-model", value_name = "ONNX")]
    text_model: Option<PathBuf>,
    /// CLIP tokenizer (tokenizer.json).
    #[arg(long)]
    tokenizer: Option<PathBuf>,
    /// ONNX Runtime execution provider.
    #[arg(long, value_enum)]
    ep: Option<EpArg>,
    /// Default cosine threshold (paper: 0.28).
    #[arg(long)]
    threshold: Option<f32>,
    /// File with the shard server's bearer token, which POST /fetch sends (also env
    /// SLAG_SHARD_TOKEN).
    #[arg(long, value_name = "FILE")]
    shard_token_file: Option<PathBuf>,
    /// The publisher's Ed25519 public key (PEM): POST /fetch then refuses what it did not sign
    /// (as `fetch --trusted-key`), and `check` verifies the stored signature and every stored
    /// file's SHA-256 with it; the store's tiles are hashed on every load. Repeatable, or several
    /// PEM blocks in one file (a key rotation).
    #[arg(long, value_name = "FILE")]
    trusted_key: Vec<PathBuf>,
    /// A private CA's certificate (PEM) that POST /fetch trusts for an https:// shard server, in
    /// addition to the built-in public roots.
    #[arg(long, value_name = "FILE")]
    ca_cert: Option<PathBuf>,
    /// Build the approximate HNSW index at load (queries pick it with index=hnsw).
    #[arg(long)]
    hnsw: bool,
    /// Implementation of the --hnsw index: instant-distance (default), or qdrant-edge (Qdrant
    /// Edge's HNSW; only in a binary built with `--features qdrant-edge`, refused otherwise).
    #[arg(long, value_name = "instant-distance|qdrant-edge")]
    hnsw_backend: Option<String>,
    /// Per-request timeout, seconds.
    #[arg(long, default_value_t = 30.0)]
    request_timeout: f64,
    /// Scans running at once (each already uses every core; default 1).
    #[arg(long)]
    max_scans: Option<usize>,
    /// Queries that may wait for a scan; one more is answered 503 with Retry-After (default 32).
    #[arg(long)]
    scan_queue: Option<usize>,
    /// Matches one request may ask for in all: the sum of top_k over a POST /query batch; more
    /// is answered 400 (default 20000).
    #[arg(long)]
    max_matches: Option<usize>,
    /// Serve the web page from this folder instead of the compiled-in one: its `index.html` and
    /// `app.js` where present, and the viewer bundles from its `vendor/` (made by `bash
    /// scripts/web-vendor.sh`). Default: the page and viewer compiled into this binary.
    #[arg(long)]
    web_dir: Option<PathBuf>,
    /// Also run a ROS 2 node (DDS, domain $ROS_DOMAIN_ID) beside HTTP: prompts on ~/prompt,
    /// answers on ~/objects, ~/matches and ~/markers, from the same store and admission gate.
    #[arg(long)]
    ros2: bool,
    /// Name of the ROS 2 node (default slag).
    #[arg(long)]
    ros2_node: Option<String>,
    /// Namespace of the ROS 2 node: / or /a/b (default /).
    #[arg(long)]
    ros2_namespace: Option<String>,
    /// header.frame_id of the ROS 2 messages (default map).
    #[arg(long)]
    ros2_frame_id: Option<String>,
}

#[derive(Args)]
struct QueryArgs {
    /// Store folder written by `fetch`.
    #[arg(long, value_name = "DIR", default_value = "slag-store")]
    store: PathBuf,
    /// Scene id.
    #[arg(long, value_name = "NAME")]
    scene: String,
    /// CLIP text tower ONNX of the model that made the shards.
    #[arg(long = "clip-textual", alias = "text-model", value_name = "ONNX")]
    text_model: PathBuf,
    /// CLIP tokenizer (tokenizer.json).
    #[arg(long)]
    tokenizer: PathBuf,
    /// ONNX Runtime execution provider.
    #[arg(long, value_enum, default_value_t = EpArg::Cpu)]
    ep: EpArg,
    /// Prompt.
    #[arg(long)]
    text: String,
    /// Matches returned (default 100).
    #[arg(long, value_name = "K")]
    top_k: Option<String>,
    /// Threshold, or `none`.
    #[arg(long, allow_hyphen_values = true)]
    threshold: Option<String>,
    /// cosine | relevancy.
    #[arg(long)]
    mode: Option<String>,
    /// minx,miny,minz,maxx,maxy,maxz (in the answer's frame, see --frame).
    #[arg(long, allow_hyphen_values = true)]
    bbox: Option<String>,
    /// Frame of the answer's coordinates and of --bbox.
    #[arg(long, value_enum, default_value_t = FrameArg::Auto)]
    frame: FrameArg,
    /// Objects returned, 1..=1000 (default 20).
    #[arg(long)]
    max_objects: Option<String>,
    /// x,y,z (answer's frame): sort objects by distance from this point.
    #[arg(long, allow_hyphen_values = true)]
    near: Option<String>,
    /// Single-linkage gap between an object's matches, answer-frame units (default: 4 × the
    /// matches' median nearest-neighbour distance).
    #[arg(long)]
    object_gap: Option<String>,
    /// Smallest object, in matching Gaussians (default 10).
    #[arg(long)]
    object_min_gaussians: Option<String>,
    /// none | segment: score each Gaussian with the mean score of its geometric segment (the
    /// open-vocabulary form of the paper's prediction filtering; needs shards with segments).
    #[arg(long)]
    smooth: Option<String>,
}

fn text_embedder(
    model: &std::path::Path,
    tokenizer: &std::path::Path,
    ep: EpArg,
) -> anyhow::Result<Arc<dyn TextEmbedder>> {
    let enc = TextEncoder::new(model, tokenizer, ep.into())?;
    let name = model
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "clip-text".into());
    Ok(Arc::new(OnnxTextEmbedder::new(enc, name)))
}

fn timeout(secs: f64, flag: &str) -> anyhow::Result<Duration> {
    Duration::try_from_secs_f64(secs)
        .ok()
        .filter(|d| !d.is_zero())
        .with_context(|| format!("{flag} {secs}: use a positive number of seconds"))
}

fn runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")
}

fn run_fetch(a: FetchArgs) -> anyhow::Result<()> {
    let store = EdgeStore::open(&a.store)?;
    let params = FetchParams {
        server: a.server,
        ca_cert: a.ca_cert,
        scene: a.scene,
        center: a.center,
        radius: a.radius,
        prune: a.prune,
        jobs: a.jobs,
        retries: a.retries,
        timeout: timeout(a.timeout, "--timeout")?,
        min_rate: a.min_rate,
        token: match &a.shard_token_file {
            Some(p) => Some(read_token(p)?),
            None => a
                .token
                .as_deref()
                .map(|t| slag_common::auth::configured_token(t, "SLAG_SHARD_TOKEN (or --token)"))
                .transpose()?,
        },
        progress: true,
        frame: a.frame.into(),
        trusted_keys: trusted_keys(&a.trusted_key)?,
    };
    let summary = runtime()?.block_on(slag_edge::fetch::fetch(&store, &params))?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&summary)?);
    } else {
        println!("{summary}");
    }
    Ok(())
}

/// The publisher's public keys of `--trusted-key FILE`… (or `trusted_key` in the config), if
/// any: every PEM block of every file.
fn trusted_keys(
    paths: &[PathBuf],
) -> slag_common::Result<Option<slag_common::shards::signature::TrustedKeys>> {
    if paths.is_empty() {
        return Ok(None);
    }
    slag_common::shards::signature::TrustedKeys::read_pem_files(paths).map(Some)
}

/// Everything `serve` needs, resolved from flags over the config file.
struct Resolved {
    store: PathBuf,
    addr: std::net::SocketAddr,
    text_model: PathBuf,
    tokenizer: PathBuf,
    ep: EpArg,
    opts: ServeOptions,
    web_dir: Option<PathBuf>,
    /// The ROS 2 node's settings with `--ros2`.
    ros2: Option<slag_edge::ros2::Ros2Options>,
}

/// The bearer token clients must send (`--token-file`, else env `SLAG_EDGE_TOKEN`), refused over
/// plain HTTP on a non-loopback `addr` unless allowed
/// ([`slag_common::tls::check_token_transport`]). A blank token from any source is refused: it
/// must never start the server open.
fn resolve_token(
    token_file: Option<&std::path::Path>,
    addr: std::net::SocketAddr,
    tls: bool,
    allow_plain_http: bool,
) -> anyhow::Result<Option<String>> {
    let env_token = slag_common::auth::env_token("SLAG_EDGE_TOKEN")?;
    let token = match token_file {
        Some(p) => Some(read_token(p)?),
        None => env_token,
    };
    slag_common::tls::check_token_transport(addr, token.is_some(), tls, allow_plain_http)?;
    Ok(token)
}

/// The shard server's token `POST /fetch` sends: `--shard-token-file`, else env
/// `SLAG_SHARD_TOKEN` (refused when blank).
fn resolve_shard_token(a: &ServeArgs, c: &ServeConfig) -> anyhow::Result<Option<String>> {
    if let Some(p) = a.shard_token_file.as_ref().or(c.shard_token_file.as_ref()) {
        return Ok(Some(read_token(p)?));
    }
    let Ok(t) = std::env::var("SLAG_SHARD_TOKEN") else {
        return Ok(None);
    };
    anyhow::ensure!(
        !t.trim().is_empty(),
        "SLAG_SHARD_TOKEN is set but blank: set it to the shard server's token, or unset it"
    );
    Ok(Some(t.trim().to_string()))
}

/// The server flags, each left out taken from the config file's key of the same name.
fn server_over_config(a: &ServerArgs, c: &ServeConfig) -> ServerArgs {
    ServerArgs {
        listen: a.listen.clone().or(c.listen.clone()),
        token_file: a.token_file.clone().or(c.token_file.clone()),
        tls_cert: a.tls_cert.clone().or(c.tls_cert.clone()),
        tls_key: a.tls_key.clone().or(c.tls_key.clone()),
        allow_plain_http: a.allow_plain_http || c.allow_plain_http.unwrap_or(false),
        header_timeout: a.header_timeout.or(c.header_timeout),
        write_timeout: a.write_timeout.or(c.write_timeout),
        max_connections: a.max_connections.or(c.max_connections),
        body_timeout: a.body_timeout.or(c.body_timeout),
        max_connections_per_ip: a.max_connections_per_ip.or(c.max_connections_per_ip),
    }
}

fn resolve(a: ServeArgs) -> anyhow::Result<Resolved> {
    let web_dir = a.web_dir.clone();
    let c = match &a.config {
        Some(p) => ServeConfig::read(p)?,
        None => ServeConfig::default(),
    };
    let server = server_over_config(&a.server, &c);
    let tls = server.tls()?;
    let limits = server.limits()?;
    let shard_token = resolve_shard_token(&a, &c)?;
    let (max_scans, scan_queue, max_matches) = resolve_scan_bounds(&a, &c)?;
    let ca_cert = a.ca_cert.clone().or(c.ca_cert.clone());
    let store = a
        .store
        .or(c.store)
        .unwrap_or_else(|| PathBuf::from("slag-store"));
    let scene = a
        .scene
        .or(c.scene)
        .context("--scene is required (flag or `scene` in --config)")?;
    let addr = server.listen_addr(DEFAULT_EDGE_LISTEN)?;
    let text_model = required(a.text_model.or(c.clip_textual), "clip-textual")?;
    let tokenizer = required(a.tokenizer.or(c.tokenizer), "tokenizer")?;
    let ep = resolve_ep(a.ep, c.ep.as_deref())?;
    let threshold = a.threshold.or(c.threshold).unwrap_or(PAPER_THRESHOLD);
    anyhow::ensure!(
        threshold.is_finite() && (-1.0..=1.0).contains(&threshold),
        "--threshold {threshold}: use a cosine in -1..=1"
    );
    let token = resolve_token(
        server.token_file.as_deref(),
        addr,
        tls.is_some(),
        server.allow_plain_http,
    )?;
    let hnsw = a.hnsw || c.hnsw.unwrap_or(false);
    let hnsw_backend = resolve_hnsw_backend(hnsw, a.hnsw_backend.or(c.hnsw_backend))?;
    let opts = ServeOptions {
        scene,
        token,
        trusted_keys: trusted_keys(if a.trusted_key.is_empty() {
            c.trusted_key.as_slice()
        } else {
            &a.trusted_key
        })?,
        threshold,
        hnsw,
        hnsw_backend,
        request_timeout: timeout(a.request_timeout, "--request-timeout")?,
        max_scans,
        scan_queue,
        max_matches,
        limits,
        shard_token,
        tls,
        ca_cert,
    };
    let ros2 = if a.ros2 || c.ros2.unwrap_or(false) {
        Some(resolve_ros2(
            a.ros2_node.or(c.ros2_node),
            a.ros2_namespace.or(c.ros2_namespace),
            a.ros2_frame_id.or(c.ros2_frame_id),
        )?)
    } else {
        None
    };
    Ok(Resolved {
        store,
        addr,
        text_model,
        tokenizer,
        ep,
        opts,
        web_dir,
        ros2,
    })
}

/// The path of a required `--flag` (or its config key, the flag's name with `_`).
/// Errors: neither given.
fn required(v: Option<PathBuf>, flag: &str) -> anyhow::Result<PathBuf> {
    v.with_context(|| {
        format!(
            "--{flag} is required (flag or `{}` in --config)",
            flag.replace('-', "_")
        )
    })
}

/// The address to listen on: `listen` (flag or config) or `0.0.0.0:8080`.
/// Errors: not `HOST:PORT`.
/// The server's scan bounds `(max_scans, scan_queue, max_matches)`: each flag, else its
/// config key, else the server's default. Errors: `max_scans` or `max_matches` of 0.
fn resolve_scan_bounds(a: &ServeArgs, c: &ServeConfig) -> anyhow::Result<(usize, usize, usize)> {
    use slag_edge::serve::{DEFAULT_MAX_MATCHES, DEFAULT_MAX_SCANS, DEFAULT_SCAN_QUEUE};
    let max_scans = a.max_scans.or(c.max_scans).unwrap_or(DEFAULT_MAX_SCANS);
    let scan_queue = a.scan_queue.or(c.scan_queue).unwrap_or(DEFAULT_SCAN_QUEUE);
    let max_matches = a
        .max_matches
        .or(c.max_matches)
        .unwrap_or(DEFAULT_MAX_MATCHES);
    anyhow::ensure!(max_matches >= 1, "--max-matches must be at least 1");
    anyhow::ensure!(max_scans >= 1, "--max-scans must be at least 1");
    Ok((max_scans, scan_queue, max_matches))
}

/// Where the text tower runs: the flag `ep`, else the config's `ep` name (case-insensitive),
/// else the CPU. Errors: a config name that is not one of the flag's values.
fn resolve_ep(ep: Option<EpArg>, config: Option<&str>) -> anyhow::Result<EpArg> {
    match (ep, config) {
        (Some(e), _) => Ok(e),
        (None, None) => Ok(EpArg::Cpu),
        (None, Some(name)) => <EpArg as ValueEnum>::from_str(name, true)
            .map_err(|_| anyhow::anyhow!("config ep {name:?}: use cpu, cuda, tensorrt or auto")),
    }
}

/// The HNSW index's backend: the default without a name; a named one only with the index on
/// (`hnsw`) and only when this build carries it. Errors: a name without `--hnsw`, an unknown
/// name, a backend not compiled in.
fn resolve_hnsw_backend(hnsw: bool, name: Option<String>) -> anyhow::Result<HnswBackend> {
    let Some(name) = name else {
        return Ok(HnswBackend::default());
    };
    anyhow::ensure!(
        hnsw,
        "--hnsw-backend {name} without --hnsw: add --hnsw (or `hnsw = true` in --config) \
         to build the index, or drop the backend"
    );
    Ok(HnswBackend::from_name(&name)?.require()?)
}

/// The ROS 2 node's options: each given name (flag or config) or the default, the domain from
/// `ROS_DOMAIN_ID`. Errors: a domain or a name that ROS 2 refuses
/// ([`slag_edge::ros2::Ros2Options::check`]).
fn resolve_ros2(
    node_name: Option<String>,
    namespace: Option<String>,
    frame_id: Option<String>,
) -> anyhow::Result<slag_edge::ros2::Ros2Options> {
    let d = slag_edge::ros2::Ros2Options::default();
    let o = slag_edge::ros2::Ros2Options {
        node_name: node_name.unwrap_or(d.node_name),
        namespace: namespace.unwrap_or(d.namespace),
        frame_id: frame_id.unwrap_or(d.frame_id),
        domain_id: slag_edge::ros2::domain_id_from_env()?,
    };
    o.check()?;
    Ok(o)
}

fn run_serve(a: ServeArgs) -> anyhow::Result<()> {
    let r = resolve(a)?;
    let edge = EdgeStore::open_existing(&r.store)?;
    let text = text_embedder(&r.text_model, &r.tokenizer, r.ep)?;
    let scheme = if r.opts.tls.is_some() {
        "https"
    } else {
        "http"
    };
    let state = Arc::new(AppState::new(edge, text, r.opts)?.with_web_dir(r.web_dir));
    let rt = runtime()?;
    if let Some(o) = r.ros2 {
        let _guard = rt.enter();
        let node = slag_edge::ros2::start(state.clone(), o)?;
        eprintln!(
            "slag-edge: ROS 2 node {} in domain {}: prompts on {}",
            node.options.node_fqn(),
            node.options.domain_id,
            node.options.topic("prompt")
        );
    }
    rt.block_on(slag_edge::serve::serve(state, r.addr, |bound| {
        tracing::info!("listening on {scheme}://{bound}");
        eprintln!("slag-edge: listening on {scheme}://{bound}");
    }))?;
    Ok(())
}

/// `slag-edge check`: every problem of the deployment, each named in the JSON report's
/// `problems` (`"ok"` is true only when there is none), then a non-zero exit when there is one.
/// Checked: the text model loads and embeds one prompt; the store opens and the scene loads;
/// every stored shard of its manifest verifies; every tile of the last fetch's disc is stored;
/// the scene holds at least one Gaussian; the text model is of the shards' CLIP model and width.
fn run_check(a: ServeArgs) -> anyhow::Result<()> {
    let r = resolve(a)?;
    let mut problems: Vec<String> = Vec::new();
    let t = std::time::Instant::now();
    let text = text_embedder(&r.text_model, &r.tokenizer, r.ep)
        .and_then(|text| Ok((text.embed(&["a chair"])?, text)));
    let text_ms = t.elapsed().as_secs_f64() * 1e3;
    let text = match text {
        Ok((v, text)) => Some((v, text)),
        Err(e) => {
            problems.push(format!("text model: {e:#}"));
            None
        }
    };
    let mut signature = None;
    let check = EdgeStore::open_existing(&r.store).and_then(|edge| {
        let check = slag_edge::engine::StoreCheck::run(&edge, &r.opts.scene)?;
        signature = Some(edge.verify_signed(&r.opts.scene, r.opts.trusted_keys.as_ref()));
        Ok(check)
    });
    let mut report = serde_json::json!({
        "text_model": r.text_model,
        "text_load_and_first_prompt_ms": text_ms,
        "ep": format!("{:?}", r.ep),
        "store": r.store,
        "scene": r.opts.scene,
        "addr": r.addr,
        "token": r.opts.token.is_some(),
        "tls_certificate_sha256": r.opts.tls.as_ref().map(|t| t.fingerprint()),
    });
    if let Some((v, _)) = &text {
        report["text_dim"] = v.first().map_or(0, Vec::len).into();
    }
    match check {
        Err(e) => problems.push(format!("store: {e:#}")),
        Ok(mut check) => {
            problems.extend(std::mem::take(&mut check.problems));
            if let Some((v, text)) = &text {
                let text_dim = v.first().map_or(0, Vec::len);
                problems.extend(text_against_store(text.as_ref(), text_dim, &check.engine));
            }
            if let (Some(o), serde_json::Value::Object(f)) =
                (report.as_object_mut(), store_fields(&check))
            {
                o.extend(f);
            }
        }
    }
    if let Some(s) = signature {
        report["signature"] = signature_report(s, r.opts.trusted_keys.as_ref(), &mut problems);
    }
    report["ok"] = problems.is_empty().into();
    report["problems"] = problems.clone().into();
    println!("{}", serde_json::to_string_pretty(&report)?);
    anyhow::ensure!(
        problems.is_empty(),
        "{} problem(s): {}; `slag-edge fetch` again for the same disc replaces missing and \
         corrupt shards",
        problems.len(),
        problems.join("; ")
    );
    Ok(())
}

/// `check`'s problem with a text model that cannot query the stored Gaussians: another CLIP
/// model than the one that embedded them, or `text_dim` other than theirs. `None`: it can.
fn text_against_store(
    text: &dyn TextEmbedder,
    text_dim: usize,
    engine: &slag_edge::engine::Engine,
) -> Option<String> {
    let m = &engine.manifest;
    if let Err(e) = text.check_pair(&m.model) {
        return Some(format!("text model: {e}"));
    }
    (text_dim != engine.store.dim()).then(|| {
        format!(
            "the text model gives {text_dim}-d embeddings, the stored Gaussians are {}-d ({}): \
             use the CLIP text tower of that model",
            engine.store.dim(),
            m.model
        )
    })
}

/// `check`'s report fields of a loaded store: its generation, model and frames, the shards
/// loaded, absent, rejected and missing, the Gaussians and their memory, what fetch set aside.
fn store_fields(check: &slag_edge::engine::StoreCheck) -> serde_json::Value {
    let engine = &check.engine;
    let m = &engine.manifest;
    let (set_aside, set_aside_bytes) = check.set_aside;
    serde_json::json!({
        "generation": m.generation,
        "embedding_model": m.model,
        "frames": m.frames,
        "shards_loaded": engine.load.loaded_tiles.len(),
        "shards_absent": engine.load.absent_tiles,
        "shards_rejected": engine.load.rejected,
        "shards_missing": check.missing,
        "gaussians": engine.store.len(),
        "vector_memory_bytes": engine.store.memory_bytes(),
        "set_aside": set_aside,
        "set_aside_bytes": set_aside_bytes,
    })
}

/// `check`'s words on the store's signature ([`EdgeStore::verify_signed`]): plainly whether the
/// committed generation is signed, by which key, and whether `trusted` verified it and every
/// stored file's SHA-256; a failed verification, or an unsigned store where a key is trusted,
/// is added to `problems`.
fn signature_report(
    check: slag_common::Result<slag_edge::store::SignatureCheck>,
    trusted: Option<&slag_common::shards::signature::TrustedKeys>,
    problems: &mut Vec<String>,
) -> serde_json::Value {
    let (status, detail) = match &check {
        Err(e) => {
            problems.push(format!("signature: {e}"));
            ("refused", e.to_string())
        }
        Ok(c) if !c.signed => {
            let text = "unsigned: the store holds no signature of the publisher, so nothing \
                        shows that the map is the one published (fetch with --trusted-key to \
                        require one)";
            if trusted.is_some() {
                problems.push(
                    "the store is unsigned but --trusted-key is given: fetch again with it"
                        .to_string(),
                );
            }
            ("unsigned", text.to_string())
        }
        Ok(c) if !c.verified => (
            "signed, not verified",
            format!(
                "signed by key {}; not verified here: pass --trusted-key to check it",
                c.key_id.as_deref().unwrap_or("?")
            ),
        ),
        Ok(c) => (
            "verified",
            format!(
                "signed by the trusted key {}; the signature and the SHA-256 of {} stored \
                 file(s) match",
                c.key_id.as_deref().unwrap_or("?"),
                c.files_hashed
            ),
        ),
    };
    serde_json::json!({
        "status": status,
        "detail": detail,
        "key_id": check.as_ref().ok().and_then(|c| c.key_id.clone()),
        "files_hashed": check.as_ref().map_or(0, |c| c.files_hashed),
    })
}

fn run_query(a: QueryArgs) -> anyhow::Result<()> {
    // Parameters first (no store, no model needed to refuse a blank prompt), then the store
    // without creating it.
    let mut params = RawQuery {
        text: Some(a.text),
        top_k: a.top_k,
        threshold: a.threshold,
        mode: a.mode,
        bbox: a.bbox,
        index: None,
        frame: None,
        max_objects: a.max_objects,
        near: a.near,
        object_gap: a.object_gap,
        object_min_gaussians: a.object_min_gaussians,
        smooth: a.smooth,
    }
    .validate_for(PAPER_THRESHOLD, Interface::Cli)?;
    params.frame = a.frame.into();
    let edge = EdgeStore::open_existing(&a.store)?;
    let engine = slag_edge::engine::Engine::load(&edge, &a.scene, false)?;
    let text = text_embedder(&a.text_model, &a.tokenizer, a.ep)?;
    text.check_pair(&engine.manifest.model)?;
    let negatives = text.embed(&slag_edge::query::CANONICAL_NEGATIVES)?;
    let answer = engine.answer(text.as_ref(), &negatives, &params)?;
    println!("{}", serde_json::to_string_pretty(&answer)?);
    Ok(())
}

fn main() -> std::process::ExitCode {
    slag_common::cli::deprecated::note_deprecated();
    let cli = Cli::parse();
    let verbose = cli.global.verbose;
    slag_common::cli::process::init_logging(verbose);
    slag_common::cli::process::exit_code(run(cli.command), hint, verbose)
}

/// What the command line adds to a library error (`e` or an error it wraps): the flag or the
/// command that acts on it. The library names the parameter ([`slag_common::Error::Param`]), the
/// query field ([`slag_common::Error::Query`]), the limit ([`slag_common::Error::Limit`]) or the
/// server's status ([`slag_common::Error::Network`]), never a flag.
fn hint(e: &anyhow::Error) -> Option<String> {
    e.chain()
        .find_map(|c| c.downcast_ref::<slag_common::Error>().and_then(hint_for))
}

/// [`hint`] for one library error.
fn hint_for(e: &slag_common::Error) -> Option<String> {
    use slag_common::onnx::{InferenceCause, inference_cause};
    use slag_common::{Error, Resource};
    Some(match e {
        Error::Param { name, .. } => return param_hint(name),
        Error::Query { field, message } => return query_hint(field, message),
        Error::Limit {
            resource: Resource::Memory,
            ..
        } => "fetch a smaller --radius, or shards of a smaller --dtype (int8, f16) from \
              `slag-encoder partition`"
            .into(),
        Error::Limit {
            resource: Resource::DiskSpace,
            ..
        } => "free space on that file system (the store's quarantine/ folder holds what fetch \
              set aside), fetch a smaller --radius, or pass another --store"
            .into(),
        Error::Limit {
            resource: Resource::ManifestBytes,
            ..
        } => "check --from: that server's manifest is larger than any slag partition's".into(),
        Error::Network {
            status: Some(401 | 403),
            ..
        } => "pass --shard-token-file FILE or set SLAG_SHARD_TOKEN".into(),
        Error::Network {
            status: Some(404), ..
        } => "check --scene, or run fetch again if the scene was re-partitioned".into(),
        Error::Network {
            status: None,
            message,
            ..
        } if message.contains("TLS certificate") => {
            "pass --ca-cert FILE with the CA certificate that issued the shard server's \
             certificate (`ca_cert` in serve's --config for POST /fetch), and a --from whose \
             host name or IP address the certificate names"
                .into()
        }
        Error::Inference { message, .. } => match inference_cause(message) {
            InferenceCause::ProviderMissing => "use --ep cpu or --ep auto".into(),
            InferenceCause::Other => {
                "rerun with --ep cpu to tell a model fault from a GPU fault".into()
            }
            _ => return None,
        },
        Error::Internal(_) => "rerun with --verbose and report the command and its output".into(),
        Error::Untrusted { what, .. } => untrusted_hint(*what).into(),
        _ => return None,
    })
}

/// The command that fills a store, as the hints name it.
const FETCH: &str = "slag-edge fetch --from URL --scene NAME --center X,Y --radius R --store DIR";

/// [`hint_for`] of a parameter the library refused ([`slag_common::Error::Param`]'s `name`):
/// the flag (or config key) that sets it.
fn param_hint(name: &str) -> Option<String> {
    Some(match name {
        "store" => format!("run `{FETCH}` first, or pass the --store that fetch wrote"),
        "scene" => format!("run `{FETCH}` for that scene first, or pass another --scene"),
        "scene_id" => "pass --scene NAME".into(),
        "radius" => "pass --radius R, a finite number ≥ 0".into(),
        "server" => "pass --from http://HOST:PORT without user or password, and the shard \
                     server's token with --shard-token-file or SLAG_SHARD_TOKEN"
            .into(),
        "hnsw_backend" => "pass --hnsw-backend instant-distance (or `hnsw_backend = \
                           \"instant-distance\"` in --config), or use a slag-edge built with \
                           `cargo build --release -p slag-edge --features qdrant-edge`"
            .into(),
        "jobs" => "pass --jobs N with N ≥ 1".into(),
        "ros2_node" => "pass --ros2-node NAME ([A-Za-z_][A-Za-z0-9_]*)".into(),
        "ros2_namespace" => "pass --ros2-namespace /NS (or /)".into(),
        "ros2_frame_id" => "pass --ros2-frame-id map".into(),
        "ROS_DOMAIN_ID" => "set ROS_DOMAIN_ID to 0..=232, or unset it for domain 0".into(),
        "token" => "write a real token in the token file or SLAG_EDGE_TOKEN / --token, or \
                    unset the variable to run without one"
            .into(),
        "max_connections" => "pass --max-connections N (or `max_connections` in --config), \
                              or raise the open-file limit (ulimit -n, LimitNOFILE)"
            .into(),
        "listen" => "pass --listen HOST:PORT, e.g. 0.0.0.0:8080 (or `listen` in --config)".into(),
        "tls_key" => "pass the certificate's private key with --tls-key FILE (or `tls_key` in \
                      --config)"
            .into(),
        "tls_cert" => "pass the key's certificate chain with --tls-cert FILE (or `tls_cert` in \
                       --config)"
            .into(),
        "header_timeout" => "pass --header-timeout SECONDS".into(),
        "write_timeout" => "pass --write-timeout SECONDS".into(),
        "body_timeout" => "pass --body-timeout SECONDS".into(),
        "max_connections_per_ip" => "pass --max-connections-per-ip N (or \
                                     `max_connections_per_ip` in --config)"
            .into(),
        "plain_http" => "pass --tls-cert FILE --tls-key FILE (HTTPS; `tls_cert` and \
                         `tls_key` in --config), or listen on a loopback address (--listen \
                         127.0.0.1:PORT), or pass --allow-plain-http (`allow_plain_http = \
                         true`) to send the token in clear text anyway"
            .into(),
        _ => return None,
    })
}

/// [`hint_for`] of a query field the library refused ([`slag_common::Error::Query`]'s `field`
/// and `message`): the flag that sets it, or what to do instead.
fn query_hint(field: &str, message: &str) -> Option<String> {
    Some(match field {
        "text" => "pass --text chair".into(),
        "top_k" => "pass --top-k N".into(),
        "threshold" => "pass --threshold T (or none)".into(),
        "mode" => "pass --mode cosine|relevancy".into(),
        "bbox" => "pass --bbox minx,miny,minz,maxx,maxy,maxz".into(),
        "max_objects" => "pass --max-objects N".into(),
        "near" => "pass --near X,Y,Z".into(),
        "object_gap" => "pass --object-gap D".into(),
        "object_min_gaussians" => "pass --object-min-gaussians N".into(),
        "smooth" if message.contains("no geometric segments") => {
            "leave out --smooth, or partition the scene with segments and fetch again".into()
        }
        "smooth" => "pass --smooth none|segment (segment with the exact scan)".into(),
        "frame" => {
            "pass --frame scene, or partition the scene with --to-map / --to-map-points".into()
        }
        "index" if message.contains("mixture") => {
            "use index=exact: a mixture scene is scanned exactly".into()
        }
        "index" => "start serve with --hnsw for index=hnsw".into(),
        _ => return None,
    })
}

/// [`hint_for`] of a refusal by the trusted key ([`slag_common::Error::Untrusted`]).
fn untrusted_hint(what: slag_common::Untrusted) -> &'static str {
    use slag_common::Untrusted;
    match what {
        Untrusted::Unsigned => {
            "the publisher signs with `slag-shards partition --signing-key` (or `serve \
             --signing-key`); to accept an unsigned map, fetch without --trusted-key"
        }
        Untrusted::OtherKey => {
            "pass the publisher's public key with --trusted-key (`slag-shards keygen` printed \
             its key id)"
        }
        Untrusted::BadSignature | Untrusted::ContentHash => {
            "the server's copy is not what the publisher signed: fetch from the publisher's \
             server (--from) over a path you trust; the store keeps serving its last good \
             generation"
        }
        Untrusted::Unhashed => {
            "have the publisher partition again with this slag and --signing-key (it writes \
             every tile's SHA-256)"
        }
        Untrusted::Replay => {
            "the store keeps its newer generation; a publisher that re-created its shard store \
             partitions with --start-generation above the robots' generation \
             (docs/guide/security.md, \"Key rotation\")"
        }
        Untrusted::Malformed => {
            "what the server sent under the trusted key fails the shard format's checks: it was \
             changed on the way or on the server; fetch from the publisher's server over a path \
             you trust; the store keeps serving its last good generation"
        }
    }
}

fn run(command: Command) -> anyhow::Result<()> {
    match command {
        Command::Fetch(a) => run_fetch(a),
        Command::Serve(a) => run_serve(a),
        Command::Query(a) => run_query(a),
        Command::Check(a) => run_check(a),
        Command::Bench(a) => {
            println!("{}", bench::run_bench(&a)?);
            Ok(())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::{hint, hint_for};
    use slag_common::{Error, Resource};

    #[test]
    fn library_errors_get_the_flag_the_library_does_not_name() {
        let h = |e: Error| {
            assert!(
                !e.to_string().contains(" --"),
                "the library names no flag: {e}"
            );
            hint_for(&e).unwrap_or_default()
        };
        assert!(h(Error::param("store", "/no-store", "a store")).contains("slag-edge fetch"));
        assert!(h(Error::param("radius", -1.0, "≥ 0")).contains("--radius"));
        assert!(h(Error::query("text", "missing query text")).contains("--text"));
        assert!(
            h(Error::http_status("http://s/v1", 401, "HTTP 401")).contains("--shard-token-file")
        );
        assert!(
            h(Error::limit(Resource::Memory, "9e9 rows", "the allocator")).contains("--radius")
        );
        assert!(h(Error::internal("query task panicked")).contains("--verbose"));
        assert!(
            h(Error::limit(
                Resource::DiskSpace,
                "9 GB",
                "1 GB free for the store /s"
            ))
            .contains("--radius")
        );
        assert!(h(Error::limit(Resource::ManifestBytes, "40 MB", "32 MiB")).contains("--from"));
        assert_eq!(hint_for(&Error::network("http://s", "down")), None);
        let refused = slag_edge::scan::hnsw::HnswBackend::QdrantEdge.require();
        if let Err(e) = refused {
            let hint = h(e);
            assert!(hint.contains("--hnsw-backend instant-distance"), "{hint}");
            assert!(hint.contains("--features qdrant-edge"), "{hint}");
        }
        // Through context, as `main` sees it.
        let e = anyhow::Error::new(Error::param("scene", "\"grid\"", "a fetched scene"))
            .context("query");
        assert!(hint(&e).is_some_and(|h| h.contains("slag-edge fetch")));
    }
}

#[cfg(test)]
mod flag_names {
    /// Every flag name of this binary, hidden aliases included, keeps one meaning across the slag
    /// binaries, and every meaning one name ([`slag_common::flag_names`]).
    #[test]
    fn each_flag_name_has_one_meaning_across_the_binaries() {
        use clap::CommandFactory;
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        slag_common::flag_names::assert_one_meaning("slag-edge", &super::Cli::command(), &root);
    }
}
