//! Shared helpers for slag's end-to-end tests: fixture paths and CLI-equivalent argument parsing.

use std::path::PathBuf;

use clap::Parser;
use slag_encoder::cli::encode::EncodeArgs;

/// `../shared` (or `$SLAG_SHARED`).
pub fn shared() -> PathBuf {
    slag_common::paths::shared_dir()
}

/// A file under `../shared/fixtures`.
pub fn fixture(rel: &str) -> PathBuf {
    shared().join("fixtures").join(rel)
}

/// The embedded default scene shipped in the repository.
pub fn default_scene() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join("data")
        .join("snowmiku-mini")
}

#[derive(Parser)]
struct EncodeCli {
    #[command(flatten)]
    args: EncodeArgs,
}

/// Parses `slag-encoder encode` arguments exactly as the binary does.
pub fn encode_args(args: &[&str]) -> EncodeArgs {
    let argv = std::iter::once("encode").chain(args.iter().copied());
    match EncodeCli::try_parse_from(argv) {
        Ok(c) => c.args,
        Err(e) => panic!("bad test arguments: {e}"),
    }
}

/// Runs `slag-encoder encode` as the binary would on `scene` with the arguments of `line`
/// (whitespace-separated; `{F}` stands for `../shared/fixtures`), quietly, into `out`.
pub fn encode_line(
    scene: &std::path::Path,
    line: &str,
    out: &std::path::Path,
) -> anyhow::Result<slag_encoder::report::Report> {
    let fixtures = shared().join("fixtures").display().to_string();
    let mut argv: Vec<String> = ["--scene", &scene.display().to_string(), "--quiet", "--out"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    argv.push(out.display().to_string());
    argv.extend(line.split_whitespace().map(|t| t.replace("{F}", &fixtures)));
    let args = encode_args(&argv.iter().map(String::as_str).collect::<Vec<_>>());
    slag_encoder::cli::encode::run(&args)
}
