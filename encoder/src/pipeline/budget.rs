//! The device reduction's memory budget: the device memory the label sums kept for the GPU
//! reduction may take. Given (`--device-reduce-memory-mb`), or sized at the start of the encode
//! from the GPUs' free memory: [`SHARE_OF_FREE`] of the least free memory of any NVIDIA GPU
//! `nvidia-smi` lists (read once, after the models are set up; the rest is left to the models'
//! arenas as they grow and to the views' raster buffers). Where it cannot be read (no NVIDIA
//! driver, lavapipe on a CPU-only machine), [`FALLBACK_BYTES`].

use std::io::Read;
use std::process::{Command, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use serde::Serialize;

/// The share of the least free device memory at the start that the kept label sums may take.
pub const SHARE_OF_FREE: f64 = 0.5;

/// The budget where the devices' free memory cannot be read: 16 GiB.
pub const FALLBACK_BYTES: u64 = 16 << 30;

/// How long `nvidia-smi` may take to answer before the fallback is used.
const QUERY_LIMIT: Duration = Duration::from_secs(10);

/// The device reduction's budget and where it came from (`report.json`'s
/// `parameters.device_reduce_budget`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct DeviceBudget {
    /// Device memory the kept label sums may take, bytes.
    pub bytes: u64,
    /// Where it came from.
    pub source: BudgetSource,
    /// The least free memory of the GPUs at the start, bytes (`None`: not read).
    pub free_bytes: Option<u64>,
}

/// Where a [`DeviceBudget`] came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum BudgetSource {
    /// The encode's setting (`--device-reduce-memory-mb`).
    Given,
    /// [`SHARE_OF_FREE`] of the GPUs' least free memory.
    FreeMemory,
    /// [`FALLBACK_BYTES`]: the free memory could not be read.
    Fallback,
}

/// The budget of the encode `c` ([`device_reduce_budget`]: its setting, on the GPU backend).
pub fn of(c: &crate::config::EncodeConfig) -> DeviceBudget {
    device_reduce_budget(
        c.aggregate.device_reduce_memory_mb,
        c.raster.backend == crate::config::RasterBackend::Gpu,
    )
}

/// The budget: `given_mb` MiB when given; otherwise sized from the GPUs' free memory when
/// `on_gpu` (the encode rasterizes on the GPU; read once a process, the first time it is
/// asked for), else [`FALLBACK_BYTES`].
pub fn device_reduce_budget(given_mb: Option<usize>, on_gpu: bool) -> DeviceBudget {
    if let Some(mb) = given_mb {
        return DeviceBudget {
            bytes: (mb as u64) << 20,
            source: BudgetSource::Given,
            free_bytes: None,
        };
    }
    static FREE: OnceLock<Option<u64>> = OnceLock::new();
    let free = on_gpu
        .then(|| *FREE.get_or_init(|| nvidia_smi_free_memory().and_then(|t| least_free_bytes(&t))))
        .flatten();
    sized_from(free)
}

/// The budget from the GPUs' least `free` memory (bytes), or the fallback without it.
fn sized_from(free: Option<u64>) -> DeviceBudget {
    match free {
        Some(free) => DeviceBudget {
            bytes: (free as f64 * SHARE_OF_FREE) as u64,
            source: BudgetSource::FreeMemory,
            free_bytes: Some(free),
        },
        None => DeviceBudget {
            bytes: FALLBACK_BYTES,
            source: BudgetSource::Fallback,
            free_bytes: None,
        },
    }
}

/// The least of the free memories `nvidia-smi --query-gpu=memory.free --format=csv,noheader,nounits`
/// printed (one MiB figure a GPU, a line each), bytes; `None` for no figure or a line that is
/// not one.
fn least_free_bytes(text: &str) -> Option<u64> {
    let mut least: Option<u64> = None;
    for line in text.lines().map(str::trim).filter(|l| !l.is_empty()) {
        let mib: u64 = line.parse().ok()?;
        least = Some(least.map_or(mib, |l| l.min(mib)));
    }
    least.map(|mib| mib << 20)
}

/// What `nvidia-smi` prints of each GPU's free memory, or `None` when it is missing, fails or
/// takes longer than [`QUERY_LIMIT`] (then it is killed).
fn nvidia_smi_free_memory() -> Option<String> {
    let mut child = Command::new("nvidia-smi")
        .args(["--query-gpu=memory.free", "--format=csv,noheader,nounits"])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .ok()?;
    let t0 = Instant::now();
    let status = loop {
        match child.try_wait() {
            Ok(Some(status)) => break status,
            Ok(None) if t0.elapsed() < QUERY_LIMIT => std::thread::sleep(Duration::from_millis(20)),
            _ => {
                let _ = child.kill();
                let _ = child.wait();
                tracing::warn!(
                    "nvidia-smi did not answer; the device reduction's budget is the fallback"
                );
                return None;
            }
        }
    };
    let mut text = String::new();
    child.stdout.take()?.read_to_string(&mut text).ok()?;
    status.success().then_some(text)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_budget_is_given_or_a_share_of_the_least_free_memory() {
        let given = device_reduce_budget(Some(1024), true);
        assert_eq!((given.bytes, given.source), (1 << 30, BudgetSource::Given));
        // Two GPUs: the budget follows the one with less free memory.
        let free = least_free_bytes("81000\n 40000 \n");
        assert_eq!(free, Some(40_000 << 20));
        let b = sized_from(free);
        assert_eq!(b.source, BudgetSource::FreeMemory);
        assert_eq!(b.bytes, (40_000u64 << 20) / 2);
        // Nothing to read, or not figures: the fallback.
        for text in ["", "N/A\n", "[Not Supported]"] {
            assert_eq!(least_free_bytes(text), None, "{text:?}");
        }
        let fallback = device_reduce_budget(None, false);
        assert_eq!(
            (fallback.bytes, fallback.source),
            (FALLBACK_BYTES, BudgetSource::Fallback)
        );
    }
}
