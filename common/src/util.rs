//! What the running process can read about its own memory and the machine's (Linux `/proc`);
//! every reading is `None` where the file is absent or unreadable (other systems, a sandbox).

/// A `Key:  N kB` line of `/proc/self/status` (`VmRSS`, `VmHWM`, ...), in bytes.
fn status_bytes(key: &str) -> Option<u64> {
    proc_kb("/proc/self/status", key)
}

/// The value of the `key:  N kB` line of the `/proc` file `path`, in bytes.
fn proc_kb(path: &str, key: &str) -> Option<u64> {
    let text = std::fs::read_to_string(path).ok()?;
    let line = text
        .lines()
        .find(|l| l.strip_prefix(key).is_some_and(|r| r.starts_with(':')))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// Resident set size of this process (`VmRSS` of `/proc/self/status`), bytes.
pub fn rss_bytes() -> Option<u64> {
    status_bytes("VmRSS")
}

/// Peak resident set size of this process (`VmHWM` of `/proc/self/status`), bytes.
pub fn peak_rss_bytes() -> Option<u64> {
    status_bytes("VmHWM")
}

/// Memory the kernel estimates is available for new allocations without swapping
/// (`MemAvailable` of `/proc/meminfo`), bytes.
pub fn mem_available_bytes() -> Option<u64> {
    proc_kb("/proc/meminfo", "MemAvailable")
}

/// CPU time this process has used so far, user + system over all its threads, seconds
/// (`utime` + `stime` of `/proc/self/stat`, clock ticks of 1/100 s: 10 ms resolution).
pub fn cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // The fields after the command name (in parentheses, which may itself hold spaces and
    // parentheses) start at field 3, the state; utime is field 14, stime 15.
    let (_, rest) = stat.rsplit_once(')')?;
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |field: usize| fields.get(field - 3)?.parse::<f64>().ok();
    Some((ticks(14)? + ticks(15)?) / 100.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn readings_are_consistent_where_proc_exists() {
        if !std::path::Path::new("/proc/self/status").exists() {
            assert_eq!(rss_bytes(), None);
            return;
        }
        let rss = rss_bytes().expect("VmRSS");
        let peak = peak_rss_bytes().expect("VmHWM");
        assert!(rss > 0, "{rss}");
        assert!(peak >= rss, "peak {peak} < current {rss}");
        assert!(mem_available_bytes().is_some_and(|m| m > 0));
        let cpu = cpu_seconds().expect("utime + stime");
        assert!(cpu_seconds().expect("utime + stime") >= cpu);
        assert_eq!(status_bytes("NoSuchKey"), None);
    }
}
