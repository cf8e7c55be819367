#!/usr/bin/env python3
"""Rewrite an exported f32 ONNX model with ONNX Runtime's transformer fusions, then in half
precision with f32 inputs and outputs: IN_F32.onnx -> OUT.onnx.

    optimize-models.py clip IN_F32.onnx OUT.onnx [--model-type vit|clip] [--no-fp16]
    optimize-models.py sam-encoder IN_F32.onnx OUT.onnx [--no-fp16]

Why: the plain exports of scripts/export-models.py spell attention, LayerNorm and GELU out as
dozens of small nodes (MatMul, Reshape, Transpose, Softmax, ReduceMean, Pow, Erf ...). ONNX
Runtime runs each as its own kernel and cannot use its fused attention (flash or memory-efficient
kernels) on them. `onnxruntime.transformers.optimizer` recognises those subgraphs and replaces
them with its contrib operators (Attention / MultiHeadAttention, SkipLayerNormalization,
LayerNormalization, BiasGelu / FastGelu); `convert_float_to_float16(keep_io_types=True)` then
turns weights and compute to fp16 while the graph's inputs and outputs stay f32, so slag's
signatures (pixel_values f32 -> image_embeds f32; image_embeddings f32) hold unchanged.

Start from the f32 export (not --fp16): the fusions match the f32 graph, and the fp16 conversion
afterwards keeps LayerNorm and Softmax accumulating in f32 inside the fused kernels.

Prints one JSON object: the operators fused, node counts before and after, file sizes. The result
must be checked against the unfused model on real inputs (`slag-bench models`, cosine per crop)
before it is used: a fusion that misfires changes the numbers, not the signature.

needs: pip install onnx onnxruntime (the CPU wheel is enough: the rewrite runs no session)
"""
import argparse
import json
import os
import sys
from collections import Counter


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("kind", choices=["clip", "sam-encoder"])
    p.add_argument("src")
    p.add_argument("dst")
    p.add_argument("--model-type", default=None,
                   help="optimizer model type (default: vit for both kinds)")
    p.add_argument("--num-heads", type=int, default=0, help="attention heads (0: from the graph)")
    p.add_argument("--hidden-size", type=int, default=0, help="model width (0: from the graph)")
    p.add_argument("--no-fp16", action="store_true", help="keep f32 (fusions only)")
    a = p.parse_args()
    import onnx
    from onnxruntime.transformers import optimizer
    from onnxruntime.transformers.fusion_options import FusionOptions

    model_type = a.model_type or "vit"
    before = Counter(n.op_type for n in onnx.load(a.src, load_external_data=False).graph.node)
    options = FusionOptions(model_type)
    # Attention whose mask is absent; no shape-inference-only rewrites that need a session.
    opt = optimizer.optimize_model(a.src, model_type=model_type, num_heads=a.num_heads,
                                   hidden_size=a.hidden_size, optimization_options=options,
                                   opt_level=0, use_gpu=True, only_onnxruntime=False)
    fused = opt.get_fused_operator_statistics()
    if not a.no_fp16:
        opt.convert_float_to_float16(keep_io_types=True)
    big = sum(t.ByteSize() if hasattr(t, "ByteSize") else 0 for t in opt.model.graph.initializer) > (1800 << 20)
    if os.path.exists(a.dst):
        os.remove(a.dst)
    opt.save_model_to_file(a.dst, use_external_data_format=big)
    after = Counter(n.op_type for n in opt.model.graph.node)
    print(json.dumps({
        "kind": a.kind, "model_type": model_type, "fp16": not a.no_fp16,
        "fused": {k: v for k, v in fused.items() if v},
        "nodes_before": sum(before.values()), "nodes_after": sum(after.values()),
        "ops_after": dict(after.most_common(15)),
        "bytes": os.path.getsize(a.dst),
    }))


if __name__ == "__main__":
    sys.exit(main())
