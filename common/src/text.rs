//! CLIP text tower + BPE tokenizer: turns query prompts into L2-normalised CLIP embeddings.
//!
//! Tokenisation follows open_clip's `SimpleTokenizer` (`open_clip.tokenize`): text cleaned
//! (whitespace runs collapsed to one space, trimmed, lower-cased), CLIP BPE through the
//! `tokenizers` crate from a `tokenizer.json` (e.g. `shared/fixtures/clip/clip-tokenizer.json`),
//! wrapped as `<|startoftext|> ... <|endoftext|>` (49406 / 49407 in the OpenAI vocabulary),
//! truncated to the context length (77) with `<|endoftext|>` kept last, zero-padded.
//! open_clip's `ftfy.fix_text` / `html.unescape` steps are not reproduced (they only change
//! mojibake and HTML entities).
//!
//! The text tower is an ONNX model `input_ids i64[B,77] → one f32[B,D]` output (open_clip's
//! `encode_text` without normalisation); [`TextEncoder::encode`] L2-normalises its rows and keeps
//! a small LRU cache of recent prompts.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};

use ort::session::Session;
use ort::value::TensorRef;
use tokenizers::Tokenizer;

use crate::onnx::{self, ElemType, ExecutionProvider, TensorSpec};
use crate::{Error, Result};

/// CLIP's text context length (tokens per prompt, including start/end tokens).
pub const CONTEXT_LENGTH: usize = 77;
/// Number of prompts whose embeddings [`TextEncoder`] remembers.
pub const CACHE_CAPACITY: usize = 256;

const TEXT_INPUTS: &[TensorSpec] = &[TensorSpec::named(
    "input_ids",
    ElemType::I64,
    &[-1, CONTEXT_LENGTH as i64],
)];
const TEXT_OUTPUTS: &[TensorSpec] = &[TensorSpec::any_name(ElemType::F32, &[-1, -1])];

/// L2-normalises `v` in place (for embeddings produced by the model at `path`).
///
/// # Errors
/// [`Error::Model`] when the norm is below [`crate::similarity::MIN_NORM`] or not finite: such an embedding has no
/// direction, and dividing would put NaN into similarity scores.
pub fn l2_normalize(v: &mut [f32], path: &Path) -> Result<()> {
    crate::similarity::normalize_in_place(v)
        .map(|_| ())
        .map_err(|d| {
            Error::model(
                path,
                format!("the model returned an embedding with {d}: it cannot be normalised"),
            )
        })
}

/// CLIP BPE tokenizer producing open_clip's `input_ids` rows.
pub struct ClipTokenizer {
    inner: Tokenizer,
    path: PathBuf,
    sot: u32,
    eot: u32,
}

impl ClipTokenizer {
    /// Loads a CLIP `tokenizer.json` (it must contain `<|startoftext|>` and `<|endoftext|>`).
    ///
    /// # Errors
    /// [`Error::Io`] when missing, [`Error::Format`] when it cannot be parsed or lacks the
    /// special tokens.
    pub fn from_file(path: &Path) -> Result<Self> {
        if !path.is_file() {
            return Err(Error::io(
                path,
                std::io::Error::new(std::io::ErrorKind::NotFound, "tokenizer file not found"),
            ));
        }
        let inner = Tokenizer::from_file(path).map_err(|e| {
            Error::format(
                path,
                format!("not a tokenizers JSON file: {e}; pass clip-tokenizer.json"),
            )
        })?;
        let special = |t: &str| {
            inner.token_to_id(t).ok_or_else(|| {
                Error::format(
                    path,
                    format!("tokenizer has no {t} token: pass a CLIP tokenizer"),
                )
            })
        };
        let (sot, eot) = (special("<|startoftext|>")?, special("<|endoftext|>")?);
        Ok(ClipTokenizer {
            inner,
            path: path.to_path_buf(),
            sot,
            eot,
        })
    }

    /// open_clip token ids of `text`: `[sot, bpe..., eot, 0...]`, exactly `context` long; when too
    /// long, truncated with `eot` kept as the last token.
    ///
    /// # Errors
    /// [`Error::Param`] for `context < 2`, [`Error::Format`] if the tokenizer fails.
    pub fn tokenize(&self, text: &str, context: usize) -> Result<Vec<i64>> {
        if context < 2 {
            return Err(Error::param(
                "context",
                context,
                "a context length of at least 2",
            ));
        }
        let clean = text
            .split_whitespace()
            .collect::<Vec<_>>()
            .join(" ")
            .to_lowercase();
        let enc = self
            .inner
            .encode(clean.as_str(), false)
            .map_err(|e| Error::format(&self.path, format!("cannot tokenize {text:?}: {e}")))?;
        let mut ids = Vec::with_capacity(context);
        ids.push(i64::from(self.sot));
        ids.extend(enc.get_ids().iter().map(|&i| i64::from(i)));
        ids.push(i64::from(self.eot));
        if ids.len() > context {
            ids.truncate(context);
            ids[context - 1] = i64::from(self.eot);
        }
        ids.resize(context, 0);
        Ok(ids)
    }
}

/// CLIP text tower (ONNX) + tokenizer, with an LRU cache of the last [`CACHE_CAPACITY`] prompts.
pub struct TextEncoder {
    session: Session,
    tokenizer: ClipTokenizer,
    path: PathBuf,
    input_name: String,
    pair_id: String,
    cache: VecDeque<(String, Vec<f32>)>,
}

impl TextEncoder {
    /// Loads the text model and the tokenizer and checks the model's signature
    /// (`input_ids i64[B,77] → one f32[B,D]`).
    ///
    /// # Errors
    /// [`Error::Model`] for a missing/unloadable/wrong model (e.g. the visual tower),
    /// [`Error::Format`] for a bad tokenizer file, plus [`onnx::environment`]'s errors.
    pub fn new(model: &Path, tokenizer: &Path, ep: ExecutionProvider) -> Result<Self> {
        let tokenizer = ClipTokenizer::from_file(tokenizer)?;
        let session = onnx::load_session(model, ep, 0)?;
        onnx::check_signature(
            &session,
            model,
            "CLIP text tower",
            TEXT_INPUTS,
            TEXT_OUTPUTS,
            "pass a CLIP text model exported with input input_ids i64[B,77] and one output \
             text_embeds f32[B,D] (e.g. open_clip encode_text)",
        )?;
        let input_name = session.inputs()[0].name().to_string();
        let pair_id = onnx::clip_pair_id(&session, model);
        Ok(TextEncoder {
            session,
            tokenizer,
            path: model.to_path_buf(),
            input_name,
            pair_id,
            cache: VecDeque::new(),
        })
    }

    /// The CLIP model id of this text tower ([`onnx::clip_pair_id`]: ONNX metadata
    /// `slag.clip_pair_id`, else the file stem without `-textual`).
    pub fn pair_id(&self) -> &str {
        &self.pair_id
    }

    /// The text tower's `.onnx` path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Refuses to query embeddings made by another CLIP model (`embeddings_id` as recorded in the
    /// embeddings file or shard manifest).
    ///
    /// # Errors
    /// [`Error::ModelMismatch`] (see [`onnx::check_clip_pair`]).
    pub fn check_pair(&self, embeddings_id: &str) -> Result<()> {
        onnx::check_clip_pair(embeddings_id, &self.pair_id, &self.path)
    }

    /// The tokenizer in use.
    pub fn tokenizer(&self) -> &ClipTokenizer {
        &self.tokenizer
    }

    /// open_clip `input_ids` of each text (`[texts.len()][77]`).
    ///
    /// # Errors
    /// As [`ClipTokenizer::tokenize`].
    pub fn tokenize(&self, texts: &[&str]) -> Result<Vec<Vec<i64>>> {
        texts
            .iter()
            .map(|t| self.tokenizer.tokenize(t, CONTEXT_LENGTH))
            .collect()
    }

    /// L2-normalised embeddings of `texts` (one row of the model's width `D` per text, in order).
    /// Prompts seen recently come from the cache; the rest run in one batch.
    ///
    /// # Errors
    /// [`Error::Model`] when the run fails or a prompt's embedding has zero norm (a model that
    /// maps it to nothing: no NaN is ever returned), tokenizer errors as [`Self::tokenize`].
    pub fn encode(&mut self, texts: &[&str]) -> Result<Vec<Vec<f32>>> {
        let mut out: Vec<Option<Vec<f32>>> = texts.iter().map(|t| self.cache_get(t)).collect();
        let missing: Vec<usize> = (0..texts.len()).filter(|&i| out[i].is_none()).collect();
        if !missing.is_empty() {
            let mut ids = Vec::with_capacity(missing.len() * CONTEXT_LENGTH);
            for &i in &missing {
                ids.extend(self.tokenizer.tokenize(texts[i], CONTEXT_LENGTH)?);
            }
            let embs = self.run(&ids, missing.len())?;
            for (&i, e) in missing.iter().zip(embs) {
                self.cache_put(texts[i], &e);
                out[i] = Some(e);
            }
        }
        Ok(out.into_iter().flatten().collect())
    }

    fn run(&mut self, ids: &[i64], n: usize) -> Result<Vec<Vec<f32>>> {
        let path = &self.path;
        let input = TensorRef::from_array_view(([n, CONTEXT_LENGTH], ids))
            .map_err(|e| Error::model(path, format!("cannot build input_ids: {e}")))?;
        let outputs = self
            .session
            .run(ort::inputs![self.input_name.as_str() => input])
            .map_err(|e| Error::model(path, format!("CLIP text run failed: {e}")))?;
        let (shape, data) = outputs[0]
            .try_extract_tensor::<f32>()
            .map_err(|e| Error::model(path, format!("CLIP text output is not f32: {e}")))?;
        if shape.len() != 2 || shape[0] != n as i64 || shape[1] <= 0 {
            return Err(Error::model(
                path,
                format!(
                    "CLIP text model returned shape {shape:?} for {n} prompts, expected [{n}, D]"
                ),
            ));
        }
        let d = shape[1] as usize;
        let mut rows: Vec<Vec<f32>> = data.chunks_exact(d).map(<[f32]>::to_vec).collect();
        for r in &mut rows {
            l2_normalize(r, path)?;
        }
        Ok(rows)
    }

    fn cache_get(&mut self, text: &str) -> Option<Vec<f32>> {
        let pos = self.cache.iter().position(|(t, _)| t == text)?;
        let entry = self.cache.remove(pos)?;
        let v = entry.1.clone();
        self.cache.push_front(entry);
        Some(v)
    }

    fn cache_put(&mut self, text: &str, v: &[f32]) {
        if self.cache.iter().any(|(t, _)| t == text) {
            return;
        }
        if self.cache.len() >= CACHE_CAPACITY {
            self.cache.pop_back();
        }
        self.cache.push_front((text.to_string(), v.to_vec()));
    }

    /// Number of prompts currently cached.
    pub fn cached(&self) -> usize {
        self.cache.len()
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn zero_or_non_finite_embedding_is_a_typed_error_not_nan() {
        let mut v = vec![0f32; 4];
        assert!(matches!(
            l2_normalize(&mut v, Path::new("m.onnx")),
            Err(Error::Model { .. })
        ));
        let mut v = vec![1e-30f32; 4];
        assert!(matches!(
            l2_normalize(&mut v, Path::new("m.onnx")),
            Err(Error::Model { .. })
        ));
        let mut v = vec![f32::NAN, 1.0];
        assert!(matches!(
            l2_normalize(&mut v, Path::new("m.onnx")),
            Err(Error::Model { .. })
        ));
        let mut v = vec![3f32, 4.0];
        l2_normalize(&mut v, Path::new("m.onnx")).unwrap();
        assert_eq!(v, vec![0.6, 0.8]);
    }
}
