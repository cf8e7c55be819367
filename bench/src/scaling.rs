//! `slag-bench scaling`: the same encode on 1, 2, … GPUs of one host (issue 5, item 2): wall
//! time, images per second, speed-up and efficiency against the first count, and each GPU's
//! rasterizer busy share (dynamic balancing shows as even shares).
//!
//! Efficiency follows the usual definition: `t(g0)·g0 / (t(g)·g)` with `g0` the first count
//! (normally 1). Each count is one run (the issue asks for one run each); the encode's outputs go
//! to `--out`/g<N>/.

use anyhow::Context;
use slag_encoder::cli::encode::{EncodeArgs, GpuCount};
use slag_encoder::report::Report;

/// Arguments of `slag-bench scaling`.
#[derive(Debug, Clone, clap::Args)]
pub struct ScalingArgs {
    /// The encode run (same flags as `slag-encoder encode`; its `--gpus` is replaced per run and
    /// `--out` gets one subfolder per count).
    #[command(flatten)]
    pub encode: EncodeArgs,
    /// GPU counts, comma-separated, ascending (e.g. 1,2,4).
    #[arg(long, value_delimiter = ',', default_value = "1,2,4")]
    pub counts: Vec<usize>,
    /// Markdown file the table is written to (default: <out>/scaling.md).
    #[arg(long)]
    pub table: Option<std::path::PathBuf>,
}

/// The scaling table of finished runs `(gpus, report)`, first entry the baseline.
pub fn table(runs: &[(usize, Report)]) -> String {
    let mut s = String::from(
        "| GPUs | wall s | images/s | speed-up | efficiency | raster busy % per GPU | images per GPU |\n\
         |---:|---:|---:|---:|---:|---|---|\n",
    );
    let Some((g0, r0)) = runs.first() else {
        return s;
    };
    let t0 = r0.timings.total * *g0 as f64;
    for (g, r) in runs {
        let t = r.timings.total.max(1e-9);
        let n = r.counts.views_used as f64;
        let backs: Vec<_> = r
            .workers
            .iter()
            .filter(|w| w.name.starts_with("raster"))
            .collect();
        let busy: Vec<String> = backs
            .iter()
            .map(|w| format!("{:.0}", 100.0 * w.busy_s / t))
            .collect();
        let imgs: Vec<String> = backs.iter().map(|w| w.images.to_string()).collect();
        s += &format!(
            "| {g} | {t:.1} | {:.2} | {:.2} | {:.2} | {} | {} |\n",
            n / t,
            t0 / t / *g0 as f64,
            t0 / t / *g as f64,
            busy.join(" "),
            imgs.join("/")
        );
    }
    s
}

/// Runs the encode once per count and writes the table.
///
/// Errors: empty or non-ascending counts, fewer GPUs than asked, encode errors.
pub fn run(a: &ScalingArgs) -> anyhow::Result<String> {
    if a.counts.is_empty() || a.counts.contains(&0) || !a.counts.is_sorted() {
        anyhow::bail!("--counts needs ascending GPU counts >= 1, e.g. --counts 1,2,4");
    }
    let mut runs = Vec::new();
    for &g in &a.counts {
        let mut e = a.encode.clone();
        e.gpus = GpuCount::Count(g);
        e.out = a.encode.out.join(format!("g{g}"));
        let r =
            slag_encoder::cli::encode::run(&e).with_context(|| format!("encode on {g} GPU(s)"))?;
        eprintln!("{g} GPU(s): {:.1} s", r.timings.total);
        runs.push((g, r));
    }
    let md = format!(
        "# Scaling over GPUs of one host\n\n`{}`\n\n{}",
        std::iter::once("slag-bench".to_string())
            .chain(std::env::args().skip(1))
            .collect::<Vec<_>>()
            .join(" "),
        table(&runs)
    );
    let path = a
        .table
        .clone()
        .unwrap_or_else(|| a.encode.out.join("scaling.md"));
    slag_common::embeddings::write_atomic(&path, md.as_bytes())?;
    Ok(md)
}
