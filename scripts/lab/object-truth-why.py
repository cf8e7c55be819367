"""Why objects of the labelled-object room are missed: what each object's Gaussians answer, and
whether an object is lost in the answer (the per-Gaussian scores) or in the grouping (the object
gap). Reads the folders of `scripts/lab/object-truth-pf.sh` (OUT/<level>-s<seed>/: scene/,
enc/embeddings.safetensors, enc/segments.safetensors, geometric.safetensors). Needs numpy and
onnxruntime (pip), and SLAG_SHARED for color-clip's text tower; not part of CI.

    python3 scripts/lab/object-truth-why.py OUT/default-s1 [OUT/default-s2 ...]

Prints per run:
1. Per object, the share of its observed Gaussians whose own class (argmax over the 12 class
   prompts, as `argmax` of `eval-objects --held-out`) is the object's class; answers the class
   nearest the Gaussian's own SH-DC colour instead (its shaded or speckled colour: what the
   surface shows); answers gray (the floor's) or white (the walls') while its colour is
   neither; anything else. Then the gray answers' share per fifth of the object's height.
2. The membership IoU of each object with its best object of its class's answer, for answers
   made of: the Gaussians at or above the paper's threshold 0.28 (the query's answer), the
   Gaussians whose argmax is the class, the object's true members (the grouping alone), and the
   threshold applied to scores averaged over each segmentation (plain mean, as `--smooth
   segment`, and weighted by the views' blend weight Σ_j a_kj). Grouping as the query's
   default: single linkage at 4 × the median nearest-match distance, groups of ≥ 10.
"""

import json
import os
import struct
import sys

import numpy as np
import onnxruntime as ort

PROTOS = np.array([[0.85, 0.1, 0.1], [0.95, 0.55, 0.1], [0.95, 0.9, 0.15], [0.15, 0.65, 0.2],
                   [0.1, 0.6, 0.65], [0.1, 0.2, 0.8], [0.5, 0.2, 0.65], [0.95, 0.55, 0.7],
                   [0.45, 0.3, 0.15], [0.95, 0.95, 0.95], [0.5, 0.5, 0.5], [0.05, 0.05, 0.05]])
GRAY, WHITE = 10, 9


def safetensors(path):
    raw = open(path, "rb").read()
    n = struct.unpack("<Q", raw[:8])[0]
    head = json.loads(raw[8:8 + n])
    kinds = {"F16": np.float16, "F32": np.float32, "U32": np.uint32, "U16": np.uint16}
    out = {}
    for k, v in head.items():
        if k != "__metadata__":
            a, b = v["data_offsets"]
            out[k] = np.frombuffer(raw[8 + n + a:8 + n + b], kinds[v["dtype"]]).reshape(v["shape"])
    return out


def ply(path):
    raw = open(path, "rb").read()
    i = raw.index(b"end_header\n") + 11
    head = raw[:i].decode().splitlines()
    props = [line.split()[2] for line in head if line.startswith("property")]
    n = int([line for line in head if line.startswith("element vertex")][0].split()[2])
    a = np.frombuffer(raw[i:i + n * 4 * len(props)], np.float32).reshape(n, len(props))
    return {p: a[:, j] for j, p in enumerate(props)}


def text_directions(clip_dir, classes):
    j = json.load(open(os.path.join(clip_dir, "color-clip.json")))
    ids = np.zeros((len(classes), 77), np.int64)
    for i, c in enumerate(classes):
        ids[i, :3] = [49406, j["token_ids"][c], 49407]
    s = ort.InferenceSession(os.path.join(clip_dir, "color-clip-textual.onnx"))
    t = s.run(None, {"input_ids": ids})[0]
    return t / np.linalg.norm(t, axis=1, keepdims=True)


def groups(means, sel):
    """The query's default grouping of the Gaussians `sel`: sets of ids."""
    idx = np.where(sel)[0]
    if len(idx) < 2:
        return []
    p = means[idx]
    d = np.sqrt(((p[:, None] - p[None]) ** 2).sum(-1))
    np.fill_diagonal(d, np.inf)
    gap = 4 * np.median(d.min(1))
    parent = list(range(len(idx)))

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for a, b in zip(*np.where(np.triu(d <= gap, 1))):
        parent[find(a)] = find(b)
    roots = np.array([find(a) for a in range(len(idx))])
    return [set(idx[roots == r].tolist()) for r in np.unique(roots) if (roots == r).sum() >= 10]


def best_iou(gs, members):
    return max((len(g & members) / len(g | members) for g in gs), default=0.0)


def run(d, clip_dir):
    truth = json.load(open(f"{d}/scene/truth.json"))
    objects = json.load(open(f"{d}/scene/objects.json"))
    classes = truth["classes"]
    g = ply(f"{d}/scene/point_cloud.ply")
    n = len(g["x"])
    means = np.stack([g["x"], g["y"], g["z"]], 1)
    dc = np.clip(0.5 + 0.28209479177387814 * np.stack([g["f_dc_0"], g["f_dc_1"], g["f_dc_2"]], 1), 0, 1)
    colour_class = ((dc[:, None, :] - PROTOS[None]) ** 2).sum(-1).argmin(1)
    obj = -np.ones(n, int)
    for r in truth["runs"]:
        if r["object"] is not None:
            obj[r["gaussians"][0]:r["gaussians"][1]] = r["object"]
    e = safetensors(f"{d}/enc/embeddings.safetensors")
    ids = e["gaussian_ids"].astype(int)
    v = e["embeddings"].astype(np.float32)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    t = text_directions(clip_dir, classes)
    scores = np.full((n, len(classes)), -1.0, np.float32)
    scores[ids] = v @ t.T
    observed = np.zeros(n, bool)
    observed[ids] = True
    sum_a = np.zeros(n)
    sum_a[ids] = e["total_weights"]
    own = scores.argmax(1)

    print(f"\n# {d}\n\n| object | Gaussians | its class | its colour's class | gray | white | other "
          "| gray share by fifth of the height (bottom → top) |\n|---|---:|---:|---:|---:|---:|---:|---|")
    total = np.zeros(6)
    for k, o in enumerate(objects):
        m = (obj == k) & observed
        c, p, cc = o["class"], own[m], colour_class[m]
        wrong = p != c
        row = np.array([m.sum(), (p == c).sum(), (wrong & (p == cc)).sum(),
                        (wrong & (p != cc) & (p == GRAY)).sum(),
                        (wrong & (p != cc) & (p == WHITE)).sum(), 0])
        row[5] = row[0] - row[1:5].sum()
        total += row
        z = means[m, 2] / o["aabb"][1][2]
        bands = np.minimum((z * 5).astype(int), 4)
        gray = wrong & (p != cc) & (p == GRAY)
        by_band = " ".join(f"{gray[bands == b].mean():.2f}" if (bands == b).any() else "–"
                           for b in range(5))
        print(f"| {o['name']} {o['shape']} | {row[0]} | " + " | ".join(
            f"{x / row[0]:.2f}" for x in row[1:]) + f" | {by_band} |")
    print("| all objects | %d | " % total[0] + " | ".join(f"{x / total[0]:.3f}" for x in total[1:]) + " | |")

    answers = {
        "threshold 0.28": lambda c: (scores[:, c] >= 0.28) & observed,
        "argmax": lambda c: (own == c) & observed,
        "true members": lambda c: np.isin(obj, [k for k, o in enumerate(objects) if o["class"] == c]),
    }
    for name in ["segments", "geometric"]:
        path = f"{d}/enc/segments.safetensors" if name == "segments" else f"{d}/geometric.safetensors"
        if not os.path.exists(path):
            continue
        seg = safetensors(path)["segments"].astype(int)
        for wname, w in [("mean", observed.astype(float)), ("Σa-weighted", sum_a)]:
            den = np.bincount(seg, weights=w)
            sm = np.stack([np.bincount(seg, weights=w * np.where(observed, scores[:, c], 0))
                           for c in range(len(classes))], 1)
            sm = np.where(den[:, None] > 0, sm / np.maximum(den[:, None], 1e-30), -1)[seg]
            answers[f"{name} {wname}, 0.28"] = (lambda s: lambda c: (s[:, c] >= 0.28) & observed)(sm)
    names = [f"{o['name']} {o['shape']}" for o in objects]
    print("\n| answer | " + " | ".join(names) + " | objects at IoU ≥ 0.5 |\n|---|" + "---:|" * (len(names) + 1))
    for a, select in answers.items():
        cache = {}
        ious = []
        for k, o in enumerate(objects):
            c = o["class"]
            if c not in cache:
                cache[c] = groups(means, select(c))
            ious.append(best_iou(cache[c], set(np.where(obj == k)[0].tolist())))
        print(f"| {a} | " + " | ".join(f"{x:.2f}" for x in ious) + f" | {sum(x >= 0.5 for x in ious)} |")


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    shared = os.environ.get("SLAG_SHARED")
    if not shared:
        sys.exit("set SLAG_SHARED to the shared folder (fixtures/clip)")
    for folder in sys.argv[1:]:
        run(folder.rstrip("/"), os.path.join(shared, "fixtures", "clip"))
