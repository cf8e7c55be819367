//! Every `slag-shards …` command line that README.md and docs/guide/ show names a subcommand and flags
//! that `slag-shards` has (`slag_common::doc_flags`).

#[test]
fn the_manual_shows_only_flags_that_exist() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let bin = std::path::Path::new(env!("CARGO_BIN_EXE_slag-shards"));
    slag_common::doc_flags::check_binary("slag-shards", bin, &root)
        .unwrap_or_else(|e| panic!("{e}"));
}
