#!/usr/bin/env python3
"""One line of scripts/lab/device-views.sh's table (a device harness, not part of CI).

Usage: views-row.py TAG RC WALL REPORT LOG GPU_CSV
REPORT is the encode's report.json, LOG its output under GNU `time -v` (peak RSS), GPU_CSV the
GPU's used memory in MiB, one sample per line. Prints the process wall, peak RSS, peak GPU
memory, the device reduction's waves and peak, the observed Gaussians and the coverage pass.
"""
import json
import re
import sys

tag, rc, wall, report, log, gpu = sys.argv[1:7]
text = open(log, errors="replace").read()
rss = re.search(r"Maximum resident set size \(kbytes\): (\d+)", text)
peak_gpu = 0
for line in open(gpu):
    line = line.strip()
    if line.isdigit():
        peak_gpu = max(peak_gpu, int(line))
try:
    r = json.load(open(report))
except (OSError, ValueError):
    tail = " | ".join(l.strip()[-200:] for l in text.splitlines()[-4:])
    print(f"{tag}: rc {rc}, wall {wall} s, no report; peak GPU {peak_gpu / 1024:.1f} GiB; {tail}")
    sys.exit(0)
c = r.get("counts", {})
sel = r.get("view_selection") or {}
cov = sel.get("coverage") or {}
n = c.get("gaussians")
obs = c.get("observed")
print(
    f"{tag}: rc {rc}, process wall {wall} s, peak RSS "
    f"{int(rss.group(1)) / 2**20 if rss else -1:.2f} GiB, peak GPU {peak_gpu / 1024:.1f} GiB, "
    f"reduce {c.get('device_reduce')} waves {c.get('device_reduce_waves')} peak "
    f"{(c.get('device_reduce_peak_bytes') or 0) / 2**30:.2f} GiB, observed {obs} of {n}, "
    f"views {c.get('views_used')} of {c.get('views_total')}, coverage pass {sel.get('pass_s', 0):.1f} s "
    f"(observed {cov.get('observed')}, by the chosen {cov.get('observed_chosen')}, stop {cov.get('stop')}), encode total "
    f"{r.get('timings', {}).get('total', 0):.1f} s"
)
