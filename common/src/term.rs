//! What the binaries' log output may assume about the terminal.
//!
//! Log lines go to stderr. Colour codes help a person at a terminal and garble everything else
//! (`slag-edge serve 2> log`, journald, CI logs), so they are written only when stderr is a
//! terminal and `NO_COLOR` (<https://no-color.org>) is unset or empty.

use std::ffi::OsStr;
use std::io::IsTerminal;

/// Whether log lines on stderr may carry ANSI colour codes: stderr is a terminal and `NO_COLOR`
/// is unset or empty. Each binary passes it to its `tracing` subscriber (`with_ansi`).
pub fn stderr_ansi() -> bool {
    ansi_allowed(
        std::io::stderr().is_terminal(),
        std::env::var_os("NO_COLOR").as_deref(),
    )
}

/// The rule behind [`stderr_ansi`]: colour only on a terminal, and never when `no_color` (the
/// value of `NO_COLOR`) is present and not empty.
pub fn ansi_allowed(is_terminal: bool, no_color: Option<&OsStr>) -> bool {
    is_terminal && no_color.is_none_or(|v| v.is_empty())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn colour_only_on_a_terminal_without_no_color() {
        assert!(ansi_allowed(true, None));
        assert!(ansi_allowed(true, Some(OsStr::new(""))));
        assert!(!ansi_allowed(true, Some(OsStr::new("1"))));
        assert!(!ansi_allowed(false, None));
        assert!(!ansi_allowed(false, Some(OsStr::new("1"))));
    }
}
