//! No Rust source file of the workspace is longer than [`MAX_LINES`] lines: a file past it holds
//! more than one thing, and is split into modules named for what they hold (each with a `//!`
//! docstring saying what it holds and why), so that the layout of the files shows the plan.
//!
//! Every `.rs` file under the workspace root counts (libraries, binaries, tests, benches,
//! examples, fuzz targets, scripts), except build outputs and vendored or hidden folders
//! ([`SKIPPED_DIRS`], and any folder whose name starts with `.`).

#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};

/// The most lines a `.rs` file may have.
const MAX_LINES: usize = 1_200;

/// Folders never searched: build outputs (`target`, `out`) and vendored web code.
const SKIPPED_DIRS: &[&str] = &["target", "out", "node_modules", "vendor"];

/// Every `.rs` file under `dir`, skipping [`SKIPPED_DIRS`] and hidden folders, sorted.
fn rust_files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).unwrap() {
            let entry = entry.unwrap();
            let path = entry.path();
            let name = entry.file_name().to_string_lossy().into_owned();
            let kind = entry.file_type().unwrap();
            if kind.is_dir() {
                if !name.starts_with('.') && !SKIPPED_DIRS.contains(&name.as_str()) {
                    stack.push(path);
                }
            } else if kind.is_file() && name.ends_with(".rs") {
                out.push(path);
            }
        }
    }
    out.sort();
    out
}

/// The files under `dir` longer than `max` lines, each as `path (N lines)` relative to `dir`,
/// longest first.
fn too_long(dir: &Path, max: usize) -> Vec<String> {
    let mut found: Vec<(usize, String)> = rust_files(dir)
        .into_iter()
        .filter_map(|path| {
            let text = std::fs::read_to_string(&path).unwrap();
            let lines = text.lines().count();
            let shown = path
                .strip_prefix(dir)
                .unwrap_or(&path)
                .display()
                .to_string();
            (lines > max).then_some((lines, shown))
        })
        .collect();
    found.sort_by(|a, b| b.0.cmp(&a.0).then_with(|| a.1.cmp(&b.1)));
    found
        .into_iter()
        .map(|(lines, path)| format!("{path} ({lines} lines)"))
        .collect()
}

#[test]
fn no_rust_file_is_longer_than_1200_lines() {
    let workspace = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let workspace = workspace.canonicalize().unwrap();
    let files = rust_files(&workspace);
    assert!(
        files.len() >= 100,
        "only {} .rs files found under {}",
        files.len(),
        workspace.display()
    );
    let long = too_long(&workspace, MAX_LINES);
    assert!(
        long.is_empty(),
        "{} .rs file(s) longer than {MAX_LINES} lines; split each into modules named for what \
         they hold, each with a `//!` docstring:\n{}",
        long.len(),
        long.join("\n")
    );
}

#[test]
fn a_file_one_line_past_the_limit_is_named_and_build_folders_are_not_searched() {
    let dir = std::env::temp_dir().join(format!("slag-file-sizes-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let write = |rel: &str, lines: usize| {
        let path = dir.join(rel);
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(&path, "fn f() {}\n".repeat(lines)).unwrap();
    };
    write("src/at_limit.rs", 5);
    write("src/deep/past_limit.rs", 6);
    write("src/longest.rs", 9);
    write("notes.txt", 50);
    write("target/debug/build.rs", 50);
    write(".hidden/x.rs", 50);
    let long = too_long(&dir, 5);
    std::fs::remove_dir_all(&dir).unwrap();
    assert_eq!(
        long,
        vec![
            "src/longest.rs (9 lines)".to_string(),
            "src/deep/past_limit.rs (6 lines)".to_string(),
        ]
    );
}
