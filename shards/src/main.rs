//! `slag-shards`: the shard stage on its own (`partition`, `serve`, `export`, `keygen`), the same
//! subcommands and flags as `slag-encoder partition|serve|export|keygen`, without the encoder's
//! GPU and ONNX Runtime dependencies: what a shard host needs.

use clap::{Parser, Subcommand};
use slag_shards::cli;

/// slag-shards: cut per-Gaussian embeddings into spatial shards, serve or export them.
///
///   slag-shards partition --embeddings OUT/embeddings.safetensors --store STORE --scene lab
///   slag-shards serve --store STORE --listen 0.0.0.0:8090
///   slag-shards export --store STORE --scene lab DIR
#[derive(Parser)]
#[command(version, about, long_about, verbatim_doc_comment)]
struct Cli {
    #[command(flatten)]
    global: cli::GlobalArgs,
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
    let args = Cli::parse();
    cli::init_logging(args.global.verbose);
    let result = match &args.command {
        Command::Partition(a) => cli::run_partition(a),
        Command::Serve(a) => cli::run_serve(a),
        Command::Export(a) => cli::run_export(a),
        Command::Keygen(a) => cli::run_keygen(a),
    };
    cli::exit_code(result, cli::hint)
}
