//! `slag-bench`: one subcommand per study (see the library docs of `slag_bench`).

use clap::{Parser, Subcommand};

/// slag studies (speed/accuracy trade-offs, stage floors, GPU scaling), one command each.
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
    Tradeoffs(Box<slag_bench::tradeoffs::TradeoffArgs>),
    /// Each encoder stage's time per image against its floor on this machine (needs the facts
    /// JSON of scripts/lab/device_facts.py; see scripts/lab/device-scaling.sh stages).
    Stages(Box<slag_bench::stages::StagesArgs>),
    /// The same encode on 1, 2, 4 … GPUs of this host: speed-up and efficiency table.
    Scaling(Box<slag_bench::scaling::ScalingArgs>),
    /// The reduction over images in its two loop orders on a synthetic store of a real scene's
    /// size (same sums bit for bit), plus the embeddings write.
    Reduce(Box<slag_bench::reduce::ReduceArgs>),
    /// Each ONNX model of the encode (CLIP tower per crop, SAM encoder and decoder per image)
    /// timed alone on real images, and variants of a model compared with the first.
    Models(Box<slag_bench::models::ModelsArgs>),
}

fn main() -> anyhow::Result<()> {
    slag_shards::cli::init_logging(false);
    let cli = Cli::parse();
    match cli.command {
        Command::Tradeoffs(a) => {
            let summary = slag_bench::tradeoffs::run(&a)?;
            println!("{summary}");
        }
        Command::Stages(a) => println!("{}", slag_bench::stages::run(&a)?),
        Command::Scaling(a) => println!("{}", slag_bench::scaling::run(&a)?),
        Command::Reduce(a) => println!("{}", slag_bench::reduce::run(&a)?),
        Command::Models(a) => println!("{}", slag_bench::models::run(&a)?),
    }
    Ok(())
}
