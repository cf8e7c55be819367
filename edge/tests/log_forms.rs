//! Log lines speak to the operator in Display forms: no `tracing` macro of the edge, the shard
//! server or the shared crate formats a value with `{:?}` (Rust's debug form, `Some("…")`, or an
//! error's whole payload). Typed errors implement `Display`; a string that must be quoted in a
//! log is written with `escape_debug()` inside quotes.

use std::path::{Path, PathBuf};

/// The `.rs` files under `dir`, recursively.
fn sources(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display())) {
        let path = entry.expect("a directory entry").path();
        if path.is_dir() {
            sources(&path, out);
        } else if path.extension().is_some_and(|x| x == "rs") {
            out.push(path);
        }
    }
}

/// The text of every log macro call in `src` (from its name to its closing parenthesis), with
/// the line it starts on. Parentheses inside string literals are skipped.
fn log_calls(src: &str) -> Vec<(usize, String)> {
    const MACROS: [&str; 5] = ["error!(", "warn!(", "info!(", "debug!(", "trace!("];
    let bytes = src.as_bytes();
    let mut calls = Vec::new();
    for (at, _) in src.char_indices() {
        let Some(m) = MACROS.iter().find(|m| src[at..].starts_with(**m)) else {
            continue;
        };
        // A macro of its own name (`tracing::warn!`, `warn!`), not the tail of another one.
        if at > 0 && (bytes[at - 1].is_ascii_alphanumeric() || bytes[at - 1] == b'_') {
            continue;
        }
        let (mut depth, mut in_str, mut escaped, mut end) = (0i32, false, false, src.len());
        for (i, c) in src[at + m.len() - 1..].char_indices() {
            match (in_str, escaped, c) {
                (true, true, _) => escaped = false,
                (true, false, '\\') => escaped = true,
                (true, false, '"') => in_str = false,
                (true, false, _) => {}
                (false, _, '"') => in_str = true,
                (false, _, '(') => depth += 1,
                (false, _, ')') => {
                    depth -= 1;
                    if depth == 0 {
                        end = at + m.len() - 1 + i + 1;
                        break;
                    }
                }
                _ => {}
            }
        }
        let line = src[..at].matches('\n').count() + 1;
        calls.push((line, src[at..end].to_string()));
    }
    calls
}

#[test]
fn the_scanner_finds_debug_forms_and_passes_display_forms() {
    let debug = "x; tracing::warn!(\"publishing failed: {e:?}\");\nwarn!(\"{:?} (\", a);";
    let calls = log_calls(debug);
    assert_eq!(calls.len(), 2, "{calls:?}");
    assert!(calls.iter().all(|(_, c)| c.contains(":?}")), "{calls:?}");
    let display = "tracing::info!(\"ok {e} \\\"{}\\\" (\", q.escape_debug()); eprintln!(\"{e:?}\")";
    let calls = log_calls(display);
    assert_eq!(calls.len(), 1, "{calls:?}");
    assert!(!calls[0].1.contains(":?}"), "{calls:?}");
}

#[test]
fn no_log_line_prints_a_debug_form() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let mut files = Vec::new();
    for dir in ["edge/src", "shards/src", "common/src"] {
        sources(&root.join(dir), &mut files);
    }
    assert!(
        files.len() > 20,
        "sources not found under {}",
        root.display()
    );
    let mut found = Vec::new();
    for f in &files {
        let src = std::fs::read_to_string(f).unwrap_or_else(|e| panic!("{}: {e}", f.display()));
        for (line, call) in log_calls(&src) {
            if call.contains(":?}") || call.contains(":#?}") {
                found.push(format!("{}:{line}: {call}", f.display()));
            }
        }
    }
    assert!(
        found.is_empty(),
        "log lines in Rust's debug form (write the Display form):\n{}",
        found.join("\n")
    );
}
