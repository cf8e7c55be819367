//! Older flag spellings the binaries still accept, so that scripts keep working, each with the
//! name to use instead. A spelling stays only where it names nothing else in any slag binary, so
//! it reads the same wherever it appears on a command line, and a binary notes its use on stderr
//! before parsing ([`note_deprecated`]).

use std::ffi::OsString;

/// An older spelling of a flag and the flag that replaces it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Deprecated {
    /// The older spelling, `--bind`.
    pub old: &'static str,
    /// The flag to use instead, `--listen`.
    pub new: &'static str,
    /// How to move over, where more than the name changes.
    pub how: &'static str,
}

/// Every older spelling still accepted (each a hidden alias, or a hidden flag of its own when its
/// value changed form).
pub const DEPRECATED: &[Deprecated] = &[
    Deprecated {
        old: "--addr",
        new: "--listen",
        how: "",
    },
    Deprecated {
        old: "--bind",
        new: "--listen",
        how: "",
    },
    Deprecated {
        old: "--text-model",
        new: "--clip-textual",
        how: "",
    },
    Deprecated {
        old: "--mixture",
        new: "--embeddings",
        how: " (it reads either form, by the file's header)",
    },
    Deprecated {
        old: "--mixture-slots",
        new: "--mixture-keep",
        how: "",
    },
    Deprecated {
        old: "--pf",
        new: "--prediction-filtering",
        how: "",
    },
    Deprecated {
        old: "--token",
        new: "--shard-token-file",
        how: " (a file whose first line is the token, or env SLAG_SHARD_TOKEN: a token on \
              the command line shows in the process list)",
    },
];

/// The older spelling `flag` (`--bind`, or `--bind=ADDR`) stands for, if it is one.
pub fn lookup(flag: &str) -> Option<&'static Deprecated> {
    let name = flag.split_once('=').map_or(flag, |(name, _)| name);
    DEPRECATED.iter().find(|d| d.old == name)
}

/// One note per older spelling among `args` (a command line without the program's name, up to
/// `--`), naming the flag to use instead.
pub fn deprecation_notes(args: impl IntoIterator<Item = OsString>) -> Vec<String> {
    args.into_iter()
        .take_while(|a| a != "--")
        .filter_map(|a| a.to_str().and_then(lookup))
        .map(|d| {
            format!(
                "note: {} is deprecated and will be removed: use {}{}",
                d.old, d.new, d.how
            )
        })
        .collect()
}

/// Prints [`deprecation_notes`] of the process's own command line on stderr.
pub fn note_deprecated() {
    for note in deprecation_notes(std::env::args_os().skip(1)) {
        eprintln!("{note}");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn notes(args: &[&str]) -> Vec<String> {
        deprecation_notes(args.iter().map(OsString::from))
    }

    #[test]
    fn older_spellings_are_noted_with_their_new_name() {
        let got = notes(&["serve", "--bind=0.0.0.0:1", "--text-model", "m.onnx"]);
        assert_eq!(got.len(), 2, "{got:?}");
        assert!(got[0].contains("--bind is deprecated") && got[0].contains("use --listen"));
        assert!(got[1].contains("use --clip-textual"));
    }

    #[test]
    fn current_names_values_and_arguments_after_the_separator_are_not() {
        assert!(notes(&["serve", "--listen", "--bind-x", "--", "--bind"]).is_empty());
    }

    #[test]
    fn an_old_spelling_is_never_a_current_name() {
        for d in DEPRECATED {
            assert!(lookup(d.new).is_none(), "{} is both", d.new);
            assert!(d.old.starts_with("--") && d.new.starts_with("--"));
        }
    }
}
