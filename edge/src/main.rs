//! `slag-edge`: the robot-side runtime.
//!
//! Placeholder: the commands (`fetch --radius`, `serve`) are specified by the edge issue and are
//! not implemented yet. This binary only parses its arguments and says so, so the workspace and the
//! aarch64 cross build have a target from day one.

use clap::{Parser, Subcommand};

/// slag-edge: download the shards around the robot and answer text queries over HTTP.
#[derive(Parser)]
#[command(version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Download the shards within a radius (not implemented yet).
    Fetch,
    /// Serve text queries over HTTP (not implemented yet).
    Serve,
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    let what = match cli.command {
        Command::Fetch => "fetch",
        Command::Serve => "serve",
    };
    anyhow::bail!("slag-edge {what} is not implemented yet: the edge runtime is a later milestone")
}
