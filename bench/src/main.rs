//! `slag-bench`: one subcommand per study (see the library docs of `slag_bench`).

use clap::{Parser, Subcommand};

/// slag studies (speed/accuracy trade-offs, stage floors, GPU scaling), one command each.
#[derive(Parser)]
#[command(name = "slag-bench", version, about)]
struct Cli {
    #[command(flatten)]
    global: slag_common::cli::process::GlobalArgs,
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

fn main() -> std::process::ExitCode {
    slag_common::cli::deprecated::note_deprecated();
    let cli = Cli::parse();
    let verbose = cli.global.verbose;
    slag_common::cli::process::init_logging(verbose);
    slag_common::cli::process::exit_code(run(cli.command), |_| None, verbose)
}

/// Runs one study and prints its table.
fn run(command: Command) -> anyhow::Result<()> {
    match command {
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

#[cfg(test)]
mod flag_names {
    /// Every flag name of this binary, hidden aliases included, keeps one meaning across the slag
    /// binaries, and every meaning one name ([`slag_common::flag_names`]).
    #[test]
    fn each_flag_name_has_one_meaning_across_the_binaries() {
        use clap::CommandFactory;
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        slag_common::flag_names::assert_one_meaning("slag-bench", &super::Cli::command(), &root);
    }
}
