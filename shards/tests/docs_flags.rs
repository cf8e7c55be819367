//! The manual against the command line of `slag-shards` ([`slag_common::doc_flags::assert_no_problems`]).

#[test]
fn the_manual_shows_only_flags_that_exist() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let exe = env!("CARGO_BIN_EXE_slag-shards");
    slag_common::doc_flags::assert_no_problems("slag-shards", exe, &root);
}
