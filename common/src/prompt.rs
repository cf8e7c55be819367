//! Limits on text prompts, shared by every interface that takes one (`slag-encoder query`,
//! `slag-edge query`, `slag-edge serve`'s `GET`/`POST /query` and `/query.ply`), so they refuse
//! the same prompts. Each interface adds its own hint (a flag, a URL, a JSON body) to the
//! message of [`check_prompt`].

use crate::{Error, Result};

/// Longest prompt accepted, in bytes of UTF-8 (CLIP reads 77 tokens anyway; 1000 bytes is far
/// beyond them).
pub const MAX_PROMPT_BYTES: usize = 1000;

/// Why a prompt is refused (before any model runs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PromptProblem {
    /// Missing, empty or only whitespace.
    Blank,
    /// Longer than [`MAX_PROMPT_BYTES`]; holds the length in bytes.
    TooLong(usize),
}

impl std::fmt::Display for PromptProblem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PromptProblem::Blank => write!(f, "missing query text (the prompt is empty or blank)"),
            PromptProblem::TooLong(n) => write!(
                f,
                "the prompt is {n} bytes; at most {MAX_PROMPT_BYTES} are accepted (CLIP reads only \
                 its first 77 tokens)"
            ),
        }
    }
}

/// What is wrong with `text` as a prompt, if anything.
pub fn prompt_problem(text: &str) -> Option<PromptProblem> {
    if text.trim().is_empty() {
        Some(PromptProblem::Blank)
    } else if text.len() > MAX_PROMPT_BYTES {
        Some(PromptProblem::TooLong(text.len()))
    } else {
        None
    }
}

/// Checks a prompt; `hint` (e.g. `use /query?text=chair`) ends the message of a refusal. A
/// command line passes no hint and adds its flag where it reports the error.
///
/// Errors: [`Error::Query`] (field `text`) for a blank prompt or one over [`MAX_PROMPT_BYTES`].
pub fn check_prompt(text: &str, hint: &str) -> Result<()> {
    match prompt_problem(text) {
        None => Ok(()),
        Some(p) if hint.is_empty() => Err(Error::query("text", p.to_string())),
        Some(p) => Err(Error::query("text", format!("{p}: {hint}"))),
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn blank_and_long_prompts_are_refused_with_the_callers_hint() {
        for t in ["", "   ", "\t\n"] {
            let e = check_prompt(t, "use /query?text=chair").unwrap_err();
            assert!(matches!(e, Error::Query { field: "text", .. }), "{e}");
            let e = e.to_string();
            assert!(
                e.contains("missing query text") && e.ends_with("use /query?text=chair"),
                "{e}"
            );
        }
        let long = "a".repeat(MAX_PROMPT_BYTES + 1);
        assert_eq!(
            prompt_problem(&long),
            Some(PromptProblem::TooLong(MAX_PROMPT_BYTES + 1))
        );
        assert!(check_prompt(&"a".repeat(MAX_PROMPT_BYTES), "").is_ok());
        assert!(check_prompt("a chair", "x").is_ok());
    }
}
