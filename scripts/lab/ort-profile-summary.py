#!/usr/bin/env python3
"""Where an ONNX Runtime session's time goes: summarise the profiler's traces (written when
SLAG_ORT_PROFILE=PREFIX is set for slag-encoder or slag-bench) by operator and provider.

    ort-profile-summary.py TRACE.json [TRACE.json ...]

Prints, per trace: the session runs (count, the first one's time, the median of the others), then
a table of the operators by total kernel time (provider, node runs, total ms, share) over every
run but the first (which builds the providers' plans), the first 15 rows, and the kernel time on
each provider. Kernel time is ONNX Runtime's "Node" events (`*_kernel_time`); the gap between
their sum and the runs' time is what happens between kernels (copies, CPU-side shape ops,
launches, synchronisation).
"""
import json
import statistics
import sys
from collections import defaultdict


def summarise(path):
    events = json.load(open(path))
    run_events = [e for e in events if e.get("cat") == "Session" and e.get("name") == "model_run"]
    runs = [e["dur"] / 1e3 for e in run_events]
    # The first run builds the providers' plans (cuDNN algorithm search): leave its nodes out.
    after = run_events[0]["ts"] + run_events[0]["dur"] if len(run_events) > 1 else -1
    ops = defaultdict(lambda: [0, 0.0])
    providers = defaultdict(float)
    for e in events:
        if e.get("cat") != "Node" or not e.get("name", "").endswith("_kernel_time"):
            continue
        if e.get("ts", 0) < after:
            continue
        args = e.get("args", {})
        key = (args.get("op_name", "?"), args.get("provider", "?"))
        ops[key][0] += 1
        ops[key][1] += e["dur"] / 1e3
        providers[key[1]] += e["dur"] / 1e3
    total = sum(v[1] for v in ops.values()) or 1.0
    steady = runs[1:] if len(runs) > 1 else runs
    print(f"## {path}\n")
    if runs:
        # The first run includes the providers' set-up (cuDNN plans); the median is steady state.
        print(f"model runs: {len(runs)}, first {runs[0]:.2f} ms, then median "
              f"{statistics.median(steady):.2f} ms, sum {sum(steady):.1f} ms; their kernel time "
              f"{total:.1f} ms ({total / max(sum(steady), 1e-9):.0%})\n")
    print("| operator | provider | node runs | total ms | share |")
    print("|---|---|---:|---:|---:|")
    for (op, prov), (n, ms) in sorted(ops.items(), key=lambda kv: -kv[1][1])[:15]:
        print(f"| {op} | {prov} | {n} | {ms:.1f} | {ms / total:.1%} |")
    print("\nkernel time by provider: " + ", ".join(
        f"{p} {ms:.1f} ms" for p, ms in sorted(providers.items(), key=lambda kv: -kv[1])) + "\n")


for p in sys.argv[1:]:
    summarise(p)
