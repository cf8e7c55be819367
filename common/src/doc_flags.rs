//! Keeps the manual honest: every command line of a slag binary that the documentation shows
//! (`slag-encoder encode --every 4`, `slag-edge serve --hnsw`, …) names a subcommand and flags
//! the binary has.
//!
//! Each binary's crate runs [`check`] ([`check_binary`]) in an integration test against its own built binary, over
//! `README.md` and every page of `docs/guide/` ([`manual_pages`]), so a page added later is
//! covered without touching the test. Only code is read: fenced code blocks (with `\`
//! continuation lines joined) and inline code spans; prose may name a flag in passing.

use std::collections::{BTreeSet, HashMap};
use std::path::{Path, PathBuf};

/// One command line of a binary as a page shows it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ShownCommand {
    /// `file:line` where the command starts.
    pub place: String,
    /// The subcommand (`None`: only top-level options, as in `slag-edge --verbose`).
    pub subcommand: Option<String>,
    /// Every `--flag` on the line, without its value.
    pub flags: Vec<String>,
}

/// `README.md` and every `*.md` under `docs/guide/` of the repository at `root`, sorted.
pub fn manual_pages(root: &Path) -> Vec<PathBuf> {
    let mut pages = vec![root.join("README.md")];
    if let Ok(dir) = std::fs::read_dir(root.join("docs").join("guide")) {
        let mut guide: Vec<PathBuf> = dir
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == "md"))
            .collect();
        guide.sort();
        pages.extend(guide);
    }
    pages
}

/// The command lines of `binary` (e.g. `slag-edge`) in one markdown text; `file` names it in
/// [`ShownCommand::place`].
pub fn shown_commands(binary: &str, file: &str, markdown: &str) -> Vec<ShownCommand> {
    let mut out = Vec::new();
    let mut fence = false;
    let mut joined = String::new();
    let mut joined_from = 0;
    // Prose is read a paragraph at a time: an inline code span may wrap onto the next line.
    let mut prose = String::new();
    let mut prose_from = 0;
    for (i, line) in markdown.lines().enumerate() {
        let n = i + 1;
        let is_fence = line.trim_start().starts_with("```");
        if !fence && (is_fence || line.trim().is_empty()) {
            scan_prose(binary, file, prose_from, &prose, &mut out);
            prose.clear();
        }
        if is_fence {
            fence = !fence;
            continue;
        }
        if fence {
            if joined.is_empty() {
                joined_from = n;
            }
            match line.trim_end().strip_suffix('\\') {
                Some(head) => {
                    joined.push_str(head);
                    joined.push(' ');
                }
                None => {
                    joined.push_str(line);
                    scan_code(binary, &format!("{file}:{joined_from}"), &joined, &mut out);
                    joined.clear();
                }
            }
        } else if !line.trim().is_empty() {
            if prose.is_empty() {
                prose_from = n;
            }
            prose.push_str(line);
            prose.push('\n');
        }
    }
    scan_prose(binary, file, prose_from, &prose, &mut out);
    out
}

/// The inline code spans (single backticks) of a paragraph that starts at line `from`.
fn scan_prose(binary: &str, file: &str, from: usize, paragraph: &str, out: &mut Vec<ShownCommand>) {
    let mut line = from;
    for (i, part) in paragraph.split('`').enumerate() {
        if i % 2 == 1 {
            // A span names a command only when it starts with one (after `VAR=value`s): prose
            // also quotes messages that mention a binary (`this slag-edge was built …`).
            let span = part.replace('\n', " ");
            let command = span
                .split_whitespace()
                .skip_while(|w| w.contains('=') && !w.starts_with('-'))
                .collect::<Vec<_>>()
                .join(" ");
            let first = command.split_whitespace().next().unwrap_or_default();
            if first.rsplit('/').next() == Some(binary) {
                scan_code(binary, &format!("{file}:{line}"), &command, out);
            }
        }
        line += part.matches('\n').count();
    }
}

/// Finds `binary` as a word of `code` (also as the last part of a path, `target/release/BIN`)
/// and reads its subcommand and flags up to the end of that command.
fn scan_code(binary: &str, place: &str, code: &str, out: &mut Vec<ShownCommand>) {
    // A shell comment ends the code (`#` at a word's start).
    let code = match code.find(" #") {
        Some(i) => &code[..i],
        None if code.trim_start().starts_with('#') => "",
        None => code,
    };
    let words: Vec<&str> = code.split_whitespace().collect();
    let mut i = 0;
    while i < words.len() {
        let w = words[i].trim_start_matches(['(', '[', '$', '"', '\'']);
        let is_binary = w.rsplit('/').next() == Some(binary);
        // `cargo test -p slag-edge --test cli` names a package, not a command line.
        let names_package = i > 0
            && matches!(
                words[i - 1],
                "-p" | "--package" | "--bin" | "--example" | "--test"
            );
        if !is_binary || names_package {
            i += 1;
            continue;
        }
        i += 1;
        // Global options may come first (`slag-edge --verbose query …`).
        let mut flags = Vec::new();
        while let Some(name) = words.get(i).and_then(|w| flag_name(w)) {
            flags.push(name);
            i += 1;
        }
        let mut subcommand = None;
        if let Some(next) = words.get(i)
            && next
                .chars()
                .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-')
            && next.starts_with(|c: char| c.is_ascii_lowercase())
        {
            subcommand = Some((*next).to_owned());
            i += 1;
        } else if flags.is_empty() {
            // `slag-edge` alone, or a placeholder such as `slag-encoder <cmd>`: nothing to check.
            continue;
        }
        let mut depth = 0i32;
        while i < words.len() {
            let w = words[i];
            if depth == 0 && (matches!(w, "|" | "&&" | "||" | ";") || w.ends_with(';')) {
                break;
            }
            depth += w.matches('[').count() as i32 - w.matches(']').count() as i32;
            if let Some(name) = flag_name(w.trim_start_matches(['[', '(', '|'])) {
                flags.push(name);
            }
            i += 1;
        }
        out.push(ShownCommand {
            place: place.to_owned(),
            subcommand,
            flags,
        });
    }
}

/// `--name` of a word that starts with `--name` (`--every`, `--text=a`, `--jobs]`).
fn flag_name(word: &str) -> Option<String> {
    let name: String = word
        .strip_prefix("--")?
        .chars()
        .take_while(|c| c.is_ascii_alphanumeric() || *c == '-')
        .collect();
    (!name.is_empty()).then(|| format!("--{name}"))
}

/// The standard output of the binary `exe` run with `args`, `None` when it exits with an error
/// or cannot start ([`run_binary`]).
pub fn output(exe: &str, args: &[&str]) -> Option<String> {
    run_binary(Path::new(exe), args).ok()
}

/// The standard output of the binary `bin` run with `args`, through `$SLAG_TEST_RUNNER` when
/// that is set (e.g. qemu under a cross build).
///
/// Errors: why it did not succeed (its exit status, or why it could not start).
pub fn run_binary(bin: &Path, args: &[&str]) -> std::result::Result<String, String> {
    let runner = std::env::var("SLAG_TEST_RUNNER").unwrap_or_default();
    let mut parts = runner.split_whitespace();
    let mut c = match parts.next() {
        Some(r) => {
            let mut c = std::process::Command::new(r);
            c.args(parts).arg(bin);
            c
        }
        None => std::process::Command::new(bin),
    };
    match c.args(args).output() {
        Ok(out) if out.status.success() => Ok(String::from_utf8_lossy(&out.stdout).into_owned()),
        Ok(out) => Err(out.status.to_string()),
        Err(e) => Err(e.to_string()),
    }
}

/// Everything wrong with the command line of `binary` (its built executable `exe`) as the
/// manual of the repository at `root` shows it ([`check_binary`]), one line each. Empty when all
/// is well. (One meaning per flag name across the binaries is each binary's own unit test:
/// [`crate::flag_names`].)
pub fn problems(binary: &str, exe: &str, root: &Path) -> Vec<String> {
    check_binary(binary, Path::new(exe), root)
        .err()
        .into_iter()
        .collect()
}

/// The `docs_flags` integration test of each slag binary: every `binary …` command line that
/// README.md and docs/guide/ show names a subcommand and flags its `--help` lists.
///
/// `exe` is the built executable (`env!("CARGO_BIN_EXE_<binary>")`), `root` the repository.
///
/// Panics (test support): with every line of [`problems`] when there is any.
pub fn assert_no_problems(binary: &str, exe: &str, root: &Path) {
    let problems = problems(binary, exe, root);
    assert!(problems.is_empty(), "`{binary}`:\n{}", problems.join("\n"));
}

/// The subcommands a top-level `--help` text lists under `Commands:`.
pub fn help_subcommands(help: &str) -> BTreeSet<String> {
    help.lines()
        .skip_while(|l| !l.trim_start().starts_with("Commands:"))
        .skip(1)
        .take_while(|l| !l.trim().is_empty())
        .filter_map(|l| l.split_whitespace().next().map(str::to_owned))
        .collect()
}

/// The `--flags` a `--help` text lists.
pub fn help_flags(help: &str) -> BTreeSet<String> {
    help.split(|c: char| c.is_whitespace() || c == ',' || c == '[' || c == '(')
        .filter_map(flag_name)
        .collect()
}

/// [`check`] against the built binary at `bin` (`binary` is its name in the manual), each help
/// read by running it, through `$SLAG_TEST_RUNNER` when that is set (e.g. qemu under a cross
/// build): what each binary's `docs_flags` integration test runs.
///
/// Errors: one message naming the binary: that it could not be started or failed on a `--help`,
/// or [`check`]'s problems, one per line.
pub fn check_binary(binary: &str, bin: &Path, root: &Path) -> std::result::Result<usize, String> {
    let failure = std::cell::RefCell::new(None::<String>);
    let help = |args: &[&str]| {
        run_binary(bin, args).unwrap_or_else(|why| {
            failure
                .borrow_mut()
                .get_or_insert(format!("`{binary} {}` failed: {why}", args.join(" ")));
            String::new()
        })
    };
    let checked = check(binary, root, &help);
    if let Some(f) = failure.into_inner() {
        return Err(f);
    }
    checked.map_err(|problems| {
        format!(
            "the manual shows what `{binary}` does not have:\n{}",
            problems.join("\n")
        )
    })
}

/// Checks every command line of `binary` in the manual of the repository at `root` against the
/// binary's help: `help(args)` returns the output of the binary run with `args` (`["--help"]`,
/// `["serve", "--help"]`).
///
/// Errors: one line per unknown subcommand or flag, with its place; also when the manual shows
/// no command line of `binary` at all (a scan that finds nothing checks nothing).
pub fn check(
    binary: &str,
    root: &Path,
    help: &dyn Fn(&[&str]) -> String,
) -> std::result::Result<usize, Vec<String>> {
    let top = help(&["--help"]);
    let subcommands = help_subcommands(&top);
    let mut helps: HashMap<Option<String>, BTreeSet<String>> = HashMap::new();
    helps.insert(None, help_flags(&top));
    let mut problems = Vec::new();
    let mut checked = 0;
    for page in manual_pages(root) {
        let Ok(text) = std::fs::read_to_string(&page) else {
            problems.push(format!("{}: cannot be read", page.display()));
            continue;
        };
        let name = page
            .strip_prefix(root)
            .unwrap_or(&page)
            .display()
            .to_string();
        for cmd in shown_commands(binary, &name, &text) {
            checked += 1;
            if let Some(sub) = &cmd.subcommand
                && !subcommands.contains(sub)
            {
                problems.push(format!(
                    "{}: `{binary} {sub}`: no such subcommand (`{binary} --help`)",
                    cmd.place
                ));
                continue;
            }
            let known = helps.entry(cmd.subcommand.clone()).or_insert_with(|| {
                let sub = cmd.subcommand.as_deref().unwrap_or_default();
                help_flags(&help(&[sub, "--help"]))
            });
            for flag in &cmd.flags {
                if flag != "--help" && !known.contains(flag) {
                    problems.push(format!(
                        "{}: `{binary} {}` shows {flag}, which its --help does not list",
                        cmd.place,
                        cmd.subcommand.as_deref().unwrap_or(""),
                    ));
                }
            }
        }
    }
    if checked == 0 {
        problems.push(format!(
            "no `{binary} …` command line found in README.md or docs/guide/"
        ));
    }
    if problems.is_empty() {
        Ok(checked)
    } else {
        Err(problems)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn commands_are_read_from_code_blocks_and_inline_code() {
        let md = "Run `slag-edge serve --hnsw` or `slag-edge`.\n\
                  ```sh\n\
                  slag-edge fetch --from URL \\\n    [--prune] [--jobs 4 | --x]  # not --comment\n\
                  cargo test -p slag-edge --test cli\n\
                  ./target/release/slag-edge --verbose query --text=a | jq --raw\n\
                  ```\n\
                  prose --not-code slag-edge serve --nope\n\n\
                  A span `slag-edge\nquery --top-k 3` wraps.\n\
                  A message `this slag-edge was built --without` is not a command.\n";
        let got = shown_commands("slag-edge", "r.md", md);
        let want = [
            ("r.md:1", Some("serve"), vec!["--hnsw"]),
            (
                "r.md:3",
                Some("fetch"),
                vec!["--from", "--prune", "--jobs", "--x"],
            ),
            ("r.md:6", Some("query"), vec!["--verbose", "--text"]),
            ("r.md:10", Some("query"), vec!["--top-k"]),
        ];
        assert_eq!(got.len(), want.len(), "{got:?}");
        for (g, (place, sub, flags)) in got.iter().zip(want) {
            assert_eq!(g.place, place);
            assert_eq!(g.subcommand.as_deref(), sub);
            assert_eq!(g.flags, flags);
        }
    }

    #[test]
    fn help_text_gives_flags_and_subcommands() {
        let top = "Usage: x <COMMAND>\n\nCommands:\n  fetch  Download\n  serve  Serve\n\nOptions:\n  -v, --verbose  Debug\n";
        assert_eq!(
            help_subcommands(top).into_iter().collect::<Vec<_>>(),
            ["fetch", "serve"]
        );
        let sub = "Options:\n      --max-shard-mb <MB>  Cap [default: 16]\n  -h, --help\n";
        assert_eq!(
            help_flags(sub).into_iter().collect::<Vec<_>>(),
            ["--help", "--max-shard-mb"]
        );
    }
}
