//! Helpers shared by the `slag-encoder` binary's integration tests.
#![allow(dead_code, clippy::unwrap_used)]

/// `slag-encoder` (this package's binary), run through `$SLAG_TEST_RUNNER` when it is set (e.g.
/// `qemu-aarch64 -L /usr/aarch64-linux-gnu` for a cross build).
pub fn slag_encoder() -> std::process::Command {
    let bin = env!("CARGO_BIN_EXE_slag-encoder");
    match std::env::var("SLAG_TEST_RUNNER") {
        Ok(r) if !r.trim().is_empty() => {
            let mut parts = r.split_whitespace();
            let mut c = std::process::Command::new(parts.next().unwrap());
            c.args(parts).arg(bin);
            c
        }
        _ => std::process::Command::new(bin),
    }
}

/// Panics with the command's stderr unless it exited with status 0.
pub fn assert_success(o: &std::process::Output) {
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
}
