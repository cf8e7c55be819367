//! What every slag binary does the same way around its subcommand: the options it takes at the
//! top ([`GlobalArgs`]), its log set-up ([`init_logging`]) and its exit status ([`exit_code`]).

/// Options every subcommand of `slag-encoder`, `slag-shards`, `slag-edge` and `slag-bench`
/// takes.
#[derive(Debug, Clone, Copy, Default, clap::Args)]
pub struct GlobalArgs {
    /// More detail: debug logging (unless RUST_LOG says otherwise) and, on an error, its debug
    /// form (with the backtrace when RUST_BACKTRACE=1) after the one-line message.
    #[arg(long, short, global = true)]
    pub verbose: bool,
}

/// Sets up `tracing` on stderr: the filter of `RUST_LOG`, else `info` (`debug` with
/// `verbose`), coloured only on a terminal without `NO_COLOR` ([`crate::term::stderr_ansi`]).
/// A second call changes nothing.
pub fn init_logging(verbose: bool) {
    let default = if verbose { "debug" } else { "info" };
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(crate::term::stderr_ansi())
        .try_init();
}

/// What a failed subcommand prints on stderr: `error:` and the error with its causes on one
/// line ([`crate::error::causes_once`]), `hint:` and what the command line can do about it where
/// `hint` knows, and with `verbose` the error's debug form (anyhow's adds the backtrace when
/// `RUST_BACKTRACE=1`).
pub fn error_report<E>(e: &E, hint: Option<String>, verbose: bool) -> String
where
    E: AsRef<dyn std::error::Error + Send + Sync + 'static> + std::fmt::Debug,
{
    let mut out = format!("error: {}", crate::error::causes_once(e.as_ref()));
    if let Some(h) = hint {
        out.push_str(&format!("\nhint: {h}"));
    }
    if verbose {
        out.push_str(&format!("\n\n{e:?}"));
    }
    out
}

/// The process's exit status for a subcommand's `result`: success, or failure after printing
/// its [`error_report`] on stderr. `hint` is the binary's own: the flag that acts on a library
/// error (the library's messages name no flag).
pub fn exit_code<E>(
    result: Result<(), E>,
    hint: impl Fn(&E) -> Option<String>,
    verbose: bool,
) -> std::process::ExitCode
where
    E: AsRef<dyn std::error::Error + Send + Sync + 'static> + std::fmt::Debug,
{
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("{}", error_report(&e, hint(&e), verbose));
            std::process::ExitCode::FAILURE
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An error with one cause, as a subcommand returns it.
    #[derive(Debug)]
    struct Failed(Box<dyn std::error::Error + Send + Sync>);

    impl AsRef<dyn std::error::Error + Send + Sync + 'static> for Failed {
        fn as_ref(&self) -> &(dyn std::error::Error + Send + Sync + 'static) {
            self.0.as_ref()
        }
    }

    #[test]
    fn an_error_is_one_line_with_its_hint_and_its_debug_form_only_when_verbose() {
        let e = Failed(Box::new(crate::Error::param("up", "w", "x, y or z")));
        let quiet = error_report(&e, Some("pass --up z".into()), false);
        assert!(quiet.starts_with("error: "), "{quiet}");
        assert_eq!(quiet.lines().count(), 2, "{quiet}");
        assert!(quiet.ends_with("\nhint: pass --up z"), "{quiet}");
        let verbose = error_report(&e, None, true);
        assert!(verbose.contains("\n\nFailed("), "{verbose}");
        assert!(!verbose.contains("hint:"), "{verbose}");
    }

    #[test]
    fn exit_status_follows_the_result() {
        let ok: Result<(), Failed> = Ok(());
        assert_eq!(
            exit_code(ok, |_| None, false),
            std::process::ExitCode::SUCCESS
        );
        let failed = Err(Failed(Box::new(std::io::Error::other("disk"))));
        assert_eq!(
            exit_code(failed, |_| None, false),
            std::process::ExitCode::FAILURE
        );
    }
}
