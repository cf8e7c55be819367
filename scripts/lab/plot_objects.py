#!/usr/bin/env python3
"""Draw the objects of `slag-encoder query` answers over the scene's Gaussians, one panel per
prompt: every Gaussian mean in gray, the matches in light magenta, each returned object's oriented
box (`obb`) in a palette colour with its rank and Gaussian count.

The view looks along the scene's shortest principal axis (for a room or a table top, down onto the
floor), so the picture needs no camera; axes are in scene units.

Usage: plot_objects.py SCENE.ply OUT.png ANSWER.json [ANSWER.json ...]
Needs numpy and matplotlib.
"""

import json
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

# Ten distinct box colours that read on a white background, as 0..1 RGB.
PALETTE = [
    (0.12, 0.47, 0.71),
    (1.00, 0.50, 0.05),
    (0.17, 0.63, 0.17),
    (0.84, 0.15, 0.16),
    (0.58, 0.40, 0.74),
    (0.55, 0.34, 0.29),
    (0.09, 0.75, 0.81),
    (0.74, 0.74, 0.13),
    (0.50, 0.50, 0.50),
    (0.89, 0.47, 0.76),
]


def read_ply_means(path):
    """x, y, z of every vertex of a binary little-endian .ply (float properties only, as 3DGS)."""
    with open(path, "rb") as f:
        props, n = [], 0
        while True:
            line = f.readline().decode("ascii").strip()
            if line.startswith("element vertex"):
                n = int(line.split()[2])
            elif line.startswith("property"):
                kind, name = line.split()[1], line.split()[2]
                if kind not in ("float", "float32"):
                    sys.exit(f"{path}: property {name} is {kind}; only float vertices are read")
                props.append(name)
            elif line == "end_header":
                break
        data = np.frombuffer(f.read(4 * n * len(props)), dtype="<f4").reshape(n, len(props))
    return data[:, [props.index(a) for a in ("x", "y", "z")]].astype(np.float64)


def main():
    if len(sys.argv) < 4:
        sys.exit(__doc__)
    ply, out, answers = sys.argv[1], sys.argv[2], sys.argv[3:]
    means = read_ply_means(ply)
    centre = means.mean(axis=0)
    # Principal axes of the scene: view along the smallest, x/y of the picture the two largest.
    _, vecs = np.linalg.eigh(np.cov((means - centre).T))
    view = vecs[:, [2, 1]]
    if np.linalg.det(vecs[:, [2, 1, 0]]) < 0:
        view[:, 1] = -view[:, 1]
    flat = (means - centre) @ view
    lo, hi = np.percentile(flat, 0.5, axis=0), np.percentile(flat, 99.5, axis=0)
    # One panel per prompt, stacked, each as wide as the scene's extent asks.
    aspect = (hi[1] - lo[1]) / max(hi[0] - lo[0], 1e-9)
    fig, axes = plt.subplots(len(answers), 1, figsize=(9.0, len(answers) * (9.0 * aspect + 0.9)),
                             dpi=100)
    axes = np.atleast_1d(axes)
    for ax, path in zip(axes, answers):
        a = json.load(open(path))
        ax.scatter(flat[:, 0], flat[:, 1], s=0.15, c="0.78", linewidths=0, rasterized=True)
        m = np.array([x["position"] for x in a["matches"]], dtype=np.float64).reshape(-1, 3)
        if len(m):
            mf = (m - centre) @ view
            ax.scatter(mf[:, 0], mf[:, 1], s=0.3, c=[(0.95, 0.55, 0.95)], linewidths=0,
                       rasterized=True)
        for k, o in reversed(list(enumerate(a["objects"]))):
            colour = PALETTE[k % len(PALETTE)]
            c = np.array(o["obb"]["center"])
            axs = np.array(o["obb"]["axes"])
            half = np.array(o["obb"]["extents"]) / 2
            corners = np.array([c + sx * half[0] * axs[0] + sy * half[1] * axs[1] + sz * half[2] * axs[2]
                                for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
            cf = (corners - centre) @ view
            # The box's 12 edges in projection.
            for i in range(8):
                for j in range(i + 1, 8):
                    if bin(i ^ j).count("1") == 1:
                        ax.plot(cf[[i, j], 0], cf[[i, j], 1], color=colour, lw=1.1)
            top = cf[np.argmax(cf[:, 1])]
            ax.text(top[0], top[1], f"#{k + 1} {o['gaussians']}", color=colour, fontsize=7.5,
                    ha="center", va="bottom", fontweight="bold", clip_on=True)
        smooth = a.get("smooth", "none")
        ax.set_title(f"\"{a['query']}\": {a['summary']['count']} matches (magenta), the first "
                     f"{len(a['objects'])} objects by score mass (boxes: #rank Gaussians), "
                     f"smooth {smooth}", fontsize=9)
        pad = 0.05 * (hi - lo)
        ax.set_xlim(lo[0] - pad[0], hi[0] + pad[0])
        ax.set_ylim(lo[1] - pad[1], hi[1] + pad[1])
        ax.set_aspect("equal")
        ax.tick_params(labelsize=7)
        ax.set_xlabel("first principal axis (scene units)", fontsize=8)
        ax.set_ylabel("second principal axis", fontsize=8)
    fig.tight_layout()
    fig.savefig(out)


if __name__ == "__main__":
    main()
