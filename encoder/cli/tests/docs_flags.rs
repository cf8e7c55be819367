//! Every `slag-encoder …` command line that README.md and docs/guide/ show names a subcommand and flags
//! that `slag-encoder` has (`slag_common::doc_flags`).
#![allow(clippy::unwrap_used)]

use std::path::Path;
use std::process::Command;

#[test]
fn the_manual_shows_only_flags_that_exist() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let help = |args: &[&str]| {
        let out = Command::new(env!("CARGO_BIN_EXE_slag-encoder"))
            .args(args)
            .output()
            .unwrap();
        assert!(out.status.success(), "slag-encoder {args:?} failed");
        String::from_utf8_lossy(&out.stdout).into_owned()
    };
    match slag_common::doc_flags::check("slag-encoder", &root, &help) {
        Ok(n) => assert!(n > 0),
        Err(problems) => panic!(
            "the manual shows what `slag-encoder` does not have:\n{}",
            problems.join("\n")
        ),
    }
}
