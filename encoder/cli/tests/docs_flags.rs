//! The command line of `slag-encoder` as its `--help` shows it (`slag_common::doc_flags::problems`):
//! every `slag-encoder …` command line that README.md and docs/guide/ show names a subcommand and
//! flags it has, and every flag of every subcommand keeps one name per thing across the slag
//! binaries (`slag_common::flag_names`).

#[test]
fn the_manual_shows_only_flags_that_exist_each_with_one_name() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let exe = env!("CARGO_BIN_EXE_slag-encoder");
    let problems = slag_common::doc_flags::problems("slag-encoder", exe, &root);
    assert!(
        problems.is_empty(),
        "`slag-encoder`:\n{}",
        problems.join("\n")
    );
}
