#!/usr/bin/env python3
"""Each GPU's utilization over the fronts' window of one encode.

Reads the samples of `nvidia-smi --query-gpu=timestamp,index,utilization.gpu,utilization.memory,
power.draw,clocks.sm --format=csv,noheader -lms 200` (what `UTIL=1` in device-gpus-ab.sh
writes; samples without the `index` column, as the first such runs took, are of GPU 0) and the
encode's output with its debug lines (RUST_LOG with slag_encoder::pipeline=debug).
The window runs from the line `scene loaded` to `workers done`: the fronts, where SAM, CLIP and
the rasterizer share the GPU. Prints per GPU the number of samples, the mean utilization (the
share of the sample's period in which at least one kernel ran, as NVIDIA defines it), how many
samples fell under 90 %, the mean memory utilization and the mean power; then when the GPU first
stays busy (the first of five samples in a row at 90 % or more, counted from the window's start)
and the mean utilization from there on.

    python3 scripts/lab/gpu-util.py util-TAG.csv e2e-f16-TAG.txt
"""
import datetime
import re
import sys


def stamp(text, pattern):
    m = re.search(r"(\d{4}-\d\d-\d\dT[\d:.]+)Z[^\n]*" + pattern, text)
    if not m:
        sys.exit(f"gpu-util: no line with {pattern!r} in the encode's output (was RUST_LOG debug?)")
    return datetime.datetime.fromisoformat(m.group(1)[:26])


def main():
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    text = open(sys.argv[2]).read()
    start, end = stamp(text, "scene loaded"), stamp(text, "workers done")
    gpus = {}
    for line in open(sys.argv[1]):
        f = [x.strip() for x in line.split(",")]
        if len(f) == 5:
            f.insert(1, "0")
        try:
            t = datetime.datetime.strptime(f[0], "%Y/%m/%d %H:%M:%S.%f")
            util, mem = int(f[2].split()[0]), int(f[3].split()[0])
            power = float(f[4].split()[0])
        except (ValueError, IndexError):
            continue  # a header, or a line cut by the sampler's end
        if start <= t <= end:
            gpus.setdefault(f[1], []).append((t, util, mem, power))
    seconds = (end - start).total_seconds()
    for gpu, rows in sorted(gpus.items()):
        n = len(rows)
        mean = lambda i, rs=rows: sum(r[i] for r in rs) / len(rs)
        under = sum(1 for r in rows if r[1] < 90)
        print(f"  gpu {gpu}: fronts {seconds:.2f} s, {n} samples, utilization {mean(1):.1f} % "
              f"(under 90 %: {under}), memory {mean(2):.1f} %, power {mean(3):.0f} W")
        busy = next((i for i in range(n - 4) if all(r[1] >= 90 for r in rows[i:i + 5])), None)
        if busy is not None:
            since = (rows[busy][0] - start).total_seconds()
            print(f"    busy from +{since:.1f} s: utilization {mean(1, rows[busy:]):.1f} % after it")


if __name__ == "__main__":
    main()
