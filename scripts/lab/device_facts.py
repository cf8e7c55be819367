"""Measured rates of a GPU machine and FLOPs of ONNX models: the floors of
`slag-bench stages`. Runs there (torch, onnx and numpy are installed); NOT part of CI.

    python3 scripts/lab/device_facts.py OUT.json [MODEL.onnx ...]

Writes OUT.json:
  gpu                    name of GPU 0 (torch)
  host_cores             os.cpu_count()
  matmul_tflops_fp16     8192^3 fp16 matrix product, median of 3 batches of 10 (dense, 2 FLOP per FMA)
  matmul_tflops_fp32     the same in fp32 with TF32 off (what an fp32 model gets)
  gpu_copy_gbps          device-to-device copy of 1 GiB, bytes read + written per second
  d2h_gbps / h2d_gbps    1 GiB between the GPU and pinned host memory, bytes per second
  host_copy_gbps         1 GiB host-to-host copy with all cores (torch CPU), read + written
  host_copy_1t_gbps      the same on one thread (numpy)
  models                 {path: {"gflop": FLOPs of one inference at batch 1 / 1e9,
                                 "inputs": the concrete input shapes used}}
FLOPs count MatMul, Gemm and Conv nodes from ONNX shape inference (2 per multiply-add), with
every dynamic input dimension set to 1 (batch 1; SAM's decoder: 1 point); attention's QK^T and
AV are MatMuls and are counted, element-wise ops are not (they are bandwidth, not FLOPs).
"""

import json
import os
import sys
import time

import numpy as np
import onnx
from onnx import shape_inference


def cuda_ms(fn, reps):
    import torch

    s, e = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    s.record()
    for _ in range(reps):
        fn()
    e.record()
    torch.cuda.synchronize()
    return s.elapsed_time(e) / reps


def matmul_tflops(dtype):
    import torch

    n = 8192
    a = torch.randn(n, n, device="cuda", dtype=dtype)
    b = torch.randn(n, n, device="cuda", dtype=dtype)
    for _ in range(3):
        a @ b
    torch.cuda.synchronize()
    ms = sorted(cuda_ms(lambda: a @ b, 10) for _ in range(3))[1]
    return 2 * n**3 / (ms / 1e3) / 1e12


def rates():
    import torch

    torch.backends.cuda.matmul.allow_tf32 = False
    out = {"gpu": torch.cuda.get_device_name(0), "host_cores": os.cpu_count()}
    out["matmul_tflops_fp16"] = matmul_tflops(torch.float16)
    out["matmul_tflops_fp32"] = matmul_tflops(torch.float32)
    nbytes = 1 << 30
    src = torch.empty(nbytes, dtype=torch.uint8, device="cuda")
    dst = torch.empty_like(src)
    dst.copy_(src)
    torch.cuda.synchronize()
    out["gpu_copy_gbps"] = 2 * nbytes / (cuda_ms(lambda: dst.copy_(src), 20) / 1e3) / 1e9
    host = torch.empty(nbytes, dtype=torch.uint8, pin_memory=True)
    host.copy_(src)
    torch.cuda.synchronize()
    out["d2h_gbps"] = nbytes / (cuda_ms(lambda: host.copy_(src, non_blocking=True), 10) / 1e3) / 1e9
    out["h2d_gbps"] = nbytes / (cuda_ms(lambda: src.copy_(host, non_blocking=True), 10) / 1e3) / 1e9
    a = torch.ones(nbytes, dtype=torch.uint8)
    b = torch.empty_like(a)
    b.copy_(a)
    t = time.perf_counter()
    for _ in range(5):
        b.copy_(a)
    out["host_copy_gbps"] = 5 * 2 * nbytes / (time.perf_counter() - t) / 1e9
    an = np.ones(nbytes // 4, dtype=np.float32)
    bn = np.empty_like(an)
    np.copyto(bn, an)
    t = time.perf_counter()
    for _ in range(3):
        np.copyto(bn, an)
    out["host_copy_1t_gbps"] = 3 * 2 * nbytes / (time.perf_counter() - t) / 1e9
    return out


def dims(vi):
    return [d.dim_value if d.HasField("dim_value") else None for d in vi.type.tensor_type.shape.dim]


def model_gflop(path):
    m = onnx.load(path)
    inits = {i.name for i in m.graph.initializer}
    used = {}
    for inp in m.graph.input:
        if inp.name in inits:
            continue
        for d in inp.type.tensor_type.shape.dim:
            if not d.HasField("dim_value"):
                d.ClearField("dim_param")
                d.dim_value = 1
        used[inp.name] = dims(inp)
    m = shape_inference.infer_shapes(m, data_prop=True)
    shapes = {vi.name: dims(vi) for vi in list(m.graph.value_info) + list(m.graph.input) + list(m.graph.output)}
    for i in m.graph.initializer:
        shapes[i.name] = list(i.dims)
    total, unknown = 0, 0

    def prod(xs):
        p = 1
        for x in xs:
            p *= x
        return p

    for n in m.graph.node:
        if n.op_type not in ("MatMul", "Gemm", "Conv"):
            continue
        a = shapes.get(n.input[0])
        b = shapes.get(n.input[1])
        y = shapes.get(n.output[0])
        if not a or not b or not y or None in a or None in b or None in y:
            unknown += 1
            continue
        if n.op_type == "Conv":
            total += 2 * prod(y) * prod(b[1:])  # weights [Cout, Cin/groups, kh, kw]
        elif n.op_type == "Gemm":
            trans_a = next((at.i for at in n.attribute if at.name == "transA"), 0)
            k = a[0] if trans_a else a[1]
            total += 2 * prod(y) * k
        else:
            total += 2 * prod(y) * a[-1]
    return {"gflop": total / 1e9, "inputs": used, "nodes_with_unknown_shapes": unknown}


def main():
    out_path = sys.argv[1]
    facts = rates() if os.environ.get("SLAG_FACTS_NO_RATES") != "1" else {}
    facts["models"] = {}
    for path in sys.argv[2:]:
        facts["models"][os.path.basename(path)] = model_gflop(path)
    with open(out_path, "w") as f:
        json.dump(facts, f, indent=2)
    print(json.dumps(facts, indent=2))


if __name__ == "__main__":
    main()
