#!/usr/bin/env python3
"""Peak host memory of a command, and when it happens.

Runs the command, samples its resident set (VmRSS of /proc/PID/status, Linux; summed over the
command and its descendants) every `--every` seconds, and prints the sampled peak and how long before the command's end it was reached
(compare with the phase timings of the encode's report.json: the reduction, the mixture and the
write are the run's last seconds). The kernel's own high-water mark (VmHWM, the largest of any one
process, read at the last sample) is printed too: a peak shorter than the sampling step shows there only.

    python3 scripts/lab/rss-timeline.py --out /tmp/rss.tsv -- slag-encoder encode ...

`--out` writes the samples (seconds since start, RSS bytes) as tab-separated lines. With
`--report OUT/report.json` (the encode's), the peak is also split by phase: before the tail, the
tail (reduction, mixture, level files, write: the report's last seconds, counted from its
`timings.total`, which starts near the process start) and after the report (`encode` waiting
for its geometric segments, when they outlast the encode they run beside, and writing them).
"""
import argparse
import json
import os
import subprocess
import sys
import time


def status_kib(pid, key):
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith(key + ":"):
                    return int(line.split()[1])
    except (FileNotFoundError, ProcessLookupError):
        return None
    return None


def tree(pid):
    """`pid` and its descendants (a wrapper such as /usr/bin/time runs the encoder as a child)."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        try:
            for task in os.listdir(f"/proc/{p}/task"):
                with open(f"/proc/{p}/task/{task}/children") as f:
                    todo.extend(int(c) for c in f.read().split())
        except (FileNotFoundError, ProcessLookupError):
            pass
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--every", type=float, default=0.05, help="sampling step, seconds")
    ap.add_argument("--out", help="write the samples here (seconds, RSS bytes)")
    ap.add_argument("--report", help="the encode's report.json: split the peak by phase")
    ap.add_argument("cmd", nargs=argparse.REMAINDER)
    a = ap.parse_args()
    cmd = a.cmd[1:] if a.cmd[:1] == ["--"] else a.cmd
    if not cmd:
        ap.error("no command given")
    t0 = time.monotonic()
    p = subprocess.Popen(cmd)
    samples, hwm = [], 0
    while p.poll() is None:
        rss = 0
        for q in tree(p.pid):
            rss += status_kib(q, "VmRSS") or 0
            hwm = max(hwm, (status_kib(q, "VmHWM") or 0) * 1024)
        samples.append((time.monotonic() - t0, rss * 1024))
        time.sleep(a.every)
    end = time.monotonic() - t0
    if a.out:
        with open(a.out, "w") as f:
            for t, r in samples:
                f.write(f"{t:.3f}\t{r}\n")
    if samples:
        t_peak, peak = max(samples, key=lambda s: s[1])
        gib = 2**30
        print(
            f"rss-timeline: wall {end:.2f} s, sampled peak {peak / gib:.3f} GiB at {t_peak:.2f} s "
            f"({end - t_peak:.2f} s before the end), VmHWM {hwm / gib:.3f} GiB, "
            f"{len(samples)} samples",
            file=sys.stderr,
        )
    if a.report and samples:
        phases(samples, a.report)
    return p.returncode


def phases(samples, report):
    """Prints the peak RSS before the encode's tail, in it, and after the report was written."""
    try:
        with open(report) as f:
            r = json.load(f)
    except (OSError, ValueError) as e:
        print(f"rss-timeline: no phases ({report}: {e})", file=sys.stderr)
        return
    t, out = r["timings"], r.get("outputs", {})
    forms = out.get("forms") or out
    tail = (
        t["reduce"]
        + t["write"]
        + (forms.get("mixture_reduce_s") or 0)
        + (forms.get("levels_reduce_s") or 0)
    )
    end = t["total"]
    windows = [("before the tail", 0, end - tail), ("tail", end - tail, end), ("after", end, 1e18)]
    gib = 2**30
    for name, lo, hi in windows:
        w = [s for s in samples if lo <= s[0] < hi]
        if w:
            ts, peak = max(w, key=lambda s: s[1])
            print(
                f"rss-timeline: {name} ({lo:.1f}..{min(hi, samples[-1][0]):.1f} s): "
                f"peak {peak / gib:.3f} GiB at {ts:.1f} s",
                file=sys.stderr,
            )


if __name__ == "__main__":
    sys.exit(main())
