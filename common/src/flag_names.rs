//! One meaning per flag name and one name per meaning, across every slag binary (`slag-encoder`,
//! `slag-shards`, `slag-edge`, `slag-bench`), hidden aliases included.
//!
//! Each binary's unit test walks its own clap command tree ([`tree_flags`]): every long flag of
//! every subcommand with its value name, default, aliases and whether it is hidden. The rows of
//! every binary are kept in `tests/flags/<binary>.txt` (the test fails when a binary's rows
//! differ from its file, and rewrites it with `SLAG_BLESS_FLAGS=1`), so one binary's test checks
//! its live tree against the others' ([`assert_one_meaning`], [`check_tree`]). It fails when
//! - one name has two meanings: a flag, or an alias of one, named as another flag is, with a
//!   different value name (`--scene <NAME>` here, `--scene-dir <DIR>` with the hidden alias
//!   `--scene` there), or not what [`CONCEPTS`] says the name means;
//! - one meaning has two names: a visible alias; a hidden alias that is not an older spelling
//!   listed in [`crate::cli::deprecated::DEPRECATED`] (which also notes its use on stderr); a
//!   visible flag spelt as such an older spelling; an older spelling no binary accepts;
//! - one concept has two defaults: a flag of [`CONCEPTS`] that keeps one default with different
//!   defaults in two places (`--top-k`).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use crate::cli::deprecated::{DEPRECATED, lookup};

/// A thing several subcommands or binaries name on the command line, with its one name.
#[derive(Debug, Clone, Copy)]
pub struct Concept {
    /// Its one long flag, e.g. `--listen`.
    pub flag: &'static str,
    /// The value names it may show (`HOST:PORT` in `--listen <HOST:PORT>`); empty for a switch.
    pub values: &'static [&'static str],
    /// What it names, in a few words.
    pub meaning: &'static str,
    /// Whether every subcommand that gives it a default gives the same one (`--listen`: no, each
    /// server has its own port).
    pub one_default: bool,
}

/// The concepts that several subcommands or binaries name, or whose names were once used for
/// something else: the flag keeps this meaning wherever it appears.
pub const CONCEPTS: &[Concept] = &[
    Concept {
        flag: "--listen",
        values: &["HOST:PORT"],
        meaning: "the socket address a server listens on",
        one_default: false,
    },
    Concept {
        flag: "--clip-textual",
        values: &["ONNX"],
        meaning: "the CLIP text tower (ONNX) that embeds prompts",
        one_default: true,
    },
    Concept {
        flag: "--scene",
        values: &["NAME"],
        meaning: "a scene's name in a shard store, a manifest and the URLs",
        one_default: true,
    },
    Concept {
        flag: "--scene-dir",
        values: &["DIR"],
        meaning: "a scene's folder (point_cloud.ply, images/, poses)",
        one_default: true,
    },
    Concept {
        flag: "--views",
        values: &["RULE"],
        meaning: "which training views are encoded (all, uniform, coverage)",
        one_default: true,
    },
    Concept {
        flag: "--view-count",
        values: &["N"],
        meaning: "how many views",
        one_default: false,
    },
    Concept {
        flag: "--every",
        values: &["N"],
        meaning: "keep every N-th training view (thinning)",
        one_default: true,
    },
    Concept {
        flag: "--hold-out-every",
        values: &["N"],
        meaning: "the held-out step: views with index ≡ N/2 (mod N) are held out",
        one_default: true,
    },
    Concept {
        flag: "--out",
        values: &["DIR", "FILE"],
        meaning: "where a subcommand writes: a folder or a file, as it says",
        one_default: false,
    },
    Concept {
        flag: "--segments",
        values: &["FILE", "FILE|off"],
        meaning: "a segments file to read (default: the one beside the embeddings)",
        one_default: true,
    },
    Concept {
        flag: "--write-segments",
        values: &["on|off"],
        meaning: "whether an encode also writes the geometric segments",
        one_default: true,
    },
    Concept {
        flag: "--store",
        values: &["DIR"],
        meaning: "the robot's store folder (fetched shards, verified)",
        one_default: true,
    },
    Concept {
        flag: "--shard-store",
        values: &["DIR"],
        meaning: "the publisher's shard store folder (sled: every scene's generations)",
        one_default: true,
    },
    Concept {
        flag: "--ep",
        values: &["EP"],
        meaning: "the ONNX Runtime execution provider (cpu, cuda, tensorrt, auto)",
        // An encode takes the GPU when there is one (auto); a query of one prompt, the
        // evaluation's text tower and the robot stay on the CPU; the model timings time CUDA.
        one_default: false,
    },
    Concept {
        flag: "--verbose",
        values: &[],
        meaning: "debug logging, and an error's debug form",
        one_default: true,
    },
    Concept {
        flag: "--mixture-keep",
        values: &["S"],
        meaning: "slots (codebook atom, weight) kept per Gaussian in a mixture",
        one_default: false,
    },
    Concept {
        flag: "--embeddings",
        values: &["FILE"],
        meaning: "a per-Gaussian embeddings file, either form (mixture or dense)",
        one_default: true,
    },
    Concept {
        flag: "--shard-token-file",
        values: &["FILE"],
        meaning: "a file holding the shard server's bearer token",
        one_default: true,
    },
    Concept {
        flag: "--token-file",
        values: &["FILE"],
        meaning: "a file holding the bearer token this server's clients must send",
        one_default: true,
    },
    Concept {
        flag: "--top-k",
        values: &["K"],
        meaning: "how many matches a query returns (default 100)",
        one_default: true,
    },
];

/// One long flag of one subcommand in a binary's command tree.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
pub struct TreeFlag {
    /// The binary, `slag-edge`.
    pub binary: String,
    /// The subcommand's path (`serve`; empty: the binary's top-level options).
    pub subcommand: String,
    /// The long name, `--listen`.
    pub long: String,
    /// The value name, `HOST:PORT` (`None` for a switch).
    pub value: Option<String>,
    /// The default value, if clap has one.
    pub default: Option<String>,
    /// Whether `--help` leaves the flag out.
    pub hidden: bool,
    /// The other names it answers to, `--bind`, each with whether `--help` shows it.
    pub aliases: Vec<(String, bool)>,
}

impl TreeFlag {
    /// Where it is, as a user would type it: `slag-edge serve --listen`.
    fn place(&self) -> String {
        let sub = if self.subcommand.is_empty() {
            String::new()
        } else {
            format!(" {}", self.subcommand)
        };
        format!("`{}{sub} {}`", self.binary, self.long)
    }

    /// One tab-separated line: binary, subcommand, long, value, default, hidden, aliases (`-`
    /// for none; a visible alias is marked `+`).
    pub fn to_line(&self) -> String {
        let or_dash = |s: &Option<String>| s.clone().unwrap_or_else(|| "-".into());
        let aliases: Vec<String> = self
            .aliases
            .iter()
            .map(|(a, visible)| if *visible { format!("+{a}") } else { a.clone() })
            .collect();
        [
            self.binary.clone(),
            if self.subcommand.is_empty() {
                "-".into()
            } else {
                self.subcommand.clone()
            },
            self.long.clone(),
            or_dash(&self.value),
            or_dash(&self.default),
            if self.hidden { "hidden" } else { "shown" }.into(),
            if aliases.is_empty() {
                "-".into()
            } else {
                aliases.join(",")
            },
        ]
        .join("\t")
    }

    /// The flag of a line [`Self::to_line`] wrote.
    ///
    /// Errors: a line without its seven fields, named.
    pub fn from_line(line: &str) -> Result<Self, String> {
        let f: Vec<&str> = line.split('\t').collect();
        let [binary, sub, long, value, default, hidden, aliases] = f[..] else {
            return Err(format!("{line:?}: seven tab-separated fields expected"));
        };
        let opt = |s: &str| (s != "-").then(|| s.to_owned());
        Ok(TreeFlag {
            binary: binary.into(),
            subcommand: opt(sub).unwrap_or_default(),
            long: long.into(),
            value: opt(value),
            default: opt(default),
            hidden: hidden == "hidden",
            aliases: opt(aliases)
                .map(|a| {
                    a.split(',')
                        .map(|a| match a.strip_prefix('+') {
                            Some(a) => (a.to_owned(), true),
                            None => (a.to_owned(), false),
                        })
                        .collect()
                })
                .unwrap_or_default(),
        })
    }
}

/// Every long flag of `cmd` and of its subcommands, at any depth, but `--help` and `--version`.
pub fn tree_flags(binary: &str, cmd: &clap::Command) -> Vec<TreeFlag> {
    let mut out = Vec::new();
    walk(binary, "", cmd, &mut out);
    out.sort();
    out
}

/// [`tree_flags`] of `cmd`, the subcommand at `path`.
fn walk(binary: &str, path: &str, cmd: &clap::Command, out: &mut Vec<TreeFlag>) {
    for arg in cmd.get_arguments() {
        let Some(long) = arg.get_long() else { continue };
        if matches!(long, "help" | "version") {
            continue;
        }
        let visible: BTreeSet<&str> = arg
            .get_visible_aliases()
            .unwrap_or_default()
            .into_iter()
            .collect();
        let value = arg.get_action().takes_values().then(|| {
            arg.get_value_names()
                .and_then(|v| v.first())
                .map(|v| v.to_string())
                .unwrap_or_else(|| arg.get_id().as_str().to_uppercase())
        });
        let defaults: Vec<String> = arg
            .get_default_values()
            .iter()
            .map(|d| d.to_string_lossy().into_owned())
            .collect();
        out.push(TreeFlag {
            binary: binary.to_owned(),
            subcommand: path.to_owned(),
            long: format!("--{long}"),
            value,
            default: (!defaults.is_empty()).then(|| defaults.join(",")),
            hidden: arg.is_hide_set(),
            aliases: arg
                .get_all_aliases()
                .unwrap_or_default()
                .into_iter()
                .map(|a| (format!("--{a}"), visible.contains(a)))
                .collect(),
        });
    }
    for sub in cmd.get_subcommands() {
        let name = sub.get_name();
        let sub_path = if path.is_empty() {
            name.to_owned()
        } else {
            format!("{path} {name}")
        };
        walk(binary, &sub_path, sub, out);
    }
}

/// What a flag means, as far as the command line can tell: the concept its name belongs to, or
/// else its own name with its value name.
fn meaning(f: &TreeFlag) -> String {
    match CONCEPTS.iter().find(|c| c.flag == f.long) {
        Some(c) => format!("{} ({})", c.flag, c.meaning),
        None => format!("{} <{}>", f.long, f.value.as_deref().unwrap_or("no value")),
    }
}

/// Everything wrong with the names of `flags` (the rows of one or more binaries), one line each
/// naming the places and what to do; empty when each name has one meaning and each meaning one
/// name.
pub fn check_tree(flags: &[TreeFlag]) -> Vec<String> {
    let mut problems = Vec::new();
    problems.extend(flags.iter().flat_map(concept_problems));
    problems.extend(flags.iter().flat_map(alias_problems));
    problems.extend(names_with_two_meanings(flags));
    problems.extend(concepts_with_two_defaults(flags));
    for d in DEPRECATED {
        let accepted = flags.iter().any(|f| {
            (f.long == d.new && f.aliases.iter().any(|(a, _)| a == d.old))
                || (f.long == d.old && f.hidden)
        });
        if !accepted {
            problems.push(format!(
                "{} is listed as an older spelling of {}, but no binary accepts it: keep it as \
                 a hidden alias of {}, or take it out of slag_common::cli::deprecated::DEPRECATED",
                d.old, d.new, d.new
            ));
        }
    }
    problems.sort();
    problems.dedup();
    problems
}

/// A flag named as a concept that shows another value than the concept's.
fn concept_problems(f: &TreeFlag) -> Option<String> {
    let c = CONCEPTS.iter().find(|c| c.flag == f.long)?;
    let value = f.value.as_deref();
    let fits = match value {
        None => c.values.is_empty(),
        Some(v) => c.values.contains(&v),
    };
    (!fits).then(|| {
        format!(
            "{} takes <{}>, but {} means {} (<{}>) in every slag binary: give this flag a name \
             of its own",
            f.place(),
            value.unwrap_or("no value"),
            c.flag,
            c.meaning,
            c.values.join("> or <"),
        )
    })
}

/// A second name for one flag: a visible alias, a hidden one that is not a listed older
/// spelling of it, a visible flag spelt as an older spelling.
fn alias_problems(f: &TreeFlag) -> Vec<String> {
    let mut out = Vec::new();
    if let Some(d) = lookup(&f.long).filter(|_| !f.hidden) {
        out.push(format!(
            "{} is an older spelling of {}: name it {} (keep {} as a hidden alias)",
            f.place(),
            d.new,
            d.new,
            d.old
        ));
    }
    for (alias, visible) in &f.aliases {
        if *visible {
            out.push(format!(
                "{} shows a second name, {alias}: one name per meaning (hide it if it is an \
                 older spelling, and list it in slag_common::cli::deprecated::DEPRECATED)",
                f.place()
            ));
        } else if lookup(alias).is_none_or(|d| d.new != f.long) {
            out.push(format!(
                "{} answers to the hidden alias {alias}, which is not listed as an older \
                 spelling of {} in slag_common::cli::deprecated::DEPRECATED (so its use is \
                 never noted): list it there, or remove it",
                f.place(),
                f.long
            ));
        }
    }
    out
}

/// Names (flags and aliases alike) that stand for two meanings.
fn names_with_two_meanings(flags: &[TreeFlag]) -> Vec<String> {
    let mut by_name: BTreeMap<&str, BTreeMap<String, Vec<String>>> = BTreeMap::new();
    for f in flags {
        let m = meaning(f);
        let names = std::iter::once((f.long.as_str(), false))
            .chain(f.aliases.iter().map(|(a, _)| (a.as_str(), true)));
        for (name, is_alias) in names {
            let place = if is_alias {
                format!("{} (alias of {})", f.place().replace(&f.long, name), f.long)
            } else {
                f.place()
            };
            by_name
                .entry(name)
                .or_default()
                .entry(m.clone())
                .or_default()
                .push(place);
        }
    }
    by_name
        .into_iter()
        .filter(|(_, meanings)| meanings.len() > 1)
        .map(|(name, meanings)| {
            let each: Vec<String> = meanings
                .iter()
                .map(|(m, places)| format!("{m} in {}", places.join(", ")))
                .collect();
            format!(
                "{name} has {} meanings: {}. One name, one meaning: rename one of them (or, if \
                 they are one thing, give them one value name and list it in \
                 slag_common::flag_names::CONCEPTS)",
                meanings.len(),
                each.join("; ")
            )
        })
        .collect()
}

/// Flags of a concept with one default ([`Concept::one_default`]) whose defaults differ. A flag
/// outside [`CONCEPTS`] may default per subcommand (a study's `--repeats`, render's
/// `--raster-scale`).
fn concepts_with_two_defaults(flags: &[TreeFlag]) -> Vec<String> {
    let mut by_meaning: BTreeMap<String, BTreeMap<&str, Vec<String>>> = BTreeMap::new();
    for f in flags {
        let Some(default) = f.default.as_deref() else {
            continue;
        };
        if !CONCEPTS.iter().any(|c| c.flag == f.long && c.one_default) {
            continue;
        }
        by_meaning
            .entry(meaning(f))
            .or_default()
            .entry(default)
            .or_default()
            .push(f.place());
    }
    by_meaning
        .into_iter()
        .filter(|(_, defaults)| defaults.len() > 1)
        .map(|(m, defaults)| {
            let each: Vec<String> = defaults
                .iter()
                .map(|(d, places)| format!("{d} in {}", places.join(", ")))
                .collect();
            format!(
                "{m} has {} defaults: {}. One default per concept: give them one, or names of \
                 their own if they are different things",
                defaults.len(),
                each.join("; ")
            )
        })
        .collect()
}

/// The folder of the binaries' flag rows in the repository at `root`.
pub fn rows_dir(root: &Path) -> PathBuf {
    root.join("tests").join("flags")
}

/// The flag rows of every binary but `binary` kept under [`rows_dir`].
///
/// Errors: an unreadable folder or file, a line [`TreeFlag::from_line`] refuses.
pub fn other_binaries(root: &Path, binary: &str) -> Result<Vec<TreeFlag>, String> {
    let dir = rows_dir(root);
    let entries = std::fs::read_dir(&dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    let mut out = Vec::new();
    for entry in entries {
        let path = entry.map_err(|e| format!("{}: {e}", dir.display()))?.path();
        if path.extension().is_none_or(|x| x != "txt")
            || path.file_stem().is_some_and(|s| s == binary)
        {
            continue;
        }
        let text =
            std::fs::read_to_string(&path).map_err(|e| format!("{}: {e}", path.display()))?;
        for line in text.lines().filter(|l| !l.is_empty()) {
            out.push(TreeFlag::from_line(line).map_err(|e| format!("{}: {e}", path.display()))?);
        }
    }
    Ok(out)
}

/// The unit test of each binary: `cmd` is its clap command tree, `root` the repository. Its
/// rows must equal `tests/flags/<binary>.txt` (rewritten instead with `SLAG_BLESS_FLAGS=1`), and
/// they and every other binary's rows must pass [`check_tree`].
///
/// Panics (test support): with every problem, one per line.
pub fn assert_one_meaning(binary: &str, cmd: &clap::Command, root: &Path) {
    let flags = tree_flags(binary, cmd);
    let text: String = flags.iter().map(|f| f.to_line() + "\n").collect();
    let file = rows_dir(root).join(format!("{binary}.txt"));
    let mut problems = Vec::new();
    if std::env::var_os("SLAG_BLESS_FLAGS").is_some() {
        if let Err(e) =
            std::fs::create_dir_all(rows_dir(root)).and_then(|()| std::fs::write(&file, &text))
        {
            problems.push(format!("{}: {e}", file.display()));
        }
    } else if std::fs::read_to_string(&file).ok().as_deref() != Some(text.as_str()) {
        problems.push(format!(
            "{} does not list {binary}'s flags as they are: check the change, then write it \
             with SLAG_BLESS_FLAGS=1 cargo test -p <its package> --bin {binary} flag",
            file.display()
        ));
    }
    let mut all = flags;
    match other_binaries(root, binary) {
        Ok(others) => all.extend(others),
        Err(e) => problems.push(e),
    }
    problems.extend(check_tree(&all));
    assert!(
        problems.is_empty(),
        "the flags of the slag binaries:\n{}",
        problems.join("\n")
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::{Arg, ArgAction, Command};

    fn opt(long: &'static str, value: &'static str) -> Arg {
        Arg::new(long).long(long).value_name(value)
    }

    /// A binary with `serve` and `encode` subcommands; the caller adds their flags.
    fn binary(serve: Vec<Arg>, encode: Vec<Arg>) -> Command {
        Command::new("x")
            .arg(
                Arg::new("verbose")
                    .long("verbose")
                    .short('v')
                    .action(ArgAction::SetTrue),
            )
            .subcommand(Command::new("serve").args(serve))
            .subcommand(Command::new("encode").args(encode))
    }

    #[test]
    fn the_tree_gives_every_flag_with_its_hidden_aliases() {
        let cmd = binary(
            vec![
                opt("listen", "HOST:PORT")
                    .aliases(["bind", "addr"])
                    .default_value("127.0.0.1:1"),
            ],
            vec![opt("scene-dir", "DIR").visible_alias("folder").hide(true)],
        );
        let rows = tree_flags("x", &cmd);
        let lines: Vec<String> = rows.iter().map(TreeFlag::to_line).collect();
        assert_eq!(
            lines,
            [
                "x\t-\t--verbose\t-\t-\tshown\t-",
                "x\tencode\t--scene-dir\tDIR\t-\thidden\t+--folder",
                "x\tserve\t--listen\tHOST:PORT\t127.0.0.1:1\tshown\t--bind,--addr",
            ]
        );
        for (row, line) in rows.iter().zip(&lines) {
            assert_eq!(&TreeFlag::from_line(line), &Ok(row.clone()));
        }
        assert!(TreeFlag::from_line("x\t-").is_err());
    }

    #[test]
    fn one_name_per_meaning_passes() {
        let cmd = binary(
            vec![
                opt("listen", "HOST:PORT").aliases(["bind", "addr"]),
                opt("scene", "NAME"),
            ],
            vec![
                opt("scene-dir", "DIR"),
                opt("clip-textual", "ONNX").alias("text-model"),
                opt("embeddings", "FILE").aliases(["mixture"]),
                opt("mixture-keep", "S").alias("mixture-slots"),
                Arg::new("prediction-filtering")
                    .long("prediction-filtering")
                    .alias("pf")
                    .action(ArgAction::SetTrue),
                opt("token", "TOKEN").hide(true),
            ],
        );
        assert_eq!(check_tree(&tree_flags("x", &cmd)), Vec::<String>::new());
    }

    /// The deliberate collisions the check exists for: each must fail.
    #[test]
    fn a_name_with_two_meanings_fails() {
        // `--scene` a name in one subcommand, a hidden alias of the folder in another.
        let cmd = binary(
            vec![opt("scene", "NAME")],
            vec![opt("scene-dir", "DIR").alias("scene")],
        );
        let problems = check_tree(&tree_flags("x", &cmd));
        assert!(
            problems
                .iter()
                .any(|p| p.starts_with("--scene has 2 meanings")
                    && p.contains("`x encode --scene` (alias of --scene-dir)")),
            "{problems:?}"
        );
        // Across two binaries: the same name with two value names.
        let mut rows = tree_flags("x", &binary(vec![opt("cache", "DIR")], vec![]));
        rows.extend(tree_flags("y", &binary(vec![], vec![opt("cache", "FILE")])));
        let problems = check_tree(&rows);
        assert!(
            problems
                .iter()
                .any(|p| p.starts_with("--cache has 2 meanings")),
            "{problems:?}"
        );
        // A concept's name with another value.
        let cmd = binary(vec![opt("scene", "DIR")], vec![]);
        let problems = check_tree(&tree_flags("x", &cmd));
        assert!(
            problems
                .iter()
                .any(|p| p.contains("`x serve --scene` takes <DIR>")),
            "{problems:?}"
        );
    }

    #[test]
    fn a_meaning_with_two_names_fails() {
        let cmd = binary(
            vec![opt("bind", "HOST:PORT")],
            vec![
                opt("scene-dir", "DIR").visible_alias("folder"),
                opt("every", "N").alias("step"),
            ],
        );
        let problems = check_tree(&tree_flags("x", &cmd));
        for wanted in [
            "`x serve --bind` is an older spelling of --listen",
            "`x encode --scene-dir` shows a second name, --folder",
            "`x encode --every` answers to the hidden alias --step",
            "--addr is listed as an older spelling of --listen, but no binary accepts it",
        ] {
            assert!(
                problems.iter().any(|p| p.contains(wanted)),
                "{wanted}: {problems:?}"
            );
        }
    }

    #[test]
    fn a_concept_with_two_defaults_fails_unless_it_may() {
        let cmd = binary(
            vec![
                opt("top-k", "K").default_value("100"),
                opt("listen", "HOST:PORT").default_value("a:1"),
            ],
            vec![
                opt("top-k", "K").default_value("20"),
                opt("listen", "HOST:PORT").default_value("b:2"),
            ],
        );
        let problems = check_tree(&tree_flags("x", &cmd));
        let defaults: Vec<&String> = problems.iter().filter(|p| p.contains("defaults")).collect();
        assert_eq!(defaults.len(), 1, "{problems:?}");
        assert!(
            defaults[0].contains("100 in `x serve --top-k`; 20 in `x encode --top-k`")
                || defaults[0].contains("20 in `x encode --top-k`; 100 in `x serve --top-k`")
        );
    }
}
