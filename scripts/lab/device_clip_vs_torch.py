"""CLIP ViT-B/16 image tower, random weights: torch on the GPU vs ONNX Runtime (what slag-encoder
runs), same model, same batch of 32 crops. Runs on a GPU machine (torch + timm + onnxruntime
there); NOT part of CI. Writes OUT/vitb16-clip-visual.onnx (for `slag-encoder bench --clip-visual`)
and prints a small table.

    python3 scripts/lab/device_clip_vs_torch.py OUT_DIR
"""

import os
import sys
import time

import numpy as np
import onnxruntime as ort
import timm
import torch

out = sys.argv[1] if len(sys.argv) > 1 else "/tmp"
os.makedirs(out, exist_ok=True)
torch.manual_seed(0)
# open_clip's ViT-B/16 image tower layout (timm's CLIP variant), projection to 512 as CLIP does.
model = timm.create_model("vit_base_patch16_clip_224", pretrained=False, num_classes=512).eval()
x = torch.randn(32, 3, 224, 224)
path = os.path.join(out, "vitb16-clip-visual.onnx")
with torch.no_grad():
    torch.onnx.export(
        model, x[:1], path, input_names=["pixel_values"], output_names=["image_embeds"],
        dynamic_axes={"pixel_values": {0: "batch"}, "image_embeds": {0: "batch"}}, opset_version=17,
        dynamo=False,
    )
print("exported", path, os.path.getsize(path) // (1 << 20), "MiB")

dev = torch.device("cuda")
rows = []
for dtype in (torch.float16, torch.float32):
    m = model.to(dev, dtype)
    xb = x.to(dev, dtype)
    with torch.no_grad():
        for _ in range(10):
            m(xb)
        torch.cuda.synchronize()
        times = []
        for _ in range(50):
            s, e = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            s.record()
            m(xb)
            e.record()
            torch.cuda.synchronize()
            times.append(s.elapsed_time(e))
    rows.append((f"torch {str(dtype).split('.')[-1]} on {torch.cuda.get_device_name()}", float(np.median(times))))

# Matrix rate for the floor: a large bf16/fp16 product on this GPU.
a = torch.randn(8192, 8192, device=dev, dtype=torch.float16)
b = torch.randn(8192, 8192, device=dev, dtype=torch.float16)
for _ in range(3):
    a @ b
torch.cuda.synchronize()
s, e = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
s.record()
for _ in range(10):
    a @ b
e.record()
torch.cuda.synchronize()
tflops = 10 * 2 * 8192**3 / (s.elapsed_time(e) / 1e3) / 1e12
# ViT-B/16 at 224: ~17.6 GFLOP (multiply-adds x2) per image; count it from the model's linear layers.
n_tokens = 197
params_linear = sum(p.numel() for n, p in model.named_parameters() if p.dim() == 2)
attn = 12 * 2 * 2 * n_tokens * n_tokens * 768  # QK^T and AV per layer
flops = 2 * n_tokens * params_linear + attn
floor_ms = 32 * flops / (tflops * 1e12) * 1e3

sess_opts = ort.SessionOptions()
sess_opts.intra_op_num_threads = os.cpu_count()
sess = ort.InferenceSession(path, sess_opts, providers=["CPUExecutionProvider"])
xn = x.numpy()
sess.run(None, {"pixel_values": xn})
times = []
for _ in range(3):
    t0 = time.perf_counter()
    sess.run(None, {"pixel_values": xn})
    times.append((time.perf_counter() - t0) * 1e3)
rows.append((f"ONNX Runtime {ort.__version__} CPU EP, {os.cpu_count()} cores (providers here: {ort.get_available_providers()})", float(np.median(times))))

print(f"\nViT-B/16 image tower, batch 32 x 224x224: {flops/1e9:.1f} GFLOP/image; measured fp16 matrix rate {tflops:.0f} TFLOP/s -> floor {floor_ms:.2f} ms / 32")
print("| runtime | ms / 32 crops | x floor |")
print("|---|---:|---:|")
for name, ms in rows:
    print(f"| {name} | {ms:.2f} | {ms/floor_ms:.1f} |")

# For `slag-bench stages --torch`: the same timings as JSON.
import json  # noqa: E402

with open(os.path.join(out, "clip-vs-torch.json"), "w") as f:
    json.dump({"model": os.path.basename(path), "batch": 32, "fp16_ms": rows[0][1],
               "fp32_ms": rows[1][1], "ort_cpu_ms": rows[2][1], "gflop_per_image": flops / 1e9,
               "matmul_tflops_fp16": tflops}, f, indent=2)
