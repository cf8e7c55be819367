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

/// Which ONNX Runtime execution provider runs a model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ExecutionProvider {
    /// The default CPU provider.
    #[default]
    Cpu,
    /// NVIDIA CUDA (only where the loaded ONNX Runtime build has it).
    ///
    /// Requesting CUDA from a runtime without it is an error ([`Error::Model`]), never a silent
    /// fallback to the CPU: a run that was meant for a GPU should not quietly take hours.
    Cuda,
}

impl std::fmt::Display for ExecutionProvider {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            ExecutionProvider::Cpu => "cpu",
            ExecutionProvider::Cuda => "cuda",
        })
    }
}

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

/// Builds a session for the ONNX model at `path`.
///
/// `intra_threads` is ONNX Runtime's intra-op thread count (0 = ONNX Runtime's default, one per
/// physical core). With [`ExecutionProvider::Cuda`] the CUDA provider must register, otherwise
/// this fails (no silent CPU fallback).
///
/// # Errors
/// [`Error::Io`] if the model file is missing, [`Error::Model`] if it cannot be parsed or CUDA is
/// unavailable, plus the errors of [`environment`].
pub fn load_session(path: &Path, ep: ExecutionProvider, intra_threads: usize) -> Result<Session> {
    if !path.is_file() {
        return Err(Error::io(
            path,
            std::io::Error::new(std::io::ErrorKind::NotFound, "ONNX model file not found"),
        ));
    }
    let env = environment()?;
    let model_err =
        |what: &str, e: &dyn std::fmt::Display| Error::model(path, format!("{what}: {e}"));
    let mut builder =
        Session::builder(env).map_err(|e| model_err("cannot create a session builder", &e))?;
    if intra_threads > 0 {
        builder = builder
            .with_intra_threads(intra_threads)
            .map_err(|e| model_err("cannot set the intra-op thread count", &e))?;
    }
    if ep == ExecutionProvider::Cuda {
        if !cuda_available()? {
            return Err(Error::model(
                path,
                "the CUDA execution provider was requested but the loaded ONNX Runtime \
                 ($ORT_DYLIB_PATH) was built without it: install the GPU build \
                 (`install-onnxruntime.sh` from the `onnxruntime-gpu` wheel) or run on the CPU",
            ));
        }
        builder = builder
            .with_execution_providers([ort::ep::CUDA::default().build().error_on_failure()])
            .map_err(|e| {
                model_err(
                    "the CUDA execution provider failed to register (CUDA/cuDNN libraries?)",
                    &e,
                )
            })?;
    }
    builder
        .commit_from_file(path)
        .map_err(|e| model_err("cannot load the ONNX model", &e))
}

/// ONNX custom metadata key holding a CLIP tower's model id (`scripts/export-models.py clip`
/// writes the same value into the image and the text tower).
pub const CLIP_PAIR_ID_KEY: &str = "slag.clip_pair_id";

/// Model id of stores made from synthetic vectors (`partition --synthetic`): no CLIP model made
/// them, so any text tower of the right width may query them.
pub const SYNTHETIC_MODEL_ID: &str = "synthetic";

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
    /// 64-bit signed integer.
    I64,
}

impl ElemType {
    fn matches(self, t: TensorElementType) -> bool {
        matches!(
            (self, t),
            (ElemType::F32, TensorElementType::Float32) | (ElemType::I64, TensorElementType::Int64)
        )
    }
    fn as_str(self) -> &'static str {
        match self {
            ElemType::F32 => "f32",
            ElemType::I64 => "i64",
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
    let found_in = list(
        session
            .inputs()
            .iter()
            .map(|o| describe_found(o.name(), o.dtype()))
            .collect(),
    );
    let found_out = list(
        session
            .outputs()
            .iter()
            .map(|o| describe_found(o.name(), o.dtype()))
            .collect(),
    );
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
