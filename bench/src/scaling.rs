//! `slag-bench scaling`: the same encode on 1, 2, … GPUs of one host: wall
//! time, images per second, speed-up and efficiency against the first count, and each GPU's
//! rasterizer busy share (dynamic balancing shows as even shares), and where the wall goes besides
//! the images: the fill (when the last GPU's rasterizer got its first image), the drain (the
//! spread of the rasterizers' last image ends) and the serial tail after the last image (the
//! reduction to `E_k` and the write).
//!
//! Efficiency follows the usual definition: `t(g0)·g0 / (t(g)·g)` with `g0` the first count
//! (normally 1). Each count is one run, not the best of several (repeat the command to see the spread); the
//! encode's outputs go to `--out`/g<N>/.

use anyhow::Context;
use slag_common::table::Table;
use slag_encoder::config::{EncodeConfig, GpuCount};
use slag_encoder::pipeline::Encoder;
use slag_encoder::report::Report;

use slag_encoder::args::EncodeArgs;

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
    let mut table = Table::with_header("GPUs | wall s | images/s | speed-up | efficiency | raster busy % per GPU | images per GPU | first image s (last GPU) | last images end s (spread) | after the last image s")
    .right([0, 1, 2, 3, 4, 7, 9]);
    let Some((g0, r0)) = runs.first() else {
        return table.markdown();
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
        let first = backs.iter().map(|w| w.first_s).fold(0.0, f64::max);
        let last_max = backs.iter().map(|w| w.last_s).fold(0.0, f64::max);
        let last_min = backs.iter().map(|w| w.last_s).fold(f64::INFINITY, f64::min);
        let spread = if backs.is_empty() {
            0.0
        } else {
            last_max - last_min
        };
        table.row([
            g.to_string(),
            format!("{t:.1}"),
            format!("{:.2}", n / t),
            format!("{:.2}", t0 / t / *g0 as f64),
            format!("{:.2}", t0 / t / *g as f64),
            busy.join(" "),
            imgs.join("/"),
            format!("{first:.2}"),
            format!("{last_max:.1} ({spread:.2})"),
            format!("{:.1}", t - last_max),
        ]);
    }
    table.markdown()
}

/// Runs the encode once per count and writes the table.
///
/// Errors: empty or non-ascending counts, fewer GPUs than asked, encode errors.
pub fn run(a: &ScalingArgs) -> anyhow::Result<String> {
    if a.counts.is_empty() || a.counts.contains(&0) || !a.counts.is_sorted() {
        anyhow::bail!("--counts needs ascending GPU counts >= 1, e.g. --counts 1,2,4");
    }
    let base = EncodeConfig::from(&a.encode);
    let mut runs = Vec::new();
    for &g in &a.counts {
        let mut e = base.clone();
        e.execution.gpus = GpuCount::Count(g);
        e.output.dir = base.output.dir.join(format!("g{g}"));
        let r = Encoder::new(e)
            .map_err(anyhow::Error::from)
            .and_then(|enc| Ok(enc.run()?))
            .with_context(|| format!("encode on {g} GPU(s)"))?;
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
        .unwrap_or_else(|| base.output.dir.join("scaling.md"));
    slag_common::io::write_atomic(&path, md.as_bytes())?;
    Ok(md)
}

#[cfg(test)]
mod tests {
    use super::*;
    use slag_encoder::report::WorkerShare;

    fn run(total: f64, backs: &[(usize, f64, f64, f64)]) -> Report {
        let mut r = Report::default();
        r.timings.total = total;
        r.counts.views_used = backs.iter().map(|b| b.0).sum();
        r.workers = backs
            .iter()
            .enumerate()
            .map(|(i, &(images, busy_s, first_s, last_s))| WorkerShare {
                name: format!("raster-{i} test"),
                images,
                busy_s,
                first_s,
                last_s,
                raster_phases_ms: None,
            })
            .chain(std::iter::once(WorkerShare {
                name: "front-0".into(),
                images: 9,
                busy_s: 1.0,
                first_s: 0.0,
                last_s: 99.0,
                raster_phases_ms: None,
            }))
            .collect();
        r
    }

    #[test]
    fn efficiency_fill_drain_and_tail_come_from_the_raster_workers() {
        let md = table(&[
            (1, run(40.0, &[(100, 30.0, 0.5, 36.0)])),
            (
                4,
                run(
                    12.5,
                    &[
                        (25, 8.0, 0.5, 9.0),
                        (25, 8.0, 1.5, 10.0),
                        (24, 7.0, 1.0, 9.5),
                        (26, 8.0, 0.7, 9.8),
                    ],
                ),
            ),
        ]);
        let rows: Vec<&str> = md.lines().skip(2).collect();
        assert_eq!(rows.len(), 2, "{md}");
        // 40 s on 1 GPU, 12.5 s on 4: speed-up 3.2, efficiency 0.80; front workers are ignored.
        assert_eq!(
            rows[0],
            "| 1 | 40.0 | 2.50 | 1.00 | 1.00 | 75 | 100 | 0.50 | 36.0 (0.00) | 4.0 |"
        );
        assert_eq!(
            rows[1],
            "| 4 | 12.5 | 8.00 | 3.20 | 0.80 | 64 64 56 64 | 25/25/24/26 | 1.50 | 10.0 (1.00) | 2.5 |"
        );
    }
}
