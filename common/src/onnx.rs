//! ONNX Runtime sessions through `ort` (2.0.0-rc.15) with `load-dynamic`.
//!
//! The runtime library is not linked: it is loaded once per process from the file named by the
//! `ORT_DYLIB_PATH` environment variable (see `../shared/tools/install-onnxruntime.sh DEST`, which
//! prints the path to export). [`environment`] performs that load and creates the single ONNX
//! Runtime environment every slag session shares; [`load_session`] builds a session on the chosen
//! [`ExecutionProvider`]; [`check_signature`] rejects a model exported for a different role (e.g. a
//! CLIP tower passed as a SAM encoder) with an [`Error::Model`] that lists what was expected and
//! what was found.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock};

use ort::environment::Environment;
use ort::ep::ExecutionProvider as _;
use ort::session::Session;
use ort::value::{TensorElementType, ValueType};

use crate::{Error, Result};

/// Which ONNX Runtime execution provider runs a model: what the user asks for (`--ep`), and, with
/// [`OnnxModel::provider`], what actually runs it (never [`ExecutionProvider::Auto`] there).
///
/// The binaries' `--ep` is `slag_common::cli::EpArg` (feature `clap`), mapped to this.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ExecutionProvider {
    /// The default CPU provider.
    #[default]
    Cpu,
    /// NVIDIA CUDA (only where the loaded ONNX Runtime build has it: PyPI's `onnxruntime-gpu`,
    /// `scripts/setup.sh --gpu`).
    ///
    /// Requesting CUDA from a runtime without it is an error ([`Error::Inference`]), never a
    /// silent fallback to the CPU: a run that was meant for a GPU should not quietly take hours.
    Cuda,
    /// NVIDIA TensorRT (where TensorRT 10 and the runtime's TensorRT provider are installed),
    /// fp16 engines cached beside the model (`<model>.trt-cache/`); nodes TensorRT cannot take
    /// fall back to CUDA. An error where TensorRT does not register.
    #[serde(rename = "tensorrt")]
    TensorRt,
    /// CUDA when the loaded runtime has it and it registers on the GPU, otherwise the CPU, with one
    /// log line per process saying why.
    Auto,
}

impl std::fmt::Display for ExecutionProvider {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            ExecutionProvider::Cpu => "cpu",
            ExecutionProvider::Cuda => "cuda",
            ExecutionProvider::TensorRt => "tensorrt",
            ExecutionProvider::Auto => "auto",
        })
    }
}

/// Where and how one ONNX model runs: the requested provider, the GPU (CUDA device ordinal, as
/// `nvidia-smi` numbers them unless `CUDA_VISIBLE_DEVICES` says otherwise), ONNX Runtime's
/// intra-op thread count (0 = its default) and a cap on the GPU memory arena of this model's
/// session.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Placement {
    /// Requested provider.
    pub ep: ExecutionProvider,
    /// CUDA device ordinal (ignored on the CPU).
    pub device: u32,
    /// Intra-op threads (0 = ONNX Runtime's default, one per physical core).
    pub intra_threads: usize,
    /// Upper bound of the session's CUDA memory arena, bytes (`gpu_mem_limit`; `None` = ONNX
    /// Runtime's default, the whole card).
    pub gpu_mem_limit: Option<usize>,
}

impl Placement {
    /// On the CPU with `intra_threads` threads.
    pub fn cpu(intra_threads: usize) -> Self {
        Placement {
            ep: ExecutionProvider::Cpu,
            device: 0,
            intra_threads,
            gpu_mem_limit: None,
        }
    }
    /// `ep` on GPU `device`.
    pub fn new(ep: ExecutionProvider, device: u32, intra_threads: usize) -> Self {
        Placement {
            ep,
            device,
            intra_threads,
            gpu_mem_limit: None,
        }
    }
}

/// Environment variable that turns on ONNX Runtime's profiler for every session: its value is a
/// path prefix, and each session writes `PREFIX-<model folder>-<model file stem>_<date>.json` (Chrome trace
/// format: one event per node run, with its provider and duration) when it ends. For finding
/// where a model's time goes; it slows the runs down.
pub const PROFILE_ENV: &str = "SLAG_ORT_PROFILE";

/// Environment variable naming the ONNX Runtime shared library (`libonnxruntime.so`).
pub const ORT_DYLIB_ENV: &str = "ORT_DYLIB_PATH";

const INSTALL_HINT: &str = "run `../shared/tools/install-onnxruntime.sh DEST` and export the path \
     it prints, e.g. `export ORT_DYLIB_PATH=DEST/libonnxruntime.so`";

static ENV: OnceLock<Environment> = OnceLock::new();
static ENV_INIT: Mutex<()> = Mutex::new(());

/// The process-wide ONNX Runtime environment, created on first use from `$ORT_DYLIB_PATH`.
///
/// # Errors
/// - [`Error::Invalid`] when `ORT_DYLIB_PATH` is unset or empty;
/// - [`Error::Model`] (with the library path) when the file does not exist, cannot be loaded, or
///   is an ONNX Runtime older than the API version `ort` needs (1.23).
///
/// A failed initialisation is not cached: fixing the variable and calling again works.
pub fn environment() -> Result<&'static Environment> {
    if let Some(env) = ENV.get() {
        return Ok(env);
    }
    let _guard = ENV_INIT.lock().unwrap_or_else(|p| p.into_inner());
    if let Some(env) = ENV.get() {
        return Ok(env);
    }
    let path = dylib_path()?;
    let builder = ort::init_from(&path).map_err(|e| {
        Error::model(
            &path,
            format!("cannot load ONNX Runtime: {e}; {INSTALL_HINT}"),
        )
    })?;
    let env = builder.with_name("slag").build().map_err(|e| {
        Error::model(
            &path,
            format!("cannot create the ONNX Runtime environment: {e}"),
        )
    })?;
    Ok(ENV.get_or_init(|| env))
}

/// The path in `$ORT_DYLIB_PATH`, checked to exist.
///
/// # Errors
/// [`Error::Invalid`] when unset, [`Error::Model`] when the file is missing.
pub fn dylib_path() -> Result<PathBuf> {
    let path = match std::env::var_os(ORT_DYLIB_ENV) {
        Some(p) if !p.is_empty() => PathBuf::from(p),
        _ => {
            return Err(Error::Invalid(format!(
                "{ORT_DYLIB_ENV} is not set: slag loads ONNX Runtime dynamically; {INSTALL_HINT}"
            )));
        }
    };
    if !path.is_file() {
        return Err(Error::model(
            &path,
            format!("{ORT_DYLIB_ENV} points to a file that does not exist; {INSTALL_HINT}"),
        ));
    }
    Ok(path)
}

/// Whether the loaded ONNX Runtime was built with the CUDA execution provider.
///
/// # Errors
/// Those of [`environment`] (the runtime must be loadable first), or [`Error::Model`] if ONNX
/// Runtime cannot list its providers.
pub fn cuda_available() -> Result<bool> {
    environment()?;
    ort::ep::CUDA::is_available().map_err(|e| {
        Error::model(
            dylib_path().unwrap_or_default(),
            format!("cannot list execution providers: {e}"),
        )
    })
}

/// Builds a session for the ONNX model at `path` on `ep` (GPU 0), with `intra_threads` intra-op
/// threads (0 = ONNX Runtime's default): [`OnnxModel::load`] without the bookkeeping.
///
/// # Errors
/// As [`OnnxModel::load`].
pub fn load_session(path: &Path, ep: ExecutionProvider, intra_threads: usize) -> Result<Session> {
    Ok(OnnxModel::load(path, &Placement::new(ep, 0, intra_threads))?.session)
}

/// `a` on a thread of its own while `b` runs on this one, and both results (a panic in `a`
/// becomes an [`Error::Internal`] naming `what`): model set-ups that need nothing of each other,
/// each seconds of session building (graph optimisation, weights to the device).
pub fn side_by_side<A: Send, B>(
    what: &str,
    a: impl FnOnce() -> Result<A> + Send,
    b: impl FnOnce() -> Result<B>,
) -> (Result<A>, Result<B>) {
    std::thread::scope(|s| {
        let a = s.spawn(a);
        let b = b();
        let a = a
            .join()
            .unwrap_or_else(|_| Err(Error::internal(format!("{what} panicked"))));
        (a, b)
    })
}

/// One loaded ONNX model with the provider that actually runs it and the GPU it sits on; its
/// errors ([`OnnxModel::error`]) name the model, the provider, the GPU and the remedy.
///
/// ONNX Runtime's `Run` needs `&mut Session` in `ort`; a model shared by several threads (one
/// session per GPU, every front worker on that GPU) is kept behind a `Mutex`, so its runs on one
/// GPU are serialised while the host work around them runs in parallel.
pub struct OnnxModel {
    session: Session,
    path: PathBuf,
    provider: ExecutionProvider,
    device: u32,
}

impl std::fmt::Debug for OnnxModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OnnxModel")
            .field("path", &self.path)
            .field("provider", &self.provider)
            .field("device", &self.device)
            .finish()
    }
}

/// Says once per process why [`ExecutionProvider::Auto`] runs on the CPU.
fn note_cpu_fallback(why: &str) {
    static SAID: OnceLock<()> = OnceLock::new();
    SAID.get_or_init(|| {
        tracing::warn!("execution provider auto: SAM and CLIP run on the CPU: {why}")
    });
}

impl OnnxModel {
    /// Loads the model at `path` where `placement` says.
    ///
    /// - [`ExecutionProvider::Cpu`]: ONNX Runtime's CPU provider.
    /// - [`ExecutionProvider::Cuda`] / [`ExecutionProvider::TensorRt`]: that provider must
    ///   register and the session must be created on GPU `placement.device`, else an error
    ///   (no silent CPU fallback). The CUDA arena is capped at `placement.gpu_mem_limit` and
    ///   grows by what is requested (`kSameAsRequested`), so sessions sharing a GPU do not
    ///   reserve it all.
    /// - [`ExecutionProvider::Auto`]: CUDA where the runtime has it and the session can be made
    ///   on the GPU, otherwise the CPU, with one warning per process saying why.
    ///
    /// Models whose weights are ONNX external data (> 2 GB, e.g. SAM ViT-H) load from their
    /// folder: keep the data file beside the `.onnx`.
    ///
    /// # Errors
    /// [`Error::Io`] if the model file is missing; [`Error::Inference`] when the provider is not in
    /// the loaded runtime, does not register, or the GPU session cannot be made (out of memory,
    /// missing CUDA library, driver/runtime mismatch, no such GPU), with the remedy;
    /// [`Error::Model`] if the file cannot be parsed; plus the errors of [`environment`].
    pub fn load(path: &Path, placement: &Placement) -> Result<Self> {
        if !path.is_file() {
            return Err(Error::io(
                path,
                std::io::Error::new(std::io::ErrorKind::NotFound, "ONNX model file not found"),
            ));
        }
        environment()?;
        match placement.ep {
            ExecutionProvider::Cpu => Self::load_on(path, placement, ExecutionProvider::Cpu),
            ExecutionProvider::Cuda | ExecutionProvider::TensorRt => {
                Self::load_on(path, placement, placement.ep)
            }
            ExecutionProvider::Auto => {
                if !cuda_available()? {
                    note_cpu_fallback(&format!(
                        "the ONNX Runtime at {} has no CUDA provider (a CPU build); \
                         `bash scripts/setup.sh --gpu` installs the GPU build",
                        dylib_path().unwrap_or_default().display()
                    ));
                    return Self::load_on(path, placement, ExecutionProvider::Cpu);
                }
                match Self::load_on(path, placement, ExecutionProvider::Cuda) {
                    Ok(m) => Ok(m),
                    Err(Error::Inference { message, .. }) => {
                        note_cpu_fallback(&format!(
                            "the CUDA provider could not run on GPU {}: {message}",
                            placement.device
                        ));
                        Self::load_on(path, placement, ExecutionProvider::Cpu)
                    }
                    Err(e) => Err(e),
                }
            }
        }
    }

    fn load_on(path: &Path, placement: &Placement, ep: ExecutionProvider) -> Result<Self> {
        let env = environment()?;
        let device = placement.device;
        let inference_err = |message: String| inference_error(path, ep, device, &message);
        let model_err =
            |what: &str, e: &dyn std::fmt::Display| Error::model(path, format!("{what}: {e}"));
        let mut builder =
            Session::builder(env).map_err(|e| model_err("cannot create a session builder", &e))?;
        if placement.intra_threads > 0 {
            builder = builder
                .with_intra_threads(placement.intra_threads)
                .map_err(|e| model_err("cannot set the intra-op thread count", &e))?;
        }
        if let Some(prefix) = std::env::var_os(PROFILE_ENV).filter(|p| !p.is_empty()) {
            builder = builder
                .with_profiling(profile_prefix(path, PathBuf::from(prefix)))
                .map_err(|e| model_err("cannot turn on ONNX Runtime's profiler", &e))?;
        }
        if matches!(ep, ExecutionProvider::Cuda | ExecutionProvider::TensorRt) {
            builder = builder
                .with_execution_providers(gpu_providers(path, placement, ep)?)
                .map_err(|e| inference_err(format!("the provider did not register: {e}")))?;
        }
        let session = builder.commit_from_file(path).map_err(|e| {
            if ep == ExecutionProvider::Cpu {
                model_err("cannot load the ONNX model", &e)
            } else {
                inference_err(format!("cannot create the session: {e}"))
            }
        })?;
        Ok(OnnxModel {
            session,
            path: path.to_path_buf(),
            provider: ep,
            device,
        })
    }

    /// The session (inputs, outputs, metadata).
    pub fn session(&self) -> &Session {
        &self.session
    }

    /// The session, to run it.
    pub fn session_mut(&mut self) -> &mut Session {
        &mut self.session
    }

    /// The `.onnx` file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The provider that runs the model (CPU, CUDA or TensorRT; never `Auto`).
    pub fn provider(&self) -> ExecutionProvider {
        self.provider
    }

    /// Where it runs, as the report and errors write it: `cpu`, `cuda:0`, `tensorrt:1`.
    pub fn device_label(&self) -> String {
        device_label(self.provider, self.device)
    }

    /// The CUDA device memory of this model's GPU, for outputs kept on the GPU (IO binding);
    /// `None` on the CPU.
    ///
    /// # Errors
    /// [`Error::Inference`] if ONNX Runtime cannot describe the memory.
    pub fn device_memory(&self) -> Result<Option<ort::memory::MemoryInfo<'static>>> {
        if self.provider == ExecutionProvider::Cpu {
            return Ok(None);
        }
        ort::memory::MemoryInfo::new(
            ort::memory::AllocationDevice::CUDA,
            self.device as i32,
            ort::memory::AllocatorType::Device,
            ort::memory::MemoryType::Default,
        )
        .map(Some)
        .map_err(|e| self.error("cannot describe the GPU memory", &e))
    }

    /// A typed error of this model: `what` failed with `e` (e.g. `"encoder run"`), with the
    /// remedy [`remedy`] finds for the message.
    pub fn error(&self, what: &str, e: &dyn std::fmt::Display) -> Error {
        self.errors().error(what, e)
    }

    /// What [`OnnxModel::error`] needs, detached from the session (for use while a run borrows
    /// it).
    pub fn errors(&self) -> ModelErrors {
        ModelErrors {
            path: self.path.clone(),
            provider: self.provider,
            device: self.device,
        }
    }
}

/// Builds the typed errors of one model ([`OnnxModel::errors`]).
#[derive(Debug, Clone)]
pub struct ModelErrors {
    path: PathBuf,
    provider: ExecutionProvider,
    device: u32,
}

impl ModelErrors {
    /// [`Error::Inference`]: `what` failed with `e`, with the remedy for the message.
    pub fn error(&self, what: &str, e: &dyn std::fmt::Display) -> Error {
        inference_error(
            &self.path,
            self.provider,
            self.device,
            &format!("{what}: {e}"),
        )
    }
    /// [`Error::Model`]: the model answered with something unexpected (shape, type).
    pub fn unexpected(&self, message: impl Into<String>) -> Error {
        Error::model(&self.path, message)
    }
}

/// `cpu`, `cuda:N`, `tensorrt:N`.
pub fn device_label(ep: ExecutionProvider, device: u32) -> String {
    match ep {
        ExecutionProvider::Cpu => "cpu".into(),
        other => format!("{other}:{device}"),
    }
}

/// The profiler's file prefix for the model at `path`: `prefix` with `-FOLDER-STEM` of the
/// model appended. ONNX Runtime appends the date and `.json`; the model's folder and file stem
/// keep the traces of several models apart.
fn profile_prefix(path: &Path, mut prefix: PathBuf) -> PathBuf {
    let stem = path.file_stem().unwrap_or_default().to_string_lossy();
    let folder = path
        .parent()
        .and_then(Path::file_name)
        .unwrap_or_default()
        .to_string_lossy();
    prefix.as_mut_os_string().push(format!("-{folder}-{stem}"));
    prefix
}

/// The execution providers of a GPU session on `placement.device`, in ONNX Runtime's order of
/// preference: with [`ExecutionProvider::TensorRt`], TensorRT (fp16 engines and timing cached
/// in `<model>.trt-cache`) before CUDA; CUDA alone otherwise. CUDA's arena grows by what is
/// requested, within `placement.gpu_mem_limit`.
///
/// Errors: [`Error::Inference`] when the loaded ONNX Runtime lacks the provider or cannot list
/// its providers.
fn gpu_providers(
    path: &Path,
    placement: &Placement,
    ep: ExecutionProvider,
) -> Result<Vec<ort::ep::ExecutionProviderDispatch>> {
    let device = placement.device;
    let inference_err = |message: String| inference_error(path, ep, device, &message);
    let available = match ep {
        ExecutionProvider::TensorRt => ort::ep::TensorRT::is_available(),
        _ => ort::ep::CUDA::is_available(),
    }
    .map_err(|e| inference_err(format!("cannot list execution providers: {e}")))?;
    if !available {
        return Err(inference_err(format!(
            "the {ep} execution provider was requested but the ONNX Runtime at {} was \
             built without it",
            dylib_path().unwrap_or_default().display()
        )));
    }
    let mut cuda = ort::ep::CUDA::default()
        .with_device_id(device as i32)
        .with_arena_extend_strategy(ort::ep::ArenaExtendStrategy::SameAsRequested);
    if let Some(limit) = placement.gpu_mem_limit {
        cuda = cuda.with_memory_limit(limit);
    }
    let mut eps = Vec::new();
    if ep == ExecutionProvider::TensorRt {
        let cache = path.with_extension("trt-cache");
        eps.push(
            ort::ep::TensorRT::default()
                .with_device_id(device as i32)
                .with_fp16(true)
                .with_engine_cache(true)
                .with_engine_cache_path(cache.display())
                .with_timing_cache(true)
                .with_timing_cache_path(cache.display())
                .build()
                .error_on_failure(),
        );
    }
    eps.push(cuda.build().error_on_failure());
    Ok(eps)
}

fn inference_error(path: &Path, ep: ExecutionProvider, device: u32, message: &str) -> Error {
    Error::Inference {
        model: path.to_path_buf(),
        provider: ep.to_string(),
        device: device_label(ep, device),
        message: message.to_string(),
        remedy: remedy(ep, message).to_string(),
    }
}

/// What kind of ONNX Runtime / CUDA failure a message ([`Error::Inference`]'s `message`)
/// reports: what [`remedy`] is chosen by, and what a command line maps to its flags.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum InferenceCause {
    /// The GPU ran out of memory.
    OutOfMemory,
    /// A CUDA / cuDNN / TensorRT library could not be loaded.
    MissingLibrary,
    /// The ONNX Runtime GPU build does not match the driver.
    DriverMismatch,
    /// The GPU asked for does not exist.
    NoSuchDevice,
    /// The runtime lacks the provider, or it did not register.
    ProviderMissing,
    /// Anything else.
    Other,
}

/// Classifies an ONNX Runtime / CUDA failure message ([`InferenceCause`]).
pub fn inference_cause(message: &str) -> InferenceCause {
    let m = message.to_ascii_lowercase();
    let any = |keys: &[&str]| keys.iter().any(|k| m.contains(k));
    if any(&[
        "out of memory",
        "alloc_failed",
        "resource allocation failed",
        "cudaerrormemoryallocation",
        "failed to allocate memory",
        "bfcarena",
    ]) {
        InferenceCause::OutOfMemory
    } else if any(&[
        "cannot open shared object",
        "error while loading shared libraries",
        "failed to load library",
        "loadlibrary",
        "libcudnn",
        "libcublas",
        "libcudart",
        "libnvinfer",
    ]) {
        InferenceCause::MissingLibrary
    } else if any(&[
        "insufficient driver",
        "driver version is insufficient",
        "cudaerrorinsufficientdriver",
        "version mismatch",
        "api version",
        "not compatible",
        "unsupported ptx",
    ]) {
        InferenceCause::DriverMismatch
    } else if any(&[
        "invalid device ordinal",
        "no cuda-capable device",
        "cudaerrornodevice",
        "cuda_error_no_device",
    ]) {
        InferenceCause::NoSuchDevice
    } else if m.contains("built without it") || m.contains("did not register") {
        InferenceCause::ProviderMissing
    } else {
        InferenceCause::Other
    }
}

/// What the user should do about an ONNX Runtime / CUDA failure message (the `remedy` of
/// [`Error::Inference`], by [`inference_cause`]): out of GPU memory, a missing CUDA library, a
/// driver or runtime version mismatch, a GPU that does not exist, a provider the runtime lacks,
/// or anything else. It names the library's parameters (a command line adds its flags).
pub fn remedy(ep: ExecutionProvider, message: &str) -> &'static str {
    match inference_cause(message) {
        InferenceCause::OutOfMemory => {
            "the GPU ran out of memory: lower the CLIP batch or SAM's points_per_batch, cap each \
             model's arena (gpu_mem_limit), or use a GPU with more free memory (nvidia-smi shows \
             what else holds it)"
        }
        InferenceCause::MissingLibrary => {
            "a CUDA library is missing: `bash scripts/setup.sh --gpu` installs onnxruntime-gpu \
             and its CUDA 13 runtime, cuBLAS and cuDNN 9 (or put yours on LD_LIBRARY_PATH); \
             TensorRT needs libnvinfer 10 as well"
        }
        InferenceCause::DriverMismatch => {
            "the ONNX Runtime GPU build does not match the driver: onnxruntime-gpu 1.31 is built \
             for CUDA 13 (driver >= 580); on a CUDA 12 machine install a CUDA 12 build \
             (ORT_GPU_VERSION=1.22.0 bash scripts/setup.sh --gpu)"
        }
        InferenceCause::NoSuchDevice => {
            "no such GPU: check nvidia-smi and CUDA_VISIBLE_DEVICES, and ask for at most that \
             many GPUs"
        }
        InferenceCause::ProviderMissing => match ep {
            ExecutionProvider::TensorRt => {
                "install TensorRT 10 and an onnxruntime-gpu with its TensorRT provider, or run on \
                 the cuda execution provider"
            }
            _ => {
                "install the GPU build of ONNX Runtime (`bash scripts/setup.sh --gpu`), or run \
                 on the cpu or auto execution provider"
            }
        },
        InferenceCause::Other => {
            "run on the cpu execution provider to tell a model fault from a GPU fault, and report \
             this message"
        }
    }
}

/// ONNX custom metadata key holding a CLIP tower's model id (`scripts/export-models.py clip`
/// writes the same value into the image and the text tower).
pub const CLIP_PAIR_ID_KEY: &str = "slag.clip_pair_id";

pub use crate::shards::synthetic::SYNTHETIC_MODEL_ID;

const TOWER_SUFFIXES: [&str; 4] = ["-visual", "-textual", "_visual", "_textual"];

/// The CLIP model id `id` names, with a trailing `-visual` / `-textual` / `_visual` / `_textual`
/// removed: `color-clip-visual` → `color-clip`. Ids recorded by older encoders (the visual
/// file stem) thus pair with their text tower.
pub fn clip_base_id(id: &str) -> &str {
    let id = id.trim();
    TOWER_SUFFIXES
        .iter()
        .find_map(|s| id.strip_suffix(s).filter(|b| !b.is_empty()))
        .unwrap_or(id)
}

/// The fallback model id of the CLIP tower at `path` (no `slag.clip_pair_id` metadata): its file
/// stem without the tower suffix (`tiny-clip-textual.onnx` → `tiny-clip`).
pub fn clip_pair_id_from_path(path: &Path) -> String {
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    clip_base_id(&stem).to_string()
}

/// The model id of the CLIP tower loaded in `session` from `path`: the ONNX custom metadata
/// [`CLIP_PAIR_ID_KEY`] when present and non-empty, otherwise [`clip_pair_id_from_path`].
/// The image tower's id is recorded with the embeddings; the text side compares its own with
/// [`check_clip_pair`].
pub fn clip_pair_id(session: &Session, path: &Path) -> String {
    session
        .metadata()
        .ok()
        .and_then(|m| m.custom(CLIP_PAIR_ID_KEY))
        .map(|v| v.trim().to_string())
        .filter(|v| !v.is_empty())
        .unwrap_or_else(|| clip_pair_id_from_path(path))
}

/// Refuses a text tower (id `text_id`, file `text_path`) that does not belong to the image tower
/// that made the embeddings (id `embeddings_id`, as recorded in the embeddings file or shard
/// manifest). Both ids are compared after [`clip_base_id`]. Embeddings without a model id or of
/// synthetic vectors ([`SYNTHETIC_MODEL_ID`]) pair with any text tower.
///
/// # Errors
/// [`Error::ModelMismatch`] naming both ids and the text tower to pass instead.
pub fn check_clip_pair(embeddings_id: &str, text_id: &str, text_path: &Path) -> Result<()> {
    let emb = clip_base_id(embeddings_id);
    if emb.is_empty() || emb == SYNTHETIC_MODEL_ID || emb == clip_base_id(text_id) {
        return Ok(());
    }
    Err(Error::ModelMismatch {
        text_path: text_path.to_path_buf(),
        text_model: clip_base_id(text_id).to_string(),
        embeddings_model: emb.to_string(),
    })
}

/// Element type of a tensor in a model signature.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ElemType {
    /// 32-bit float.
    F32,
    /// 16-bit (IEEE half) float.
    F16,
    /// 64-bit signed integer.
    I64,
    /// Unsigned byte (e.g. pixels 0..=255).
    U8,
}

impl ElemType {
    fn matches(self, t: TensorElementType) -> bool {
        matches!(
            (self, t),
            (ElemType::F32, TensorElementType::Float32)
                | (ElemType::F16, TensorElementType::Float16)
                | (ElemType::I64, TensorElementType::Int64)
                | (ElemType::U8, TensorElementType::Uint8)
        )
    }
    fn as_str(self) -> &'static str {
        match self {
            ElemType::F32 => "f32",
            ElemType::F16 => "f16",
            ElemType::I64 => "i64",
            ElemType::U8 => "u8",
        }
    }
}

/// One expected input or output of a model.
#[derive(Debug, Clone, Copy)]
pub struct TensorSpec {
    /// Required name, or `None` to accept any name (e.g. a single embedding output).
    pub name: Option<&'static str>,
    /// Element type.
    pub dtype: ElemType,
    /// Expected dimensions; `-1` accepts any size (and a dynamic dimension always matches).
    pub dims: &'static [i64],
}

impl TensorSpec {
    /// A named tensor spec.
    pub const fn named(name: &'static str, dtype: ElemType, dims: &'static [i64]) -> Self {
        TensorSpec {
            name: Some(name),
            dtype,
            dims,
        }
    }
    /// A spec that accepts any tensor name.
    pub const fn any_name(dtype: ElemType, dims: &'static [i64]) -> Self {
        TensorSpec {
            name: None,
            dtype,
            dims,
        }
    }

    fn describe(&self) -> String {
        format!(
            "{}: {}{}",
            self.name.unwrap_or("*"),
            self.dtype.as_str(),
            dims_str(self.dims)
        )
    }

    fn matches(&self, name: &str, ty: &ValueType) -> bool {
        if self.name.is_some_and(|n| n != name) {
            return false;
        }
        let (Some(t), Some(shape)) = (ty.tensor_type(), ty.tensor_shape()) else {
            return false;
        };
        self.dtype.matches(t)
            && shape.len() == self.dims.len()
            && shape
                .iter()
                .zip(self.dims)
                .all(|(&a, &e)| e < 0 || a < 0 || a == e)
    }
}

fn dims_str(dims: &[i64]) -> String {
    let mut s = String::from("[");
    for (i, d) in dims.iter().enumerate() {
        if i > 0 {
            s.push(',');
        }
        if *d < 0 {
            s.push('?');
        } else {
            let _ = write!(s, "{d}");
        }
    }
    s.push(']');
    s
}

fn describe_found(name: &str, ty: &ValueType) -> String {
    match (ty.tensor_type(), ty.tensor_shape()) {
        (Some(t), Some(shape)) => {
            let t = match t {
                TensorElementType::Float32 => "f32".to_string(),
                TensorElementType::Int64 => "i64".to_string(),
                TensorElementType::Float16 => "f16".to_string(),
                TensorElementType::Uint8 => "u8".to_string(),
                other => format!("{other:?}"),
            };
            format!("{name}: {t}{}", dims_str(shape))
        }
        _ => format!("{name}: (not a tensor)"),
    }
}

/// Checks that `session`'s inputs and outputs are exactly `inputs` and `outputs` (same count, each
/// spec matched in order: name where given, element type, rank, fixed dimensions).
///
/// `role` names what the model was passed as (e.g. `"SAM image encoder"`), `hint` says what to pass
/// instead (e.g. `"pass a SAM encoder exported with pixel_values f32[1,3,1024,1024]"`).
///
/// # Errors
/// [`Error::Model`] `"<role>: expected inputs [...] -> outputs [...], found inputs [...] -> outputs
/// [...]; <hint>"`.
pub fn check_signature(
    session: &Session,
    path: &Path,
    role: &str,
    inputs: &[TensorSpec],
    outputs: &[TensorSpec],
    hint: &str,
) -> Result<()> {
    let ok = |specs: &[TensorSpec], found: &[ort::value::Outlet]| {
        specs.len() == found.len()
            && specs
                .iter()
                .zip(found)
                .all(|(s, o)| s.matches(o.name(), o.dtype()))
    };
    if ok(inputs, session.inputs()) && ok(outputs, session.outputs()) {
        return Ok(());
    }
    let list = |v: Vec<String>| format!("[{}]", v.join(", "));
    let expected_in = list(inputs.iter().map(TensorSpec::describe).collect());
    let expected_out = list(outputs.iter().map(TensorSpec::describe).collect());
    let found = |outlets: &[ort::value::Outlet]| {
        list(
            outlets
                .iter()
                .map(|o| describe_found(o.name(), o.dtype()))
                .collect(),
        )
    };
    let (found_in, found_out) = (found(session.inputs()), found(session.outputs()));
    Err(Error::model(
        path,
        format!(
            "wrong model for the {role}: expected inputs {expected_in} -> outputs {expected_out}, \
             found inputs {found_in} -> outputs {found_out}; {hint}"
        ),
    ))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn failures_get_the_remedy_for_their_cause() {
        let cases = [
            (
                "CUBLAS failure 3: CUBLAS_STATUS_ALLOC_FAILED ; GPU=0",
                "ran out of memory",
            ),
            (
                "Failed to allocate memory for requested buffer of size 1073741824",
                "ran out of memory",
            ),
            (
                "libcudnn.so.9: cannot open shared object file: No such file or directory",
                "CUDA library is missing",
            ),
            (
                "CUDA failure 35: CUDA driver version is insufficient for CUDA runtime version",
                "does not match the driver",
            ),
            ("CUDA failure 101: invalid device ordinal", "no such GPU"),
            ("something else entirely", "cpu execution provider"),
        ];
        for (message, want) in cases {
            let got = remedy(ExecutionProvider::Cuda, message);
            assert!(got.contains(want), "{message:?} -> {got:?}");
            // Install commands stay; a binary's flags are the command line's to add.
            let flags = ["--ep", "--gpus", "--clip-batch", "--sam-", "--gpu-mem"];
            assert!(
                !flags.iter().any(|f| got.contains(f)),
                "a library remedy names no flag: {got}"
            );
        }
        assert_eq!(
            inference_cause("CUDA failure 2: out of memory"),
            InferenceCause::OutOfMemory
        );
        assert_eq!(inference_cause("nothing known"), InferenceCause::Other);
        assert!(
            remedy(ExecutionProvider::TensorRt, "was built without it").contains("TensorRT 10")
        );
        let e = inference_error(
            Path::new("m.onnx"),
            ExecutionProvider::Cuda,
            3,
            "decoder run: out of memory",
        );
        let text = e.to_string();
        assert!(
            text.starts_with("model m.onnx on cuda:3: decoder run: out of memory; the GPU ran out"),
            "{text}"
        );
        assert_eq!(device_label(ExecutionProvider::Cpu, 3), "cpu");
    }

    #[test]
    fn clip_ids_pair_by_base_name() {
        assert_eq!(clip_base_id("color-clip-visual"), "color-clip");
        assert_eq!(clip_base_id("color-clip-textual"), "color-clip");
        assert_eq!(clip_base_id("vitb16_visual"), "vitb16");
        assert_eq!(clip_base_id("ViT-B-16"), "ViT-B-16");
        assert_eq!(clip_base_id("-visual"), "-visual");
        assert_eq!(
            clip_pair_id_from_path(Path::new("/x/tiny-clip-textual.onnx")),
            "tiny-clip"
        );
        assert_eq!(
            clip_pair_id_from_path(Path::new("color-clip-visual.onnx")),
            "color-clip"
        );
        // Old stores recorded the visual file stem; new ones the pair id: both pair.
        let t = Path::new("color-clip-textual.onnx");
        check_clip_pair("color-clip-visual", "color-clip", t).unwrap();
        check_clip_pair("color-clip", "color-clip", t).unwrap();
        check_clip_pair("color-clip", "color-clip-textual", t).unwrap();
        // Synthetic or unlabelled embeddings take any text tower.
        check_clip_pair("synthetic", "tiny-clip", t).unwrap();
        check_clip_pair("", "tiny-clip", t).unwrap();
    }

    #[test]
    fn mismatched_text_tower_is_refused_naming_both_ids() {
        let t = Path::new("/m/tiny-clip-textual.onnx");
        let e = check_clip_pair("color-clip-visual", "tiny-clip", t).unwrap_err();
        match &e {
            Error::ModelMismatch {
                text_path,
                text_model,
                embeddings_model,
            } => {
                assert_eq!(text_path, t);
                assert_eq!(text_model, "tiny-clip");
                assert_eq!(embeddings_model, "color-clip");
            }
            other => panic!("expected ModelMismatch, got {other:?}"),
        }
        let msg = e.to_string();
        assert!(
            msg.contains("`tiny-clip`")
                && msg.contains("`color-clip`")
                && msg.contains("color-clip-textual.onnx")
                && msg.contains(CLIP_PAIR_ID_KEY),
            "{msg}"
        );
    }

    #[test]
    fn dims_are_printed_with_dynamic_marks() {
        assert_eq!(dims_str(&[-1, 3, 224, 224]), "[?,3,224,224]");
        assert_eq!(dims_str(&[]), "[]");
    }

    #[test]
    fn spec_matching_respects_name_type_and_dims() {
        let ty = ValueType::Tensor {
            ty: TensorElementType::Float32,
            shape: ort::value::Shape::new([-1, 3, 224, 224]),
            dimension_symbols: ort::value::SymbolicDimensions::new([
                "batch".to_string(),
                String::new(),
                String::new(),
                String::new(),
            ]),
        };
        let s = TensorSpec::named("pixel_values", ElemType::F32, &[-1, 3, 224, 224]);
        assert!(s.matches("pixel_values", &ty));
        assert!(!s.matches("input_ids", &ty));
        assert!(
            !TensorSpec::named("pixel_values", ElemType::I64, &[-1, 3, 224, 224])
                .matches("pixel_values", &ty)
        );
        assert!(
            !TensorSpec::named("pixel_values", ElemType::F32, &[1, 3, 1024, 1024])
                .matches("pixel_values", &ty)
        );
        assert!(TensorSpec::any_name(ElemType::F32, &[2, 3, 224, 224]).matches("x", &ty));
        assert!(!TensorSpec::any_name(ElemType::F32, &[-1, 512]).matches("x", &ty));
    }
}
