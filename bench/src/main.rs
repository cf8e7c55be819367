//! `slag-bench`: one subcommand per study (see the library docs of `slag_bench`).

use clap::{Parser, Subcommand};

/// slag studies (speed/accuracy trade-offs, …), reproducible by one command each.
#[derive(Parser)]
#[command(name = "slag-bench", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Speed/accuracy trade study on a real scene with color-clip: writes
    /// OUT/tradeoffs.md and OUT/tradeoffs.csv.
    Tradeoffs(slag_bench::tradeoffs::TradeoffArgs),
}

fn main() -> anyhow::Result<()> {
    slag_encoder::cli::init_logging(false);
    let cli = Cli::parse();
    match cli.command {
        Command::Tradeoffs(a) => {
            let summary = slag_bench::tradeoffs::run(&a)?;
            println!("{summary}");
        }
    }
    Ok(())
}
