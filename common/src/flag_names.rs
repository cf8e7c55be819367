//! One name per thing on the command line: across `slag-encoder`, `slag-shards` and `slag-edge`
//! a concept has one visible long flag, and a visible long flag names one concept.
//!
//! [`CONCEPTS`] is the table of the things several subcommands or binaries name: each with its
//! flag, the values its `--help` may show, what it means, and the older spellings every binary
//! still accepts as hidden aliases (so scripts keep working). Each binary's crate runs [`check`]
//! in an integration test against its own built binary: it lists every flag of every subcommand
//! from `--help` ([`list`]) and fails when
//! - a visible flag is an older spelling of a concept (a second name for one thing);
//! - a concept's flag shows another value (one name for a second thing);
//! - one flag shows two different values in two subcommands of the binary;
//! - an older spelling is no longer accepted where the concept's flag is.
//!
//! The table is the same for the three binaries, so a concept keeps one name across them.

use std::collections::{BTreeMap, BTreeSet};

/// A thing that several subcommands or binaries name on the command line.
#[derive(Debug, Clone, Copy)]
pub struct Concept {
    /// Its one visible long flag, e.g. `--listen`.
    pub flag: &'static str,
    /// The value names its `--help` may show (`HOST:PORT` in `--listen <HOST:PORT>`).
    pub values: &'static [&'static str],
    /// What it names, in a few words.
    pub meaning: &'static str,
    /// Older spellings, still accepted as hidden aliases wherever `flag` is.
    pub old: &'static [&'static str],
    /// A value the flag accepts, to try the older spellings with.
    pub sample: &'static str,
}

/// The concepts with one name across the three binaries.
pub const CONCEPTS: &[Concept] = &[
    Concept {
        flag: "--listen",
        values: &["HOST:PORT"],
        meaning: "the socket address a server listens on",
        old: &["--addr", "--bind"],
        sample: "127.0.0.1:8080",
    },
    Concept {
        flag: "--clip-textual",
        values: &["ONNX"],
        meaning: "the CLIP text tower (ONNX) that embeds prompts",
        old: &["--text-model"],
        sample: "clip-textual.onnx",
    },
    Concept {
        flag: "--scene",
        values: &["NAME"],
        meaning: "a scene's name in a shard store, a manifest and the URLs",
        old: &[],
        sample: "lab",
    },
    Concept {
        flag: "--scene-dir",
        values: &["DIR"],
        meaning: "a scene's folder (point_cloud.ply, images/, poses)",
        old: &["--scene"],
        sample: "scene",
    },
    Concept {
        flag: "--views",
        values: &["RULE"],
        meaning: "which training views are encoded (all, uniform, coverage)",
        old: &[],
        sample: "all",
    },
    Concept {
        flag: "--view-count",
        values: &["N"],
        meaning: "how many views",
        old: &["--views"],
        sample: "4",
    },
    Concept {
        flag: "--out",
        values: &["DIR", "FILE"],
        meaning: "where a subcommand writes: a folder or a file, as it says",
        old: &[],
        sample: "out",
    },
    Concept {
        flag: "--segments",
        values: &["FILE", "FILE|off", "on|off"],
        meaning: "the geometric segments: a segments file to read, or on / off",
        old: &[],
        sample: "off",
    },
];

/// One flag of one subcommand, as its `--help` defines it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ShownFlag {
    /// The subcommand (`None`: the binary's top-level options).
    pub subcommand: Option<String>,
    /// The long name, `--listen`.
    pub long: String,
    /// The value name, `HOST:PORT` (`None` for a switch).
    pub value: Option<String>,
}

/// The long flags a `--help` text defines, each with its value name: the option lines after
/// `Usage:` (`  -v, --verbose`, `      --listen <HOST:PORT>`) and their visible aliases
/// (`[aliases: --bind]`), never a flag a description or the text above `Usage:` mentions.
pub fn defined_flags(help: &str) -> Vec<(String, Option<String>)> {
    let mut out: Vec<(String, Option<String>)> = Vec::new();
    for line in help.lines().skip_while(|line| !line.starts_with("Usage:")) {
        if let Some(flag) = option_line(line) {
            out.push(flag);
        }
        let aliases = line
            .split_once("[aliases: ")
            .or_else(|| line.split_once("[alias: "))
            .and_then(|(_, rest)| rest.split_once(']'));
        if let (Some((aliases, _)), Some((_, value))) = (aliases, out.last().cloned()) {
            for alias in aliases.split(',').map(|a| a.trim().trim_start_matches('-')) {
                if alias.len() > 1 {
                    out.push((format!("--{alias}"), value.clone()));
                }
            }
        }
    }
    out
}

/// The long flag and value name an option line defines (`      --listen <HOST:PORT>  …`).
fn option_line(line: &str) -> Option<(String, Option<String>)> {
    let rest = line.strip_prefix("      --").or_else(|| {
        let short = line.strip_prefix("  -")?;
        let mut chars = short.chars();
        chars.next().filter(char::is_ascii_alphanumeric)?;
        chars.as_str().strip_prefix(", --")
    })?;
    let long: String = rest
        .chars()
        .take_while(|c| c.is_ascii_alphanumeric() || *c == '-')
        .collect();
    let after = rest[long.len()..].trim_start_matches([' ', '=', '[']);
    let value = after
        .strip_prefix('<')
        .and_then(|v| v.split_once('>'))
        .map(|(v, _)| v.to_owned());
    (!long.is_empty()).then(|| (format!("--{long}"), value))
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

/// Every flag of every subcommand of a binary: `help(args)` returns the binary's output for
/// `args` (`["--help"]`, `["serve", "--help"]`), `None` when it exits with an error.
///
/// Errors: a `--help` page that cannot be read, named.
pub fn list(
    help: &dyn Fn(&[&str]) -> Option<String>,
) -> std::result::Result<Vec<ShownFlag>, String> {
    let top = help(&["--help"]).ok_or("`--help` failed")?;
    let mut out: Vec<ShownFlag> = defined_flags(&top)
        .into_iter()
        .map(|(long, value)| ShownFlag {
            subcommand: None,
            long,
            value,
        })
        .collect();
    for sub in help_subcommands(&top) {
        if sub == "help" {
            continue;
        }
        let page = help(&[&sub, "--help"]).ok_or(format!("`{sub} --help` failed"))?;
        out.extend(
            defined_flags(&page)
                .into_iter()
                .map(|(long, value)| ShownFlag {
                    subcommand: Some(sub.clone()),
                    long,
                    value,
                }),
        );
    }
    Ok(out)
}

/// Checks every flag of `binary` against [`CONCEPTS`] and against each other (see the module
/// docs); `help` as in [`list`]. Returns the number of flags checked.
///
/// Errors: one line per problem, naming the subcommand, the flag and what to do.
pub fn check(
    binary: &str,
    help: &dyn Fn(&[&str]) -> Option<String>,
) -> std::result::Result<usize, Vec<String>> {
    let flags = list(help).map_err(|e| vec![format!("{binary}: {e}")])?;
    let mut problems = Vec::new();
    let mut values: BTreeMap<&str, BTreeMap<Option<&str>, &ShownFlag>> = BTreeMap::new();
    let shown = |sub: &Option<String>, long: &str| {
        flags.iter().any(|f| f.subcommand == *sub && f.long == long)
    };
    for f in &flags {
        let place = format!("`{binary} {}`", f.subcommand.as_deref().unwrap_or_default());
        let concept = CONCEPTS.iter().find(|c| c.flag == f.long);
        let older_of = CONCEPTS.iter().find(|c| c.old.contains(&f.long.as_str()));
        match (concept, older_of) {
            (Some(c), _) => {
                if !c.values.contains(&f.value.as_deref().unwrap_or_default()) {
                    problems.push(format!(
                        "{place} shows {} <{}>, but {} means {} (<{}>) in every slag binary: \
                         give this flag a name of its own",
                        f.long,
                        f.value.as_deref().unwrap_or_default(),
                        c.flag,
                        c.meaning,
                        c.values.join("> or <"),
                    ));
                }
                // An older spelling the subcommand shows names another concept there.
                let old = c.old.iter().filter(|old| !shown(&f.subcommand, old));
                problems.extend(refused_old_spellings(binary, f, c, old, help));
            }
            (None, Some(c)) => problems.push(format!(
                "{place} shows {}, an older spelling of {} ({}): name it {} and keep {} as a \
                 hidden alias",
                f.long, c.flag, c.meaning, c.flag, f.long
            )),
            (None, None) => {
                values
                    .entry(&f.long)
                    .or_default()
                    .entry(f.value.as_deref())
                    .or_insert(f);
            }
        }
    }
    for (long, by_value) in values.iter().filter(|(_, v)| v.len() > 1) {
        let shown: Vec<String> = by_value
            .iter()
            .map(|(v, f)| {
                format!(
                    "<{}> in `{}`",
                    v.unwrap_or("no value"),
                    f.subcommand.as_deref().unwrap_or(binary)
                )
            })
            .collect();
        problems.push(format!(
            "`{binary}`: {long} takes {}: one name, one meaning; rename one of them (or, if \
             they are one thing, add it to slag_common::flag_names::CONCEPTS)",
            shown.join(" but ")
        ));
    }
    match (flags.len(), problems.is_empty()) {
        (0, _) => Err(vec![format!("`{binary} --help` lists no flag")]),
        (n, true) => Ok(n),
        (_, false) => Err(problems),
    }
}

/// The older spellings `old` of `c` that the subcommand of `f` no longer accepts.
fn refused_old_spellings<'a>(
    binary: &str,
    f: &ShownFlag,
    c: &Concept,
    old: impl Iterator<Item = &'a &'static str>,
    help: &dyn Fn(&[&str]) -> Option<String>,
) -> Vec<String> {
    let sub = f.subcommand.as_deref();
    old.filter(|old| {
        let args: Vec<&str> = sub.into_iter().chain([**old, c.sample, "--help"]).collect();
        help(&args).is_none()
    })
    .map(|old| {
        format!(
            "`{binary} {} {old} {}` is refused: keep {old} as a hidden alias of {} so that \
                 scripts keep working",
            sub.unwrap_or_default(),
            c.sample,
            c.flag
        )
    })
    .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    const TOP: &str = "A tool.\n      --not-an-option <X> in the text above Usage\n\nUsage: x <COMMAND>\n\nCommands:\n  serve  Serve\n  encode  Encode\n  help  \
                       Print this\n\nOptions:\n  -v, --verbose  Debug\n  -h, --help  Print help\n";

    /// A fake binary whose `serve` and `encode` pages are given; `accepts` lists the older
    /// spellings its parser still takes.
    fn binary<'a>(
        serve: &'a str,
        encode: &'a str,
        accepts: &'a [&'a str],
    ) -> impl Fn(&[&str]) -> Option<String> + 'a {
        move |args: &[&str]| match args {
            ["--help"] => Some(TOP.to_owned()),
            ["serve", "--help"] => Some(format!("Usage: x serve\n\nOptions:\n{serve}")),
            ["encode", "--help"] => Some(format!("Usage: x encode\n\nOptions:\n{encode}")),
            [_, old, _, "--help"] => accepts.contains(old).then(String::new),
            _ => None,
        }
    }

    #[test]
    fn option_lines_give_flags_and_values_but_descriptions_do_not() {
        let page = "About --x\n      --before <USAGE>\nUsage: x [OPTIONS]\nOptions:\n      --listen <HOST:PORT>  Listen address [default: x]\n          \
                    the old --bind is an alias\n  -q, --quiet  Quiet [aliases: --silent, -s]\n      --segments [<FILE|off>]\n  \
                    <DIR>  Output folder\n";
        assert_eq!(
            defined_flags(page),
            [
                ("--listen".to_owned(), Some("HOST:PORT".to_owned())),
                ("--quiet".to_owned(), None),
                ("--silent".to_owned(), None),
                ("--segments".to_owned(), Some("FILE|off".to_owned())),
            ]
        );
    }

    #[test]
    fn one_name_per_concept_passes() {
        let serve = "      --listen <HOST:PORT>  Listen\n      --scene <NAME>  Scene name\n";
        // `--views` is a concept of its own beside `--view-count`: not its alias there.
        let encode = "      --scene-dir <DIR>  Folder\n      --scene-name-free <X>\n      \
                      --views <RULE>\n      --view-count <N>\n";
        let help = binary(serve, encode, &["--addr", "--bind", "--scene"]);
        assert_eq!(check("x", &help), Ok(8));
    }

    #[test]
    fn a_second_name_for_a_concept_fails() {
        let serve = "      --bind <ADDR>  Address to bind\n";
        let help = binary(serve, "", &[]);
        let problems = check("x", &help).unwrap_err();
        assert!(
            problems
                .iter()
                .any(|p| p.contains("--bind, an older spelling of --listen")),
            "{problems:?}"
        );
        // A visible alias is a second visible name too.
        let serve = "      --listen <HOST:PORT>  Listen [aliases: --addr]\n";
        let problems = check("x", &binary(serve, "", &["--addr", "--bind"])).unwrap_err();
        assert_eq!(problems.len(), 1, "{problems:?}");
        assert!(problems[0].contains("shows --addr, an older spelling of --listen"));
    }

    #[test]
    fn a_second_meaning_for_a_name_fails() {
        let serve = "      --scene <NAME>  Scene name\n";
        let encode = "      --scene <DIR>  Scene folder\n";
        let problems = check("x", &binary(serve, encode, &[])).unwrap_err();
        assert_eq!(problems.len(), 1, "{problems:?}");
        assert!(
            problems[0].contains("`x encode` shows --scene <DIR>"),
            "{problems:?}"
        );
        let serve = "      --store <STORE>  Store\n";
        let encode = "      --store <FILE>  Store\n";
        let problems = check("x", &binary(serve, encode, &[])).unwrap_err();
        assert!(problems[0].contains("--store takes <FILE> in `encode` but <STORE> in `serve`"));
    }

    #[test]
    fn an_older_spelling_that_no_longer_parses_fails() {
        let serve = "      --listen <HOST:PORT>  Listen\n";
        let problems = check("x", &binary(serve, "", &["--addr"])).unwrap_err();
        assert_eq!(problems.len(), 1, "{problems:?}");
        assert!(problems[0].contains("`x serve --bind 127.0.0.1:8080` is refused"));
    }
}
