#!/usr/bin/env python3
"""Pareto plot of slag's speed/accuracy trade study.

usage: plot_tradeoffs.py docs/results/tradeoffs.csv docs/results/tradeoffs.png

Panels (from the CSV written by `slag-bench tradeoffs`):
  1. encode wall time (s, log) vs held-out 2D mIoU for the encode points (the study's accuracy
     axis; points that encoded every view have none and are left out); the Pareto front
     (faster and more accurate) is drawn as a line and its points ringed;
  1b. the same points against the 3D colour mIoU, beside it (no front: the 3D score cannot show
     progress, its pixel oracle reaches 0.26 on snowmiku);
  2. bytes per Gaussian vs agreement with the exact f32 answer (IoU of the cos >= 0.28 sets;
     HNSW: tie-aware top-k recall) for the storage and index points;
  3. bytes per Gaussian vs query latency (ms) for the same points.
"""
import csv
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.ticker import NullFormatter, ScalarFormatter  # noqa: E402


def pareto(points):
    """Indices of the points no other point beats in both time (lower) and mIoU (higher)."""
    front = []
    for i, (t, m) in enumerate(points):
        dominated = any(
            (t2 <= t and m2 >= m and (t2 < t or m2 > m)) for j, (t2, m2) in enumerate(points) if j != i
        )
        if not dominated:
            front.append(i)
    return sorted(front, key=lambda i: points[i][0])


def main():
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    with open(sys.argv[1], newline="") as f:
        rows = list(csv.DictReader(f))
    held = [r for r in rows if r["section"] == "encode" and r.get("held_out_miou", "na") != "na"]
    enc3d = [r for r in rows if r["section"] == "encode" and r["colour_miou"] != "na"]
    sto = [r for r in rows if r["section"] in ("storage", "index")]

    fig, axes = plt.subplots(2, 2, figsize=(15, 11))
    ax = [axes[0][0], axes[1][0], axes[1][1]]
    ax3d = axes[0][1]
    colours = {"baseline": "black", "reference": "tab:red", "every": "tab:blue", "raster": "tab:green",
               "top-k": "tab:orange", "masks": "tab:purple", "aggregation": "tab:brown"}

    def label_of(r):
        return {"every": f"every {r['every']}", "raster": f"raster {r['raster_scale']}",
                "top-k": f"top-{r['top_k']}", "masks": r["masks"] + f" (every {r['every']})",
                "aggregation": r["point"].split("-kall")[-1].lstrip("-") or "mean",
                "baseline": "baseline", "reference": f"reference (every {r['every']})"}.get(r["knob"], r["point"])

    def encode_panel(a, enc, column, ylabel, title, with_front):
        pts = [(float(r["encode_s"]), float(r[column])) for r in enc]
        for r, (t, m) in zip(enc, pts):
            a.scatter(t, m, color=colours.get(r["knob"], "gray"), s=40, zorder=3)
            a.annotate(label_of(r), (t, m), textcoords="offset points", xytext=(4, 4), fontsize=8)
        if with_front:
            front = pareto(pts)
            if front:
                a.plot([pts[i][0] for i in front], [pts[i][1] for i in front], "--", color="gray",
                       zorder=2, label="Pareto front")
                a.scatter([pts[i][0] for i in front], [pts[i][1] for i in front], s=160,
                          facecolors="none", edgecolors="gray", zorder=2)
        for k, c in colours.items():
            if any(r["knob"] == k for r in enc):
                a.scatter([], [], color=c, label=k)
        a.set_xscale("log")
        a.set_xlabel("encode wall time, s (log)")
        a.set_ylabel(ylabel)
        a.set_title(title)
        a.legend(fontsize=8)
        a.grid(alpha=0.3)

    encode_panel(ax[0], held, "held_out_miou", "held-out 2D mIoU (views no point encoded)",
                 "Encode: time vs held-out mIoU (Pareto front)", True)
    encode_panel(ax3d, enc3d, "colour_miou", "3D colour mIoU (per-Gaussian class)",
                 "Encode: time vs 3D colour mIoU (beside)", False)

    for r in sto:
        b, iou, ms = float(r["bytes_per_gaussian"]), float(r["iou"]), float(r["query_ms"])
        hnsw = r["index"] == "hnsw"
        marker = "s" if r["section"] == "index" else "o"
        c = "tab:red" if hnsw else ("tab:blue" if r["section"] == "storage" else "gray")
        label = r["point"].replace("store-", "")
        if r["section"] == "index":
            label += f" ({r['observed']} rows)"
        ax[1].scatter(b, iou, marker=marker, color=c, s=40)
        ax[1].annotate(label, (b, iou), textcoords="offset points", xytext=(4, 4), fontsize=8)
        ax[2].scatter(b, ms, marker=marker, color=c, s=40)
        ax[2].annotate(label, (b, ms), textcoords="offset points", xytext=(4, 4), fontsize=8)
    ax[1].set_xscale("log")
    ax[1].set_xlabel("bytes per Gaussian (log)")
    ax[1].set_ylabel("agreement with exact f32 (IoU; HNSW: top-k recall)")
    ax[1].set_title("Storage: size vs agreement")
    ax[1].grid(alpha=0.3)
    ax[2].set_xscale("log")
    ax[2].set_yscale("log")
    # Plain numbers on the log axes, major ticks only (minor labels overlap on short ranges).
    for a, axis in ((ax[0], "x"), (ax3d, "x"), (ax[1], "x"), (ax[2], "x"), (ax[2], "y")):
        axis_obj = a.xaxis if axis == "x" else a.yaxis
        axis_obj.set_major_formatter(ScalarFormatter())
        axis_obj.set_minor_formatter(NullFormatter())
    ax[2].set_xlabel("bytes per Gaussian (log)")
    ax[2].set_ylabel("query latency, ms (log; index points: top-k)")
    ax[2].set_title("Storage: size vs query latency")
    ax[2].grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(sys.argv[2], dpi=110)


if __name__ == "__main__":
    main()
