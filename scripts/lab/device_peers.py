"""gsplat's lifting cost on a slag scene, beside slag's own (run by scripts/lab/device-peers.sh).

    python3 device_peers.py SCENE OUT.json [--every N] [--raster-scale S] [--labels L]
                            [--repeats R] [--slag-report report.json]

SCENE is a slag scene folder (`slag-encoder synth-scene` writes one): point_cloud.ply (INRIA
layout, binary little-endian floats: x y z, scale_0..2 (log), rot_0..3 (w x y z), opacity
(logit)), sparse/0/cameras.txt (one PINHOLE camera) and sparse/0/images.txt (COLMAP text).
The views are every N-th of images.txt, rasterized at S times the image size (slag's
`--raster-scale`, same rounding), so gsplat sees the same Gaussians, views and pixels as slag.

Timed per view with CUDA events, after one warm-up pass over the views, R repeats, median:
  - forward: gsplat.rasterization of the RGB (SH degree 0) image;
  - weight: forward + backward of a 1-channel render (colour 1 per Gaussian): the backward gives
    each Gaussian's total blend weight, Σ_p w_kp;
  - labels: forward + backward of an L-channel render (colour 0 per Gaussian, L channels) against
    L disjoint masks (a grid of L blocks): the gradient of Σ_p Σ_j 1[p ∈ M_j] C_pj with respect
    to the colours is a_kj = Σ_{p∈M_j} w_kp, the lifting's quantity for L masks.
With --slag-report, slag's lifting ms per view (raster + the a_kj image stage, and the busiest of
the overlapping back threads) is read from that report.json and the ratios slag / gsplat are printed and written.
Needs torch with CUDA and gsplat (1.5.3; it JIT-compiles its CUDA with the machine's nvcc).
"""
import argparse
import json
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch


def load_ply(path):
    """The Gaussians of an INRIA .ply: means [N,3], quats [N,4] (wxyz, normalised), scales [N,3]
    (exp), opacities [N] (sigmoid), colours [N,3] (from f_dc if present, else grey)."""
    with open(path, "rb") as f:
        names, n = [], None
        line = f.readline().strip()
        if line != b"ply":
            raise SystemExit(f"{path}: not a PLY file")
        while True:
            line = f.readline()
            if not line:
                raise SystemExit(f"{path}: header has no end_header")
            t = line.split()
            if t[:2] == [b"format", b"ascii"]:
                raise SystemExit(f"{path}: ASCII PLY is not supported")
            if t[:2] == [b"element", b"vertex"]:
                n = int(t[2])
            elif t and t[0] == b"element" and n is not None:
                break  # properties of later elements are not ours
            elif t and t[0] == b"property":
                if t[1] != b"float":
                    raise SystemExit(f"{path}: property {t[-1]!r} is {t[1]!r}, expected float")
                names.append(t[2].decode())
            elif t == [b"end_header"]:
                break
        data = np.fromfile(f, dtype="<f4", count=n * len(names))
    if n is None or data.size != n * len(names):
        raise SystemExit(f"{path}: truncated body ({data.size} of {n} x {len(names)} floats)")
    v = data.reshape(n, len(names))
    col = {k: i for i, k in enumerate(names)}

    def cols(*ks):
        missing = [k for k in ks if k not in col]
        if missing:
            raise SystemExit(f"{path}: missing properties {missing}")
        return torch.from_numpy(np.ascontiguousarray(v[:, [col[k] for k in ks]]))

    means = cols("x", "y", "z")
    scales = torch.exp(cols("scale_0", "scale_1", "scale_2"))
    quats = torch.nn.functional.normalize(cols("rot_0", "rot_1", "rot_2", "rot_3"), dim=-1)
    opac = torch.sigmoid(cols("opacity")[:, 0])
    if all(k in col for k in ("f_dc_0", "f_dc_1", "f_dc_2")):
        rgb = (0.5 + 0.28209479177387814 * cols("f_dc_0", "f_dc_1", "f_dc_2")).clamp(0, 1)
    else:
        rgb = torch.full((n, 3), 0.5)
    return means, quats, scales, opac, rgb


def qvec2rotmat(q):
    w, x, y, z = q
    return np.array([[1 - 2 * y * y - 2 * z * z, 2 * x * y - 2 * w * z, 2 * x * z + 2 * w * y],
                     [2 * x * y + 2 * w * z, 1 - 2 * x * x - 2 * z * z, 2 * y * z - 2 * w * x],
                     [2 * x * z - 2 * w * y, 2 * y * z + 2 * w * x, 1 - 2 * x * x - 2 * y * y]])


def load_views(scene, every, scale):
    """(width, height, K [3,3], world-to-camera [V,4,4]) of every `every`-th view, at `scale`."""
    cam = (scene / "sparse/0/cameras.txt").read_text().split("\n")
    cam = [c.split() for c in cam if c.strip() and not c.startswith("#")]
    if len(cam) != 1 or cam[0][1] != "PINHOLE":
        raise SystemExit(f"{scene}: expected one PINHOLE camera, got {cam}")
    W, H = int(cam[0][2]), int(cam[0][3])
    fx, fy, cx, cy = map(float, cam[0][4:8])
    # slag's Intrinsics::scaled: sizes rounded, then the intrinsics scaled by the size ratios.
    w, h = max(1, round(W * scale)), max(1, round(H * scale))
    sx, sy = w / W, h / H
    K = torch.tensor([[fx * sx, 0, cx * sx], [0, fy * sy, cy * sy], [0, 0, 1]],
                     dtype=torch.float32)
    mats = []
    for line in (scene / "sparse/0/images.txt").read_text().split("\n"):
        f = line.split()
        if len(f) < 10 or f[0].startswith("#"):
            continue
        M = np.eye(4)
        M[:3, :3] = qvec2rotmat(np.array(list(map(float, f[1:5]))))
        M[:3, 3] = np.array(list(map(float, f[5:8])))
        mats.append(M)
    mats = mats[::every]
    if not mats:
        raise SystemExit(f"{scene}: no views left with every {every}")
    return w, h, K, torch.tensor(np.stack(mats), dtype=torch.float32)


def timed(fn, views, repeats):
    """Median over `repeats` of the mean ms per view of `fn(view)`, after one warm-up pass."""
    for v in views:
        fn(v)
    torch.cuda.synchronize()
    per = []
    for _ in range(repeats):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        for v in views:
            fn(v)
        end.record()
        torch.cuda.synchronize()
        per.append(start.elapsed_time(end) / len(views))
    return statistics.median(per)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--every", type=int, default=1)
    ap.add_argument("--raster-scale", type=float, default=0.5)
    ap.add_argument("--labels", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--slag-report", type=Path)
    a = ap.parse_args()
    import gsplat
    from gsplat import rasterization

    dev = "cuda"
    t0 = time.time()
    means, quats, scales, opac, rgb = [x.to(dev) for x in load_ply(a.scene / "point_cloud.ply")]
    w, h, K, viewmats = load_views(a.scene, a.every, a.raster_scale)
    K, viewmats = K.to(dev)[None], viewmats.to(dev)
    n, nv = means.shape[0], viewmats.shape[0]
    print(f"scene: {n} Gaussians, {nv} views at {w}x{h} (raster scale {a.raster_scale}), "
          f"loaded in {time.time() - t0:.1f} s; gsplat {gsplat.__version__}", flush=True)

    def render(v, colors):
        img, _, _ = rasterization(means, quats, scales, opac, colors, viewmats[v:v + 1], K, w, h,
                                  packed=False)
        return img

    # L disjoint masks: a grid of blocks covering the image, one-hot per pixel [1, h, w, L].
    L = a.labels
    gx = int(math.ceil(math.sqrt(L)))
    gy = int(math.ceil(L / gx))
    ys = torch.arange(h, device=dev) * gy // h
    xs = torch.arange(w, device=dev) * gx // w
    label = (ys[:, None] * gx + xs[None, :]).clamp(max=L - 1)
    onehot = torch.nn.functional.one_hot(label, L).float()[None]
    ones = torch.ones(n, 1, device=dev)
    zeros_l = torch.zeros(n, L, device=dev)
    views = list(range(nv))

    def forward(v):
        with torch.no_grad():
            render(v, rgb)

    def weight(v):
        c = ones.clone().requires_grad_(True)
        render(v, c).sum().backward()

    def labels(v):
        c = zeros_l.clone().requires_grad_(True)
        (render(v, c) * onehot).sum().backward()
        return c.grad

    t0 = time.time()
    forward(0), weight(0), labels(0)
    torch.cuda.synchronize()
    print(f"first calls (JIT compile or load of gsplat's CUDA) {time.time() - t0:.1f} s",
          flush=True)
    # The gradient is a_kj: check it against a direct sum for one label on view 0 (the weights of
    # a 1-channel render's backward restricted to that label's pixels).
    g = labels(0)
    j = int(g.sum(0).argmax())  # the label with the most weight (some blocks may see only sky)
    c1 = ones.clone().requires_grad_(True)
    (render(0, c1)[..., 0] * onehot[..., j]).sum().backward()
    err = (g[:, j] - c1.grad[:, 0]).abs().max().item()
    scale_ref = c1.grad.abs().max().item()
    if not scale_ref > 0:
        raise SystemExit("check: view 0 has no weight in any label; the scene or views are wrong")
    print(f"check: a_k{j} from the {L}-label backward vs a 1-channel masked backward: max |diff| "
          f"{err:.3g} (max a_k{j} {scale_ref:.3g}); Gaussians with a_kj > 0 on view 0: "
          f"{int((g > 0).any(1).sum())}", flush=True)
    res = {
        "gaussians": n, "views": nv, "width": w, "height": h, "raster_scale": a.raster_scale,
        "labels": L, "repeats": a.repeats, "gsplat": gsplat.__version__,
        "torch": torch.__version__, "gpu": torch.cuda.get_device_name(0),
        "check_max_abs_diff": err, "check_max_a": scale_ref,
    }
    for name, fn in [("forward_ms", forward), ("weight_fwd_bwd_ms", weight),
                     ("labels_fwd_bwd_ms", labels)]:
        res[name] = timed(fn, views, a.repeats)
        print(f"gsplat {name}: {res[name]:.2f} ms / view", flush=True)
    if a.slag_report:
        r = json.loads(a.slag_report.read_text())
        t, c = r["timings"], r["counts"]
        v = max(1, c["views_used"])
        raster = 1000 * t["raster"] / v
        agg = 1000 * t["image_aggregate"] / v
        res["slag"] = {
            "views": c["views_used"], "gaussians": c["gaussians"],
            "masks_per_image": c["masks"] / v, "raster_ms": raster, "a_kj_host_ms": agg,
            "lifting_ms": raster + agg, "device_sum_views": c.get("device_sum_views"),
            "peak_rss_bytes": c.get("peak_rss_bytes"), "rasterizer": r["models"]["rasterizer"],
        }
        lift = raster + agg
        # The back threads of a rasterizer (prepare, raster, image) overlap: the pipeline
        # sustains one view per busiest thread's busy time per view.
        back = [w for w in r.get("workers", [])
                if w["name"].split("-")[0] in ("prepare", "raster", "image") and w["images"]]
        busiest = max((1000 * w["busy_s"] / w["images"] for w in back), default=lift)
        res["slag"]["back_threads_ms"] = {w["name"]: 1000 * w["busy_s"] / w["images"] for w in back}
        res["slag"]["lifting_pipelined_ms"] = busiest
        res["ratios"] = {
            "slag_lifting_over_gsplat_labels": lift / res["labels_fwd_bwd_ms"],
            "slag_pipelined_over_gsplat_labels": busiest / res["labels_fwd_bwd_ms"],
            "slag_lifting_over_gsplat_forward": lift / res["forward_ms"],
            "gsplat_labels_over_forward": res["labels_fwd_bwd_ms"] / res["forward_ms"],
        }
        print(f"slag lifting pipelined: {busiest:.2f} ms / view (busiest back thread; "
              + ", ".join(f"{k} {x:.1f}" for k, x in res["slag"]["back_threads_ms"].items()) + ")")
        print(f"slag lifting: {lift:.2f} ms / view (raster {raster:.2f} + a_kj host {agg:.2f}; "
              f"{c['masks'] / v:.1f} masks / image, device sums on {c.get('device_sum_views')} "
              f"of {v} views)")
        for k, x in res["ratios"].items():
            print(f"ratio {k}: {x:.2f}")
    a.out.write_text(json.dumps(res, indent=2))


if __name__ == "__main__":
    sys.exit(main())
