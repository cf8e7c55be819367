//! Every `slag-edge …` command line that README.md and docs/guide/ show names a subcommand and flags
//! that `slag-edge` has (`slag_common::doc_flags`).
#![allow(clippy::unwrap_used)]

use std::path::Path;
use std::process::Command;

#[test]
fn the_manual_shows_only_flags_that_exist() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    // Under qemu (cross build) the binary is started through `$SLAG_TEST_RUNNER`.
    let runner = std::env::var("SLAG_TEST_RUNNER").unwrap_or_default();
    let help = |args: &[&str]| {
        let bin = env!("CARGO_BIN_EXE_slag-edge");
        let mut parts = runner.split_whitespace();
        let mut c = match parts.next() {
            Some(r) => {
                let mut c = Command::new(r);
                c.args(parts).arg(bin);
                c
            }
            None => Command::new(bin),
        };
        let out = c.args(args).output().unwrap();
        assert!(out.status.success(), "slag-edge {args:?} failed");
        String::from_utf8_lossy(&out.stdout).into_owned()
    };
    match slag_common::doc_flags::check("slag-edge", &root, &help) {
        Ok(n) => assert!(n > 0),
        Err(problems) => panic!(
            "the manual shows what `slag-edge` does not have:\n{}",
            problems.join("\n")
        ),
    }
}
