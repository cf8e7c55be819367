//! The machine a study ran on, for the generated documents' headers.

use std::fmt::Write as _;

/// What the study's header records about the machine and the run.
#[derive(Debug, Clone, serde::Serialize)]
pub struct MachineInfo {
    /// Logical CPUs available to this process (`std::thread::available_parallelism`).
    pub cpus: usize,
    /// `model name` of the first CPU in `/proc/cpuinfo` (`"unknown"` elsewhere).
    pub cpu_model: String,
    /// UTC date and time at the start of the run, `YYYY-MM-DD HH:MM UTC`.
    pub date_utc: String,
    /// `release` or `debug` (the build profile of this binary: `debug_assertions`).
    pub profile: &'static str,
    /// `git rev-parse --short HEAD` of the working directory, when available.
    pub git_commit: Option<String>,
}

impl MachineInfo {
    /// Reads the machine facts now.
    pub fn detect() -> MachineInfo {
        let cpus = std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(1);
        let cpu_model = std::fs::read_to_string("/proc/cpuinfo")
            .ok()
            .and_then(|s| {
                s.lines()
                    .find(|l| l.starts_with("model name"))
                    .and_then(|l| l.split_once(':'))
                    .map(|(_, v)| v.trim().to_string())
            })
            .unwrap_or_else(|| "unknown".into());
        let git_commit = std::process::Command::new("git")
            .args(["rev-parse", "--short", "HEAD"])
            .output()
            .ok()
            .filter(|o| o.status.success())
            .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
            .filter(|s| !s.is_empty());
        MachineInfo {
            cpus,
            cpu_model,
            date_utc: utc_now(),
            profile: if cfg!(debug_assertions) {
                "debug"
            } else {
                "release"
            },
            git_commit,
        }
    }

    /// One markdown line: `N CPUs (model), profile build, date, commit`.
    pub fn markdown(&self) -> String {
        let mut s = format!(
            "{} logical CPUs ({}), {} build, {}",
            self.cpus, self.cpu_model, self.profile, self.date_utc
        );
        if let Some(c) = &self.git_commit {
            let _ = write!(s, ", commit {c}");
        }
        s
    }
}

/// Current UTC time as `YYYY-MM-DD HH:MM UTC` (proleptic Gregorian calendar).
pub fn utc_now() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0);
    format_utc(secs)
}

/// `secs` since the Unix epoch as `YYYY-MM-DD HH:MM UTC` (days → civil date: H. Hinnant's
/// `civil_from_days`).
pub fn format_utc(secs: u64) -> String {
    let days = (secs / 86_400) as i64;
    let rem = secs % 86_400;
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{y:04}-{m:02}-{d:02} {:02}:{:02} UTC",
        rem / 3600,
        (rem % 3600) / 60
    )
}

#[cfg(test)]
mod tests {
    use super::format_utc;

    #[test]
    fn utc_dates_match_known_instants() {
        assert_eq!(format_utc(0), "1970-01-01 00:00 UTC");
        // 2000-02-29 12:34 UTC (leap day) = 951827640.
        assert_eq!(format_utc(951_827_640), "2000-02-29 12:34 UTC");
        // 2026-11-21 22:55 UTC = 1795301700.
        assert_eq!(format_utc(1_795_301_700), "2026-11-21 22:55 UTC");
    }
}
