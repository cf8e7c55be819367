//! `slag-shards`: the shard stage on its own (`partition`, `serve`, `export`, `keygen`), the same
//! subcommands and flags as `slag-encoder partition|serve|export|keygen`, without the encoder's
//! GPU and ONNX Runtime dependencies: what a shard host needs.

use clap::{Parser, Subcommand};
use slag_shards::cli;

/// slag-shards: cut per-Gaussian embeddings into spatial shards, serve or export them.
///
///   slag-shards partition --embeddings OUT/mixture.safetensors --shard-store STORE --scene lab
///   slag-shards serve --shard-store STORE --listen 0.0.0.0:8090
///   slag-shards export --shard-store STORE --scene lab --out DIR
#[derive(Parser)]
#[command(version, about, long_about, verbatim_doc_comment)]
struct Cli {
    #[command(flatten)]
    global: slag_common::cli::process::GlobalArgs,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
#[allow(clippy::large_enum_variant)] // parsed once per process
enum Command {
    /// Cut an embeddings file into spatial shards (ground-plane k-d tiles) in a sled store.
    Partition(cli::PartitionArgs),
    /// Serve a store's manifests and shards over HTTP (ETag, Range).
    Serve(cli::ServeArgs),
    /// Write a scene's manifest.json + shard files for any static host or object store.
    Export(cli::ExportArgs),
    /// Write a new Ed25519 key pair for signing manifests (--signing-key).
    Keygen(cli::KeygenArgs),
}

fn main() -> std::process::ExitCode {
    slag_common::cli::deprecated::note_deprecated();
    let args = Cli::parse();
    let verbose = args.global.verbose;
    slag_common::cli::process::init_logging(verbose);
    let result = match &args.command {
        Command::Partition(a) => cli::run_partition(a),
        Command::Serve(a) => cli::run_serve(a),
        Command::Export(a) => cli::run_export(a),
        Command::Keygen(a) => cli::run_keygen(a),
    };
    slag_common::cli::process::exit_code(result, cli::hint, verbose)
}

#[cfg(test)]
mod flag_names {
    /// Every flag name of this binary, hidden aliases included, keeps one meaning across the slag
    /// binaries, and every meaning one name ([`slag_common::flag_names`]).
    #[test]
    fn each_flag_name_has_one_meaning_across_the_binaries() {
        use clap::CommandFactory;
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        slag_common::flag_names::assert_one_meaning("slag-shards", &super::Cli::command(), &root);
    }
}
