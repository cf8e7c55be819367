//! Fault injection at durability boundaries, for crash tests: one seam shared by the edge store
//! and fetch (`slag-edge`), the shard store and partition (`slag-shards`) and
//! [`crate::io::write_atomic`].
//!
//! A *durability boundary* is the moment right after one step that changes what is on disk: a
//! write into a file, an `fsync`, a `rename`, a folder sync, a file removal, a sled insert,
//! transaction or flush. Each such step calls [`boundary`] (or [`boundary_in`]) with a stable
//! name (`site:step`, e.g. `store.manifest_copy:rename`); a crash test stops the process at each
//! one in turn and checks what a restart finds.
//!
//! Driven by the environment, read once per process:
//! - `SLAG_FAULT_EXIT_AT=<n>`: the process exits with status [`FAULT_EXIT_STATUS`] (137, what a
//!   shell reports for `kill -9`) at the n-th boundary it passes (1-based), without unwinding,
//!   flushing or running destructors, as a crash would; the boundary's number and name go to
//!   stderr first;
//! - `SLAG_FAULT_LIST=<path>`: each boundary passed appends one line `<n> <name>` to `path`
//!   (created if needed; written before any exit at that boundary), so a test learns how many
//!   boundaries a run passes and which, and numbers its kills from that instead of a fixed count.
//!   The file is opened in append mode: several processes (or several runs) may share it;
//! - `SLAG_FAULT_ENOSPC_AT=<n>`: the n-th call of [`enospc`] (the edge's partial-file writes)
//!   fails as if the disk were full.
//!
//! Unset or blank (the normal case), [`boundary`] and [`enospc`] cost one atomic load each.
//! A value that is not a positive number counts as unset.

use std::io::Write;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, OnceLock};

/// Exit status of a process stopped by `SLAG_FAULT_EXIT_AT` (128 + SIGKILL).
pub const FAULT_EXIT_STATUS: i32 = 137;

/// Variable naming the boundary at which the process exits (module doc).
pub const EXIT_AT_VAR: &str = "SLAG_FAULT_EXIT_AT";
/// Variable naming the file that lists the boundaries passed (module doc).
pub const LIST_VAR: &str = "SLAG_FAULT_LIST";
/// Variable naming the partial-file write that fails as if the disk were full (module doc).
pub const ENOSPC_AT_VAR: &str = "SLAG_FAULT_ENOSPC_AT";

/// What a process stopped by `SLAG_FAULT_EXIT_AT` writes to stderr before the boundary's number
/// and, in parentheses, its name ([`stopped_at`] reads it back).
const EXIT_MESSAGE: &str = "exiting at boundary";

/// The boundary hook's settings, read from the environment on first use.
struct Boundaries {
    exit_at: Option<u64>,
    list: Option<Mutex<std::fs::File>>,
    passed: AtomicU64,
}

/// A positive number from `var`; `None` when unset, blank, 0 or not a number.
fn env_count(var: &str) -> Option<u64> {
    std::env::var(var)
        .ok()
        .and_then(|v| v.trim().parse::<u64>().ok())
        .filter(|&n| n > 0)
}

/// The hook's settings; `None` (nothing to do) when neither variable is set.
fn boundaries() -> Option<&'static Boundaries> {
    static B: OnceLock<Option<Boundaries>> = OnceLock::new();
    B.get_or_init(|| {
        let exit_at = env_count(EXIT_AT_VAR);
        let list = std::env::var_os(LIST_VAR)
            .filter(|p| !p.is_empty())
            .map(|path| {
                std::fs::OpenOptions::new()
                    .create(true)
                    .append(true)
                    .open(&path)
                    .unwrap_or_else(|e| {
                        // A test asked for the list and would count nothing: stop loudly.
                        eprintln!("{LIST_VAR}={}: cannot open it: {e}", path.to_string_lossy());
                        std::process::exit(FAULT_EXIT_STATUS)
                    })
            });
        (exit_at.is_some() || list.is_some()).then(|| Boundaries {
            exit_at,
            list: list.map(Mutex::new),
            passed: AtomicU64::new(0),
        })
    })
    .as_ref()
}

/// A durability boundary named `name` (module doc): counts it, lists it under
/// `SLAG_FAULT_LIST`, and exits the process with [`FAULT_EXIT_STATUS`] when it is the one
/// `SLAG_FAULT_EXIT_AT` names. Call it right after the step it names has returned.
pub fn boundary(name: &str) {
    if let Some(b) = boundaries() {
        pass(b, name, None);
    }
}

/// [`boundary`] named `site:step` (e.g. `store.manifest_copy` and `rename`), for a helper that
/// performs the same steps for several callers; nothing is formatted unless a variable is set.
pub fn boundary_in(site: &str, step: &str) {
    if let Some(b) = boundaries() {
        pass(b, site, Some(step));
    }
}

fn pass(b: &Boundaries, site: &str, step: Option<&str>) {
    let n = b.passed.fetch_add(1, Ordering::SeqCst) + 1;
    let name = match step {
        Some(s) => format!("{site}:{s}"),
        None => site.to_string(),
    };
    if let Some(list) = &b.list {
        let mut f = list
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        // One write per line, so that lines of processes sharing the file never interleave.
        let _ = f.write_all(format!("{n} {name}\n").as_bytes());
    }
    if b.exit_at == Some(n) {
        eprintln!("{EXIT_AT_VAR}={n}: {EXIT_MESSAGE} {n} ({name})");
        std::process::exit(FAULT_EXIT_STATUS);
    }
}

/// The disk-full hook (module doc): the n-th call of the process, n from
/// `SLAG_FAULT_ENOSPC_AT`, returns the error a full disk gives (`ENOSPC`) instead of `Ok`. Call
/// it before a write that a full disk would refuse. Unset, it costs one atomic load.
///
/// Errors: [`std::io::Error`] of raw OS error 28 (`ENOSPC` on Linux) at that call.
pub fn enospc() -> std::io::Result<()> {
    static AT: OnceLock<Option<u64>> = OnceLock::new();
    static CALLS: AtomicU64 = AtomicU64::new(0);
    let Some(at) = *AT.get_or_init(|| env_count(ENOSPC_AT_VAR)) else {
        return Ok(());
    };
    if CALLS.fetch_add(1, Ordering::SeqCst) + 1 == at {
        return Err(std::io::Error::from_raw_os_error(28));
    }
    Ok(())
}

/// Reads a list written under `SLAG_FAULT_LIST`: the names of the boundaries passed, in the
/// order passed (lines that are not `<n> <name>` are skipped).
///
/// Errors: the file cannot be read ([`crate::Error::Io`]); a missing file reads as empty.
pub fn read_list(path: &std::path::Path) -> crate::Result<Vec<String>> {
    let text = match std::fs::read_to_string(path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(crate::Error::io(path, e)),
    };
    Ok(text
        .lines()
        .filter_map(|l| l.split_once(' '))
        .filter(|(n, _)| n.parse::<u64>().is_ok())
        .map(|(_, name)| name.to_string())
        .collect())
}

/// The name of the boundary at which a process stopped under `SLAG_FAULT_EXIT_AT`, read from its
/// stderr; `None` when it holds no such line (the process did not stop at a boundary).
pub fn stopped_at(stderr: &str) -> Option<String> {
    let line = stderr.lines().find(|l| l.contains(EXIT_MESSAGE))?;
    Some(line.rsplit_once('(')?.1.strip_suffix(')')?.to_string())
}

#[cfg(test)]
mod tests {
    use super::{EXIT_AT_VAR, EXIT_MESSAGE, read_list, stopped_at};

    #[test]
    fn the_stop_line_names_its_boundary_and_lists_read_back_in_order() {
        let err = format!("INFO x\n{EXIT_AT_VAR}=3: {EXIT_MESSAGE} 3 (store.flush:db)\n");
        assert_eq!(stopped_at(&err).as_deref(), Some("store.flush:db"));
        assert_eq!(stopped_at("exited normally"), None);
        let dir = tempfile::tempdir().expect("tmp");
        let p = dir.path().join("list.txt");
        assert!(read_list(&p).expect("missing reads as empty").is_empty());
        std::fs::write(&p, "1 a:write\nnot a line\n2 a:fsync\n").expect("write");
        assert_eq!(read_list(&p).expect("read"), ["a:write", "a:fsync"]);
    }
}
