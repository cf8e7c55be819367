#!/usr/bin/env python3
"""Where an ONNX model's time goes on ONNX Runtime's CUDA provider: the host copies, the
per-node launches, or the GPU's own work. For each model, median wall time per run of:

  host     session.run with numpy inputs and outputs (what slag does for its host tensors)
  bound    IO binding: inputs already on the GPU, outputs left there (no host copies)
  graph    the same with the CUDA provider's `enable_cuda_graph` (the run replays one captured
           CUDA graph: no per-node launch cost; needs fixed shapes and every node on the GPU)

host - bound is the copies; bound - graph is the launch overhead; graph is close to the GPU's
own time. GPU machine only (onnxruntime-gpu's Python package, numpy); not part of CI.

usage: python3 scripts/lab/device_ort_cuda_graph.py [--repeats N] MODEL.onnx[:dim=value,...] ...
  dims name a dynamic axis (e.g. batch=64, num_prompts=256, num_points=2); unnamed ones are 1.
Prints one JSON line per model and a Markdown table.
"""
import argparse
import json
import statistics
import sys
import time

import numpy as np
import onnxruntime as ort

DEV = "cuda"  # --cpu: "cpu", to try the script itself on a machine without a GPU

NP = {"tensor(float)": np.float32, "tensor(float16)": np.float16, "tensor(int64)": np.int64,
      "tensor(int32)": np.int32, "tensor(uint8)": np.uint8}


def inputs_for(sess, dims, rng):
    """Random inputs of the model's declared shapes; SAM's prompt inputs get valid values."""
    feeds = {}
    for i in sess.get_inputs():
        shape = [d if isinstance(d, int) else int(dims.get(d, 1)) for d in i.shape]
        dt = NP[i.type]
        if i.name == "point_coords":
            x = rng.uniform(0, 1024, shape)
        elif i.name == "point_labels":
            x = np.ones(shape)
            if shape[-1] > 1:
                x[..., -1] = -1
        elif i.name in ("has_mask_input", "mask_input"):
            x = np.zeros(shape)
        elif i.name == "orig_im_size":
            x = np.array([742, 990])
        elif dt == np.uint8:
            x = rng.integers(0, 256, shape)
        else:
            x = rng.standard_normal(shape)
        feeds[i.name] = np.ascontiguousarray(x.astype(dt))
    return feeds


def median_ms(fn, repeats):
    for _ in range(3):
        fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(ts)


def session(path, graph):
    opts = ort.SessionOptions()
    if DEV == "cpu":
        return ort.InferenceSession(path, opts, providers=["CPUExecutionProvider"])
    prov = ("CUDAExecutionProvider", {"device_id": "0", "enable_cuda_graph": "1" if graph else "0"})
    return ort.InferenceSession(path, opts, providers=[prov])


def bind(sess, feeds):
    """IO binding with the inputs copied to the GPU once and the outputs left there; the
    binding and the device values it holds."""
    b = sess.io_binding()
    keep = []
    for name, x in feeds.items():
        v = ort.OrtValue.ortvalue_from_numpy(x, DEV, 0)
        keep.append(v)
        b.bind_ortvalue_input(name, v)
    for o in sess.get_outputs():
        b.bind_output(o.name, DEV, 0)
    return b, keep


def runner(sess, b):
    def run():
        sess.run_with_iobinding(b)
        b.synchronize_outputs()
    return run


def bound_runner(sess, feeds):
    """Inputs on the GPU, outputs left there."""
    b, keep = bind(sess, feeds)
    return runner(sess, b), keep


def graph_runner(sess, feeds):
    """IO binding at fixed GPU addresses (inputs and outputs preallocated), as CUDA graphs need."""
    b, keep = bind(sess, feeds)
    # One plain bound run gives the output shapes; then bind preallocated outputs.
    sess.run_with_iobinding(b)
    shapes = [(o.name, v.shape(), v.data_type()) for o, v in zip(sess.get_outputs(),
                                                                 b.get_outputs())]
    b.clear_binding_outputs()
    for name, shape, dt in shapes:
        t = {"tensor(float)": np.float32, "tensor(float16)": np.float16}.get(dt, np.float32)
        v = ort.OrtValue.ortvalue_from_shape_and_type(shape, t, DEV, 0)
        keep.append(v)
        b.bind_ortvalue_output(name, v)
    return runner(sess, b), keep


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--cpu", action="store_true", help="CPU provider, no CUDA graph (a dry run)")
    ap.add_argument("models", nargs="+")
    a = ap.parse_args()
    global DEV
    DEV = "cpu" if a.cpu else "cuda"
    rng = np.random.default_rng(0)
    rows = []
    for spec in a.models:
        path, _, dimspec = spec.partition(":")
        dims = dict(kv.split("=") for kv in dimspec.split(",") if kv)
        row = {"model": path, "dims": dims}
        try:
            s = session(path, False)
            feeds = inputs_for(s, dims, rng)
            row["host_ms"] = median_ms(lambda: s.run(None, feeds), a.repeats)
            run, _keep = bound_runner(s, feeds)
            row["bound_ms"] = median_ms(run, a.repeats)
            ref = s.run(None, feeds)
            del s
        except Exception as e:  # noqa: BLE001 - reported, next model
            row["error"] = f"{type(e).__name__}: {e}"[:400]
            print(json.dumps(row), flush=True)
            rows.append(row)
            continue
        try:
            g = session(path, True)
            run, keep = graph_runner(g, feeds)
            row["graph_ms"] = median_ms(run, a.repeats)
            out = [v.numpy() for v in keep[len(feeds):]]
            row["graph_max_abs_diff"] = max(
                float(np.max(np.abs(o.astype(np.float32) - r.astype(np.float32))))
                for o, r in zip(out, ref))
        except Exception as e:  # noqa: BLE001 - reported
            row["graph_error"] = f"{type(e).__name__}: {e}"[:600]
        print(json.dumps(row), flush=True)
        rows.append(row)
    print("\n| model | dims | host ms | bound ms | CUDA graph ms | graph vs host, max abs diff |")
    print("|---|---|---:|---:|---:|---:|")
    for r in rows:
        f = lambda k: f"{r[k]:.2f}" if k in r else "–"  # noqa: E731
        print(f"| {r['model'].split('/')[-2]}/{r['model'].split('/')[-1]} | "
              f"{','.join(f'{k}={v}' for k, v in r['dims'].items())} | {f('host_ms')} | "
              f"{f('bound_ms')} | {f('graph_ms')} | {r.get('graph_max_abs_diff', r.get('graph_error', r.get('error', '–')))} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
