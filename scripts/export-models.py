#!/usr/bin/env python3
"""Export your own SAM and CLIP models to ONNX in the signatures slag reads ("bring your own models").

Needs python3 with, from PyPI: torch, onnx, segment-anything==1.0 (SAM), open-clip-torch (CLIP);
for MobileSAM also mobilesam-mirror and timm. onnxruntime is optional: when importable, every
exported file is run once as a check.

    export-models.py sam --kind vit_b|vit_l|vit_h|vit_t|tiny [--checkpoint FILE | --random] [--fp16] [--fuse] OUT_DIR
    export-models.py clip --model ViT-B-16|tiny [--pretrained TAG | --random] [--fp16] [--fuse] [--u8-pixels] OUT_DIR

sam  writes OUT_DIR/sam-KIND-encoder.onnx (pixel_values f32[1,3,1024,1024] -> image_embeddings
     f32[1,256,64,64]; ViT-H, anything over 2 GB, or with --external-data: its weights in
     sam-KIND-encoder.onnx.data beside it; keep the two files together) and OUT_DIR/sam-KIND-decoder.onnx (segment_anything's
     SamOnnxModel(return_single_mask=False): image_embeddings, point_coords [P,N,2], point_labels
     [P,N], mask_input, has_mask_input, orig_im_size -> masks, iou_predictions, low_res_masks).
     vit_t is MobileSAM (TinyViT encoder, SAM's decoder; package mobilesam-mirror).
     tiny is a small random ViT for tests (always random).
clip writes OUT_DIR/NAME-visual.onnx (pixel_values f32[B,3,224,224] -> image_embeds f32[B,D]),
     OUT_DIR/NAME-textual.onnx (input_ids i64[B,77] -> text_embeds f32[B,D]), both not normalised,
     OUT_DIR/clip-tokenizer.json (open_clip's CLIP BPE tokenizer for the `tokenizers` crate) and
     OUT_DIR/NAME.json (what was exported, the pair id, token ids of a few prompts), with NAME =
     MODEL-TAG (e.g. ViT-B-16-openai) or MODEL-random. Both towers carry the ONNX metadata
     slag.clip_pair_id = "MODEL/TAG/<sha256 of all CLIP weights, 16 hex>": slag-encoder records it
     with the embeddings and the text side (slag-encoder query, slag-edge) refuses a text tower
     whose id differs.

--fp16: weights and compute in half precision, graph inputs and outputs still f32 (a cast inside
the graph), so slag's signatures are unchanged. Meant for the CUDA execution provider; the SAM
decoder stays f32 (it is small and its prompt coordinates need f32) unless --fp16-decoder.

--fuse (clip): the image tower with ONNX Runtime's fused kernels: each self-attention block is
exported as one com.microsoft MultiHeadAttention node (flash / memory-efficient attention on
CUDA), then, when onnxruntime is importable, its transformer optimizer fuses LayerNorm, the
residual add + LayerNorm and the bias + GELU. Same signature and weights; the export's check
compares the f32 tower with torch on random pixels (cosine). MultiHeadAttention runs in half
precision on CUDA only: check an --fp16 --fuse tower on the GPU (`slag-bench models`).

--u8-pixels (clip): the image tower takes `pixels u8[B,3,224,224]` (the resized crop's RGB bytes)
and scales and normalises them in its graph (scripts/clip-u8-pixels.py); slag then copies a
quarter of the bytes to the GPU per crop. Same embeddings. Recommended on a GPU.

--fuse (sam): the image encoder's attention, relative positions included, as one
com.microsoft MultiHeadAttention node per block (the bias folded into widened query and key
vectors: see fuse_sam_attention). ONNX Runtime's offline transformer optimizer is not run on it
(on ViT-H it did not finish in 8 minutes); the session's own graph optimisations apply. The
export checks the fused encoder against segment_anything's in torch (f32) before exporting.

The SAM decoder does the image's own work once per call, not once per prompt (see
share_image_work: the same function, checked against segment_anything's in torch at export);
--image-work repeated exports it as segment_anything traces it.

--fp16-decoder (sam): the decoder's mask decoder (two-way transformer, upscaling, hypernetwork
and IoU heads) in half precision too. The prompt encoding (the points' positional encoding) and
the mask post-processing stay f32, and so do the graph's inputs and outputs. Its weights are a
few MB, but with many prompts per call its activations are large: on a GPU, half precision
runs it on the tensor cores.
"""
import argparse
import hashlib
import json
import os
import re
import shutil
import sys
import tempfile
from functools import partial
from pathlib import Path

OPSET = 17
# ONNX protobufs cannot exceed 2 GiB; above this the weights go to an external data file.
EXTERNAL_DATA_ABOVE = 1800 << 20

SAM_CHECKPOINTS = {  # the official file names (segment-anything / MobileSAM releases)
    "vit_b": "sam_vit_b_01ec64.pth",
    "vit_l": "sam_vit_l_0b3195.pth",
    "vit_h": "sam_vit_h_4b8939.pth",
    "vit_t": "mobile_sam.pt",
}


def die(msg):
    print(f"export-models: {msg}", file=sys.stderr)
    sys.exit(2)


def sibling_script(file_name):
    """A script of this folder with a hyphenated name, imported as a module."""
    import importlib.util

    path = Path(__file__).resolve().with_name(file_name)
    spec = importlib.util.spec_from_file_location(path.stem.replace("-", "_"), path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def need(module, pip_name):
    try:
        return __import__(module)
    except ImportError as e:
        die(f"python module {module!r} is missing ({e}): pip install {pip_name}")


def onnx_export(torch, module, args, path, input_names, output_names, dynamic_axes=None,
                external=False, custom_opsets=None):
    """Legacy (TorchScript) exporter, opset 17, into a temporary folder (the exporter may scatter
    one file per tensor for models over 2 GB); then one .onnx, plus one .data file when large."""
    import onnx

    path = Path(path)
    with tempfile.TemporaryDirectory(dir=path.parent) as tmp:
        raw = Path(tmp) / "model.onnx"
        with torch.no_grad():
            torch.onnx.export(module, args, str(raw), input_names=input_names,
                              output_names=output_names, dynamic_axes=dynamic_axes,
                              opset_version=OPSET, dynamo=False,
                              custom_opsets=custom_opsets or {})
        size = sum(f.stat().st_size for f in Path(tmp).iterdir())
        model = onnx.load(str(raw))  # also reads external tensors, if any
        data = path.with_name(path.name + ".data")
        for p in (path, data):
            if p.exists():
                p.unlink()
        if external or size > EXTERNAL_DATA_ABOVE:
            onnx.save_model(model, str(path), save_as_external_data=True,
                            all_tensors_to_one_file=True, location=data.name, size_threshold=1024)
        else:
            onnx.save_model(model, str(path))
    return path


def multi_head_attention(torch):
    """A torch function that exports as one ONNX Runtime `com.microsoft::MultiHeadAttention`
    node: `apply(q, k, v, heads, scale)` with q, k, v `[batch, tokens, heads * head_size]` (one
    head size for all three), `scale` a float or None (1/sqrt(head_size), the node's default).
    In torch it computes scaled-dot-product attention, so an export's check against torch
    still applies."""

    class Mha(torch.autograd.Function):
        @staticmethod
        def forward(ctx, q, k, v, heads, scale):
            b, s, d = q.shape
            q, k, v = (t.reshape(b, s, heads, d // heads).transpose(1, 2) for t in (q, k, v))
            o = torch.nn.functional.scaled_dot_product_attention(q, k, v, scale=scale)
            return o.transpose(1, 2).reshape(b, s, d)

        @staticmethod
        def symbolic(g, q, k, v, heads, scale):
            attrs = {"num_heads_i": heads} if scale is None else {"num_heads_i": heads,
                                                                  "scale_f": scale}
            out = g.op("com.microsoft::MultiHeadAttention", q, k, v, **attrs)
            out.setType(q.type())
            return out

    return Mha


def fuse_blocks(blocks, fuse, none_found):
    """Replaces each block's `attn` by `fuse(attn)` (a block whose `fuse` gives None keeps its
    own); dies with `none_found` when no block was fused. Returns the count fused."""
    count = 0
    for block in blocks:
        fused = fuse(getattr(block, "attn", None))
        if fused is None:
            continue
        block.attn = fused
        count += 1
    if count == 0:
        die(none_found)
    return count


def fuse_attention(torch, tower):
    """Replaces every self-attention `nn.MultiheadAttention` of `tower` (open_clip's visual
    transformer) by one ONNX Runtime `com.microsoft::MultiHeadAttention` node in the export: the
    packed q/k/v projection stays a MatMul, the attention itself becomes one fused kernel (flash
    or memory-efficient attention on CUDA) instead of ~20 nodes of reshapes, transposes, two
    matrix products and a softmax. In torch the same module computes scaled-dot-product
    attention, so the export's own check against torch still applies. Returns the count."""

    Mha = multi_head_attention(torch)

    class FusedAttention(torch.nn.Module):
        def __init__(self, mha):
            super().__init__()
            self.weight, self.bias = mha.in_proj_weight, mha.in_proj_bias
            self.out_proj, self.heads = mha.out_proj, mha.num_heads

        def forward(self, q_x, k_x, v_x, need_weights=False, attn_mask=None):
            if attn_mask is not None or k_x is not q_x or v_x is not q_x:
                raise ValueError("fused attention covers unmasked self-attention only")
            q, k, v = torch.nn.functional.linear(q_x, self.weight, self.bias).chunk(3, dim=-1)
            return self.out_proj(Mha.apply(q, k, v, self.heads, None)), None

    def fuse(mha):
        if not isinstance(mha, torch.nn.MultiheadAttention):
            return None
        if not (mha.batch_first and mha._qkv_same_embed_dim and mha.in_proj_bias is not None):
            die("--fuse needs batch-first self-attention with a packed q/k/v projection "
                "(open_clip >= 2.24); this model's attention differs")
        return FusedAttention(mha)

    return fuse_blocks(tower.transformer.resblocks, fuse,
                       "--fuse found no attention block to fuse in this model's visual tower")


def fuse_sam_attention(torch, encoder):
    """Replaces the attention of every block of segment_anything's `ImageEncoderViT` by one
    ONNX Runtime `com.microsoft::MultiHeadAttention` node in the export, relative positions
    included, so that flash attention can run it on CUDA without writing the attention matrix.

    SAM adds a decomposed relative-position bias to the scaled scores (MViTv2):
    s_ij = scale·q_i·k_j + q_i·Rh[h_i, h_j] + q_i·Rw[w_i, w_j], with (h, w) the token's row and
    column in its window (14 × 14) or in the whole 64 × 64 grid (global blocks). Both bias terms
    are dot products of a per-query vector with a one-hot per-key vector, so s_ij is one dot
    product of widened vectors: q'_i = [scale·q_i, q_i·Rh[h_i]ᵀ, q_i·Rw[w_i]ᵀ, 0…] and
    k'_j = [k_j, onehot(h_j), onehot(w_j), 0…], zero-padded to a multiple of 8 (head size
    80 + 14 + 14 → 112 in windows, 80 + 64 + 64 = 208 in global blocks for ViT-H); the values
    are zero-padded to the same size and the padding dropped after. Attention with scale 1 over
    (q', k', v') is then exactly SAM's attention with its bias, and no bias tensor
    (heads × 4096 × 4096 in a global block) is ever formed. In torch the replacement computes
    scaled-dot-product attention on the same widened vectors, so the export's check against
    torch applies; `check_fused_sam_encoder` compares it with the original. Returns the count."""
    from segment_anything.modeling.image_encoder import get_rel_pos

    Mha = multi_head_attention(torch)

    class FusedRelPosAttention(torch.nn.Module):
        def __init__(self, att):
            super().__init__()
            self.qkv, self.proj, self.heads, self.scale = att.qkv, att.proj, att.num_heads, att.scale
            self.rel_pos_h, self.rel_pos_w = att.rel_pos_h, att.rel_pos_w

        def forward(self, x):
            b, h, w, c = x.shape
            n = self.heads
            d = c // n
            q, k, v = self.qkv(x).reshape(b, h, w, 3, n, d).unbind(3)  # each [b, h, w, n, d]
            rh = get_rel_pos(h, h, self.rel_pos_h).to(q.dtype)  # [h (query row), h (key row), d]
            rw = get_rel_pos(w, w, self.rel_pos_w).to(q.dtype)  # [w, w, d]
            # q·Rh[h_i]ᵀ as one batched product per query row, q·Rw[w_i]ᵀ per query column.
            rel_h = (q.permute(1, 0, 2, 3, 4).reshape(h, b * w * n, d) @ rh.transpose(1, 2))
            rel_h = rel_h.reshape(h, b, w, n, h).permute(1, 0, 2, 3, 4)  # [b, h, w, n, h]
            rel_w = (q.permute(2, 0, 1, 3, 4).reshape(w, b * h * n, d) @ rw.transpose(1, 2))
            rel_w = rel_w.reshape(w, b, h, n, w).permute(1, 2, 0, 3, 4)  # [b, h, w, n, w]
            width = d + h + w
            pad = -width % 8
            one_h = torch.eye(h, dtype=q.dtype, device=q.device)[:, None, None, :]
            one_w = torch.eye(w, dtype=q.dtype, device=q.device)[None, :, None, :]
            kh = one_h.expand(h, w, n, h).unsqueeze(0).expand(b, h, w, n, h)
            kw = one_w.expand(h, w, n, w).unsqueeze(0).expand(b, h, w, n, w)
            zq = q.new_zeros(b, h, w, n, pad)
            qw = torch.cat([q * self.scale, rel_h, rel_w, zq], dim=-1)
            kw_ = torch.cat([k, kh, kw, zq], dim=-1)
            vw = torch.cat([v, v.new_zeros(b, h, w, n, width + pad - d)], dim=-1)
            s = h * w
            o = Mha.apply(*(t.reshape(b, s, n * (width + pad)) for t in (qw, kw_, vw)), n, 1.0)
            o = o.reshape(b, h, w, n, width + pad)[..., :d].reshape(b, h, w, c)
            return self.proj(o)

    def fuse(att):
        if not getattr(att, "use_rel_pos", False):
            die("--fuse (sam) needs attention with relative positions (segment_anything's "
                "ImageEncoderViT); this encoder's attention differs")
        return FusedRelPosAttention(att)

    return fuse_blocks(getattr(encoder, "blocks", []), fuse,
                       "--fuse (sam) found no attention block in this image encoder")


def check_fused_sam_encoder(torch, encoder, fused_encoder):
    """Runs segment_anything's image encoder and the fused one (f32; on the GPU when torch has
    one, else the CPU) on the same random pixels; returns the largest absolute difference of the
    image embeddings and their scale; dies when the difference exceeds 1e-3 of the embeddings'
    largest magnitude."""
    g = torch.Generator().manual_seed(3)
    x = torch.randn(1, 3, 1024, 1024, generator=g)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    with torch.no_grad():
        ref = encoder.to(device)(x.to(device)).cpu()
        got = fused_encoder.to(device)(x.to(device)).cpu()
        encoder.to("cpu"), fused_encoder.to("cpu")
    diff, scale = float((got - ref).abs().max()), float(ref.abs().max())
    if not diff <= 1e-3 * max(scale, 1e-6):
        die(f"the fused SAM encoder differs from segment_anything's: max |diff| {diff} "
            f"(embeddings up to {scale})")
    return {"image_embeddings_max_abs_diff": diff, "image_embeddings_max_abs": scale}


def ort_fusions(path, heads, width):
    """ONNX Runtime's transformer optimizer over an export, in place: LayerNormalization,
    SkipLayerNormalization (residual add + LayerNorm) and BiasGelu (the bias add + erf GELU) as
    single contrib kernels. Returns the operators it fused, or None without onnxruntime."""
    try:
        from onnxruntime.transformers import optimizer
        from onnxruntime.transformers.fusion_options import FusionOptions
    except ImportError:
        print("export-models: onnxruntime not importable: LayerNorm / GELU fusions skipped",
              file=sys.stderr)
        return None
    opt = optimizer.optimize_model(str(path), model_type="vit", num_heads=heads,
                                   hidden_size=width, optimization_options=FusionOptions("vit"),
                                   opt_level=0, use_gpu=True)
    fused = {k: v for k, v in opt.get_fused_operator_statistics().items() if v}
    opt.save_model_to_file(str(path))
    return fused


def set_metadata(path, props):
    import onnx

    path = Path(path)
    data = path.with_name(path.name + ".data")
    model = onnx.load(str(path), load_external_data=False)
    old = {p.key: p.value for p in model.metadata_props}
    old.update(props)
    onnx.helper.set_model_props(model, old)
    onnx.save_model(model, str(path))  # external data references are kept as they are
    assert not data.exists() or data.stat().st_size > 0


def io_signature(path):
    import onnx

    m = onnx.load(str(path), load_external_data=False)

    def dims(v):
        return [d.dim_value if d.HasField("dim_value") else -1 for d in v.type.tensor_type.shape.dim]

    def elem(v):
        return onnx.helper.tensor_dtype_to_np_dtype(v.type.tensor_type.elem_type).name

    return ([(v.name, elem(v), dims(v)) for v in m.graph.input],
            [(v.name, elem(v), dims(v)) for v in m.graph.output])


def signature_ok(got, want):
    """Names, element types and ranks equal; a dimension the exporter left dynamic (-1) matches
    any expected size (slag's own check treats it the same way)."""
    def same(g, w):
        return (len(g) == len(w) and
                all(gn == wn and gt == wt and len(gd) == len(wd) and
                    all(x == y or x == -1 or y == -1 for x, y in zip(gd, wd))
                    for (gn, gt, gd), (wn, wt, wd) in zip(g, w)))
    return same(got[0], want[0]) and same(got[1], want[1])


def check_with_ort(path, feeds):
    """Runs the model once with onnxruntime's CPU provider (default, i.e. full, graph
    optimisation, as slag does) when onnxruntime is installed; in a child process, because some
    onnxruntime builds crash on half-precision transformer graphs. Returns the output shapes, or a
    string saying why not. SLAG_EXPORT_NO_CHECK=1 skips it (a CPU run of SAM ViT-H takes
    minutes)."""
    if os.environ.get("SLAG_EXPORT_NO_CHECK") == "1":
        return "skipped (SLAG_EXPORT_NO_CHECK=1)"
    try:
        import onnxruntime  # noqa: F401
    except ImportError:
        return None
    import subprocess

    import numpy as np

    with tempfile.TemporaryDirectory() as tmp:
        np.savez(f"{tmp}/feeds.npz", **feeds)
        code = ("import sys, json, numpy as np, onnxruntime as ort\n"
                "f = dict(np.load(sys.argv[2]))\n"
                "s = ort.InferenceSession(sys.argv[1], providers=['CPUExecutionProvider'])\n"
                "o = s.run(None, f)\n"
                "np.savez(sys.argv[3], *o)\n"
                "print(json.dumps([list(x.shape) for x in o]))\n")
        r = subprocess.run([sys.executable, "-c", code, str(path), f"{tmp}/feeds.npz",
                            f"{tmp}/out.npz"], capture_output=True, text=True)
        if r.returncode != 0:
            msg = (f"onnxruntime {onnxruntime.__version__} CPU failed on {Path(path).name} "
                   f"(exit {r.returncode}): {r.stderr.strip().splitlines()[-1:]}")
            print(f"export-models: warning: {msg}", file=sys.stderr)
            return msg
        out = np.load(f"{tmp}/out.npz")
        check_with_ort.last = [out[k] for k in out.files]
        return json.loads(r.stdout)


def file_sizes(paths):
    out = []
    for p in paths:
        p = Path(p)
        out.append(f"{p.name} {p.stat().st_size / 2**20:.1f} MiB")
        data = p.with_name(p.name + ".data")
        if data.exists():
            out.append(f"{data.name} {data.stat().st_size / 2**20:.1f} MiB")
    return out


# ------------------------------------------------------------------------------------------ SAM
def tiny_sam(modeling, torch):
    """A small SAM with the real architecture (ViT encoder, SAM's prompt encoder and two-way
    transformer decoder) for tests: 96-wide, 2-deep encoder, same 256x64x64 embeddings."""
    enc = modeling.ImageEncoderViT(depth=2, embed_dim=96, img_size=1024, mlp_ratio=4,
                                   norm_layer=partial(torch.nn.LayerNorm, eps=1e-6), num_heads=3,
                                   patch_size=16, qkv_bias=True, use_rel_pos=True,
                                   global_attn_indexes=[1], window_size=14, out_chans=256)
    prompt = modeling.PromptEncoder(embed_dim=256, image_embedding_size=(64, 64),
                                    input_image_size=(1024, 1024), mask_in_chans=16)
    dec = modeling.MaskDecoder(num_multimask_outputs=3,
                               transformer=modeling.TwoWayTransformer(depth=2, embedding_dim=256,
                                                                      mlp_dim=512, num_heads=8),
                               transformer_dim=256, iou_head_depth=3, iou_head_hidden_dim=256)
    return modeling.Sam(image_encoder=enc, prompt_encoder=prompt, mask_decoder=dec,
                        pixel_mean=[123.675, 116.28, 103.53], pixel_std=[58.395, 57.12, 57.375])


def half_decoder(mask_decoder):
    """Converts segment_anything's MaskDecoder to half precision in place, behind f32
    `predict_masks` inputs and outputs (what SamOnnxModel calls): the prompt encoder's f32
    embeddings are cast on the way in, the masks and IoU predictions back on the way out."""
    mask_decoder.half()
    predict = mask_decoder.predict_masks

    def predict_masks(**kw):
        masks, iou = predict(**{k: v.half() for k, v in kw.items()})
        return masks.float(), iou.float()

    mask_decoder.predict_masks = predict_masks


def share_image_work(mask_decoder, expand=False):
    """Replaces segment_anything's `MaskDecoder.predict_masks` (what SamOnnxModel calls) with
    the same computation that does the image's own work once per call instead of once per
    prompt. The original copies the image embedding and its positional encoding once per prompt
    (`repeat_interleave`) before the two-way transformer. Every prompt then projects the same
    4096 image tokens again in the first block: the keys and values of its token-to-image
    attention and the queries of its image-to-token attention. Here the transformer gets the
    image with batch 1; those three projections run once, and the attention products broadcast
    over the prompts (MatMul broadcasts a batch of 1). The image tokens become per-prompt only
    after the first block's image-to-token update, as in the original. The result is the same
    function (the same products and sums per element). Works on any SamOnnxModel decoder whose
    mask input is one per call ([1,1,256,256], as SamOnnxModel's is)."""
    import torch

    dec = mask_decoder

    def predict_masks(image_embeddings, image_pe, sparse_prompt_embeddings,
                      dense_prompt_embeddings):
        prompts = sparse_prompt_embeddings.size(0)
        output_tokens = torch.cat([dec.iou_token.weight, dec.mask_tokens.weight], dim=0)
        output_tokens = output_tokens.unsqueeze(0).expand(prompts, -1, -1)
        tokens = torch.cat((output_tokens, sparse_prompt_embeddings), dim=1)
        src = image_embeddings + dense_prompt_embeddings  # [1, C, h, w]: shared by the prompts
        _, c, h, w = src.shape
        hs, src = dec.transformer(src, image_pe, tokens)  # src: [prompts, h*w, C]
        iou_token_out = hs[:, 0, :]
        mask_tokens_out = hs[:, 1:(1 + dec.num_mask_tokens), :]
        src = src.transpose(1, 2).reshape(prompts, c, h, w)
        upscaled = dec.output_upscaling(src)
        hyper_in = torch.stack([dec.output_hypernetworks_mlps[i](mask_tokens_out[:, i, :])
                                for i in range(dec.num_mask_tokens)], dim=1)
        b, c2, h2, w2 = upscaled.shape
        masks = (hyper_in @ upscaled.view(b, c2, h2 * w2)).view(b, -1, h2, w2)
        return masks, dec.iou_prediction_head(iou_token_out)

    dec.predict_masks = predict_masks
    if expand:
        # Each attention's projections still run once on the batch-1 image tokens, then are
        # copied out to the prompts (Expand) before the products, so that every matrix product
        # has equal batches on both sides instead of a broadcast one.
        import math

        def expanded(a, q, k, v):
            q, k, v = a.q_proj(q), a.k_proj(k), a.v_proj(v)
            b = max(q.shape[0], k.shape[0], v.shape[0])
            q, k, v = (a._separate_heads(t.expand(b, -1, -1), a.num_heads) for t in (q, k, v))
            attn = torch.softmax(q @ k.permute(0, 1, 3, 2) / math.sqrt(q.shape[-1]), dim=-1)
            return a.out_proj(a._recombine_heads(attn @ v))

        for layer in dec.transformer.layers:
            for a in (layer.self_attn, layer.cross_attn_token_to_image,
                      layer.cross_attn_image_to_token):
                a.forward = partial(expanded, a)


def check_shared_decoder(torch, sam, SamOnnxModel, expand):
    """Applies `share_image_work` and checks it in torch against the decoder as traced before,
    on random embeddings and 7 prompts (f32): returns the largest absolute difference of the
    low-resolution mask logits and of the IoU predictions; dies above 1e-4."""
    g = torch.Generator().manual_seed(2)
    feeds = (torch.randn(1, 256, 64, 64, generator=g),
             torch.cat([torch.rand(7, 1, 2, generator=g) * 1024, torch.zeros(7, 1, 2)], 1),
             torch.tensor([[1.0, -1.0]]).repeat(7, 1), torch.zeros(1, 1, 256, 256),
             torch.tensor([0.0]), torch.tensor([742.0, 990.0]))
    with torch.no_grad():
        _, iou_ref, low_ref = SamOnnxModel(sam, return_single_mask=False)(*feeds)
        share_image_work(sam.mask_decoder, expand)
        _, iou, low = SamOnnxModel(sam, return_single_mask=False)(*feeds)
    diff = {"low_res_masks_max_abs_diff": float((low - low_ref).abs().max()),
            "iou_predictions_max_abs_diff": float((iou - iou_ref).abs().max())}
    if max(diff.values()) > 1e-4:
        die(f"the decoder that shares the image's work differs from segment_anything's: {diff}")
    return diff


def export_sam(a):
    torch = need("torch", "torch")
    need("onnx", "onnx")
    if a.kind == "vit_t":
        pkg = need("mobile_sam", "mobilesam-mirror timm")
        from mobile_sam.utils.onnx import SamOnnxModel
    else:
        pkg = need("segment_anything", "segment-anything==1.0")
        from segment_anything.utils.onnx import SamOnnxModel
    if a.kind == "tiny":
        if a.checkpoint:
            die("--kind tiny is a random test model: it takes no --checkpoint")
        a.random = True
    elif not (a.random or a.checkpoint):
        die(f"--kind {a.kind}: pass --checkpoint {SAM_CHECKPOINTS[a.kind]} (the official "
            "checkpoint) or --random (random weights: for timing and tests only)")
    torch.manual_seed(a.seed)
    if a.kind == "tiny":
        from segment_anything import modeling
        sam = tiny_sam(modeling, torch)
    else:
        sam = pkg.sam_model_registry[a.kind](checkpoint=None)
        if a.checkpoint:
            state = torch.load(a.checkpoint, map_location="cpu", weights_only=True)
            sam.load_state_dict(state)
    sam = sam.eval()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    enc_path = out / f"sam-{a.kind}-encoder.onnx"
    dec_path = out / f"sam-{a.kind}-decoder.onnx"

    # Decoder first, before the encoder is converted to half precision.
    torch.backends.mha.set_fastpath_enabled(False) if hasattr(torch.backends, "mha") else None
    shared_check = None
    if a.image_work != "repeated":
        shared_check = check_shared_decoder(torch, sam, SamOnnxModel, a.image_work == "expanded")
    if a.fp16_decoder:
        half_decoder(sam.mask_decoder)
    dummy = {"image_embeddings": torch.randn(1, 256, 64, 64),
             "point_coords": torch.randint(0, 1024, (2, 2, 2), dtype=torch.float),
             "point_labels": torch.tensor([[1, -1], [1, -1]], dtype=torch.float),
             "mask_input": torch.zeros(1, 1, 256, 256),
             "has_mask_input": torch.tensor([0.0]),
             "orig_im_size": torch.tensor([600, 800], dtype=torch.float)}
    onnx_export(torch, SamOnnxModel(sam, return_single_mask=False), tuple(dummy.values()),
                dec_path, input_names=list(dummy),
                output_names=["masks", "iou_predictions", "low_res_masks"],
                dynamic_axes={"point_coords": {0: "num_prompts", 1: "num_points"},
                              "point_labels": {0: "num_prompts", 1: "num_points"}})

    class Encoder(torch.nn.Module):
        def __init__(self, enc, half):
            super().__init__()
            self.enc = enc.half() if half else enc
            self.half = half

        def forward(self, pixel_values):
            if self.half:
                return self.enc(pixel_values.half()).float()
            return self.enc(pixel_values)

    fused = None
    if a.fuse and not a.decoder_only:
        import copy

        image_encoder = copy.deepcopy(sam.image_encoder)
        blocks = fuse_sam_attention(torch, image_encoder)
        fused = {"attention_blocks": blocks,
                 "check_f32": check_fused_sam_encoder(torch, sam.image_encoder, image_encoder)}
        sam.image_encoder = image_encoder.eval()
    if not a.decoder_only:
        enc = Encoder(sam.image_encoder, a.fp16).eval()
        onnx_export(torch, enc, (torch.zeros(1, 3, 1024, 1024),), enc_path,
                    input_names=["pixel_values"], output_names=["image_embeddings"],
                    external=a.external_data)
    source = f"checkpoint {Path(a.checkpoint).name}" if a.checkpoint else f"random (seed {a.seed})"
    files = [dec_path] if a.decoder_only else [enc_path, dec_path]
    for p in files:
        role = "encoder" if p == enc_path else "decoder"
        set_metadata(p, {"slag.sam_kind": a.kind, "slag.sam_role": role, "slag.weights": source,
                         "slag.fused_attention": str(bool(fused and role == "encoder")).lower(),
                         "slag.fp16": str(bool(a.fp16 if role == "encoder" else a.fp16_decoder)).lower()})
    expect_enc = ([("pixel_values", "float32", [1, 3, 1024, 1024])],
                  [("image_embeddings", "float32", [1, 256, 64, 64])])
    got = None if a.decoder_only else io_signature(enc_path)
    if got is not None and not signature_ok(got, expect_enc):
        die(f"{enc_path}: unexpected signature {got}")
    ins, outs = io_signature(dec_path)
    names = ([n for n, _, _ in ins], [n for n, _, _ in outs])
    if names != (list(dummy), ["masks", "iou_predictions", "low_res_masks"]):
        die(f"{dec_path}: unexpected signature {ins} -> {outs}")
    shapes = None if a.decoder_only else check_with_ort(
        enc_path, {"pixel_values": torch.zeros(1, 3, 1024, 1024).numpy()})
    print(json.dumps({"encoder": None if a.decoder_only else str(enc_path),
                      "decoder": str(dec_path), "kind": a.kind,
                      "weights": source, "fp16_encoder": bool(a.fp16),
                      "fp16_decoder": bool(a.fp16_decoder), "decoder_shares_image_work": shared_check,
                      "fused_encoder": fused,
                      "files": file_sizes(files),
                      "onnxruntime_check": shapes}, indent=1))


# ------------------------------------------------------------------------------------------ CLIP
TINY_CLIP = {"embed_dim": 512,
             "vision_cfg": {"image_size": 224, "layers": 2, "width": 128, "patch_size": 16,
                            "head_width": 64},
             "text_cfg": {"context_length": 77, "vocab_size": 49408, "width": 64, "heads": 1,
                          "layers": 2}}
CHECK_TEXTS = ["a photo of a cat", "chair", "A red mug on a wooden table", "",
               "UPPER case,   punctuation!?", "don't stop", "über 9000 cafés"]


def clip_tokenizer_json(tok):
    """open_clip's SimpleTokenizer (CLIP BPE) as a `tokenizers` JSON: the same vocabulary and
    merges, specials named <|startoftext|> / <|endoftext|> (what slag looks up), the same word
    split (open_clip's regex), byte-level alphabet and `</w>` word suffix. slag adds the start/end
    tokens, pads and truncates itself (open_clip.tokenize's rules)."""
    rename = {"<start_of_text>": "<|startoftext|>", "<end_of_text>": "<|endoftext|>"}
    vocab = {rename.get(k, k): v for k, v in tok.encoder.items()}
    for k in ("<|startoftext|>", "<|endoftext|>"):
        if k not in vocab:
            die(f"the tokenizer has no {k} token")
    merges = [list(m) for m in sorted(tok.bpe_ranks, key=tok.bpe_ranks.get)]
    special = lambda name: {"id": name, "ids": [vocab[name]], "tokens": [name]}  # noqa: E731
    return {
        "version": "1.0", "truncation": None, "padding": None, "added_tokens": [],
        "normalizer": {"type": "Sequence", "normalizers": [
            {"type": "NFC"},
            {"type": "Replace", "pattern": {"Regex": r"\s+"}, "content": " "},
            {"type": "Lowercase"}]},
        "pre_tokenizer": {"type": "Sequence", "pretokenizers": [
            {"type": "Split",
             "pattern": {"Regex": r"'s|'t|'re|'ve|'m|'ll|'d|[\p{L}]+|[\p{N}]|[^\s\p{L}\p{N}]+"},
             "behavior": "Removed", "invert": True},
            {"type": "ByteLevel", "add_prefix_space": False, "trim_offsets": True,
             "use_regex": False}]},
        "post_processor": {"type": "TemplateProcessing",
                           "single": [{"SpecialToken": {"id": "<|startoftext|>", "type_id": 0}},
                                      {"Sequence": {"id": "A", "type_id": 0}},
                                      {"SpecialToken": {"id": "<|endoftext|>", "type_id": 0}}],
                           "pair": [{"Sequence": {"id": "A", "type_id": 0}},
                                    {"Sequence": {"id": "B", "type_id": 1}}],
                           "special_tokens": {k: special(k) for k in
                                              ("<|endoftext|>", "<|startoftext|>")}},
        "decoder": {"type": "ByteLevel", "add_prefix_space": True, "trim_offsets": True,
                    "use_regex": True},
        "model": {"type": "BPE", "dropout": None, "unk_token": "<|endoftext|>",
                  "continuing_subword_prefix": None, "end_of_word_suffix": "</w>",
                  "fuse_unk": False, "byte_fallback": False, "ignore_merges": False,
                  "vocab": vocab, "merges": merges},
    }


def weights_sha256(model):
    h = hashlib.sha256()
    for name, t in sorted(model.state_dict().items()):
        h.update(name.encode())
        h.update(str(tuple(t.shape)).encode())
        h.update(t.detach().float().contiguous().cpu().numpy().tobytes())
    return h.hexdigest()


def export_clip(a):
    torch = need("torch", "torch")
    need("onnx", "onnx")
    open_clip = need("open_clip", "open-clip-torch")
    torch.backends.mha.set_fastpath_enabled(False)  # plain ops, exportable to ONNX
    torch.manual_seed(a.seed)
    if a.model == "tiny":
        if a.pretrained:
            die("--model tiny is a random test model: it takes no --pretrained")
        a.random = True
        model = open_clip.CLIP(**TINY_CLIP)
        tok = open_clip.get_tokenizer("ViT-B-32")
    else:
        if not (a.random or a.pretrained):
            tags = [t for m, t in open_clip.list_pretrained() if m == a.model]
            die(f"--model {a.model}: pass --pretrained TAG (one of {tags}; downloads the weights) "
                "or --random")
        if a.model not in open_clip.list_models():
            die(f"unknown open_clip model {a.model!r}; see open_clip.list_models()")
        model = open_clip.create_model(a.model, pretrained=a.pretrained or None, device="cpu")
        tok = open_clip.get_tokenizer(a.model)
    model = model.eval()
    if not isinstance(tok, open_clip.tokenizer.SimpleTokenizer):
        die(f"{a.model} uses {type(tok).__name__}, not CLIP's BPE tokenizer (SimpleTokenizer): "
            "slag's tokenizer (start/end tokens, 77 ids) cannot reproduce it")
    if tok.context_length != 77:
        die(f"{a.model} has context length {tok.context_length}; slag's text side feeds 77 ids")
    if getattr(tok.clean_fn, "__name__", "") not in ("_clean_lower", "<lambda>"):
        print(f"export-models: warning: {a.model}'s tokenizer cleans text with "
              f"{tok.clean_fn.__name__}; slag lower-cases and collapses whitespace only",
              file=sys.stderr)
    tag = "random" if a.random else a.pretrained
    digest = weights_sha256(model)
    pair_id = f"{a.model}/{tag}/{digest[:16]}"
    name = re.sub(r"[^A-Za-z0-9._-]+", "-", f"{a.model}-{tag}").strip("-")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    vis_path, txt_path = out / f"{name}-visual.onnx", out / f"{name}-textual.onnx"
    tok_path, info_path = out / "clip-tokenizer.json", out / f"{name}.json"
    ids = tok(CHECK_TEXTS)
    # Real-valued pixels (not zeros, which hide wrong indexing) for the image tower's check;
    # with --u8-pixels, random bytes and the tower's reference on their normalised values.
    gen = torch.Generator().manual_seed(1)
    check_bytes = torch.randint(0, 256, (3, 3, 224, 224), dtype=torch.uint8, generator=gen)
    u8 = sibling_script("clip-u8-pixels.py")
    mean = torch.tensor(u8.MEAN).view(1, 3, 1, 1)
    std = torch.tensor(u8.STD).view(1, 3, 1, 1)
    check_pixels = ((check_bytes.float() / 255 - mean) / std if a.u8_pixels
                    else torch.rand(3, 3, 224, 224, generator=gen) * 4 - 2)
    with torch.no_grad():
        ref_txt = model.encode_text(ids, normalize=False).float()
        ref_vis = model.encode_image(check_pixels, normalize=False).float()
    image_size = model.visual.image_size
    image_size = image_size[0] if isinstance(image_size, (tuple, list)) else image_size
    if image_size != 224:
        die(f"{a.model} takes {image_size}px images; slag's CLIP crops are 224x224")
    if a.fp16:
        model = model.half()

    class Visual(torch.nn.Module):
        def __init__(self, m, half):
            super().__init__()
            self.m, self.half = m, half

        def forward(self, pixel_values):
            x = pixel_values.half() if self.half else pixel_values
            return self.m.encode_image(x, normalize=False).float()

    class Textual(torch.nn.Module):
        def __init__(self, m):
            super().__init__()
            self.m = m

        def forward(self, input_ids):
            return self.m.encode_text(input_ids, normalize=False).float()

    batch = {0: "batch"}
    visual = Visual(model, a.fp16)
    fused = None
    if a.fuse:
        import copy
        visual = Visual(copy.deepcopy(model), a.fp16)  # the text tower keeps the plain blocks
        heads = fuse_attention(torch, visual.m.visual)
        fused = {"MultiHeadAttention": heads}
    onnx_export(torch, visual, (torch.zeros(2, 3, 224, 224),), vis_path,
                input_names=["pixel_values"], output_names=["image_embeds"],
                dynamic_axes={"pixel_values": batch, "image_embeds": batch},
                custom_opsets={"com.microsoft": 1} if a.fuse else None)
    if a.fuse:
        width = visual.m.visual.transformer.width
        more = ort_fusions(vis_path, visual.m.visual.transformer.resblocks[0].attn.heads, width)
        fused.update(more or {})
    onnx_export(torch, Textual(model), (torch.zeros(2, 77, dtype=torch.long),), txt_path,
                input_names=["input_ids"], output_names=["text_embeds"],
                dynamic_axes={"input_ids": batch, "text_embeds": batch})
    common = {"slag.clip_pair_id": pair_id, "slag.open_clip_model": a.model,
              "slag.pretrained": tag, "slag.weights_sha256": digest,
              "slag.fp16": str(bool(a.fp16)).lower(), "slag.tokenizer": tok_path.name}
    set_metadata(vis_path, {**common, "slag.clip_tower": "visual",
                            "slag.fused": json.dumps(fused) if fused else "none"})
    set_metadata(txt_path, {**common, "slag.clip_tower": "textual"})
    if a.u8_pixels:
        import onnx

        m = onnx.load(str(vis_path))
        u8.u8_pixels(m)
        onnx.save(m, str(vis_path))
    dim = ref_txt.shape[1]
    vis_in = ("pixels", "uint8") if a.u8_pixels else ("pixel_values", "float32")
    for p, want in ((vis_path, ([(*vis_in, [-1, 3, 224, 224])],
                                [("image_embeds", "float32", [-1, dim])])),
                    (txt_path, ([("input_ids", "int64", [-1, 77])],
                                [("text_embeds", "float32", [-1, dim])]))):
        got = io_signature(p)
        if not signature_ok(got, want):
            die(f"{p}: signature {got}, expected {want}")
    tok_path.write_text(json.dumps(clip_tokenizer_json(tok), ensure_ascii=False))
    import numpy as np

    ort_check = None
    txt_shapes = check_with_ort(txt_path, {"input_ids": ids.numpy()})
    if isinstance(txt_shapes, list):
        got, ref = check_with_ort.last[0], ref_txt.numpy()
        cos = (got * ref).sum(1) / (np.linalg.norm(got, axis=1) * np.linalg.norm(ref, axis=1))
        ort_check = {"text_cosine_min_vs_torch_f32": float(cos.min())}
    elif txt_shapes is not None:
        ort_check = {"text": txt_shapes}
    if txt_shapes is not None:
        feeds = ({"pixels": check_bytes.numpy()} if a.u8_pixels
                 else {"pixel_values": check_pixels.numpy()})
        ort_check["visual"] = check_with_ort(vis_path, feeds)
        if isinstance(ort_check["visual"], list):
            got, ref = check_with_ort.last[0], ref_vis.numpy()
            cos = (got * ref).sum(1) / (np.linalg.norm(got, axis=1) * np.linalg.norm(ref, axis=1))
            ort_check["visual_cosine_min_vs_torch_f32"] = float(cos.min())
    info = {"open_clip_model": a.model, "pretrained": tag, "clip_pair_id": pair_id,
            "weights_sha256": digest, "fp16": bool(a.fp16), "fused": fused,
            "pixels": "u8" if a.u8_pixels else "f32", "dim": dim,
            "visual": vis_path.name, "textual": txt_path.name, "tokenizer": tok_path.name,
            "check": {"texts": CHECK_TEXTS, "input_ids": ids.tolist()},
            "onnxruntime_check": ort_check,
            "files": file_sizes([vis_path, txt_path, tok_path])}
    info_path.write_text(json.dumps(info, indent=1))
    print(json.dumps({k: v for k, v in info.items() if k != "check"}, indent=1))


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog=__doc__.split("\n", 2)[2])
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("sam", help="SAM image encoder + prompt decoder")
    s.add_argument("--kind", required=True, choices=["vit_b", "vit_l", "vit_h", "vit_t", "tiny"])
    w = s.add_mutually_exclusive_group()
    w.add_argument("--checkpoint", help="official checkpoint, e.g. " + SAM_CHECKPOINTS["vit_h"])
    w.add_argument("--random", action="store_true", help="random weights (timing, tests)")
    s.add_argument("--fp16", action="store_true", help="half-precision encoder, f32 I/O")
    s.add_argument("--fp16-decoder", action="store_true",
                   help="half-precision mask decoder (prompt encoding f32), f32 I/O")
    s.add_argument("--decoder-only", action="store_true",
                   help="write the decoder alone (the encoder does not depend on decoder flags)")
    s.add_argument("--image-work", choices=["shared", "expanded", "repeated"], default="shared",
                   help="the decoder's per-image work: once per call, products broadcast over "
                        "the prompts (shared), once per call then copied to the prompts "
                        "(expanded), or once per prompt as segment_anything traces it (repeated)")
    s.add_argument("--fuse", action="store_true",
                   help="encoder attention (relative positions included) as ONNX Runtime's "
                        "fused MultiHeadAttention")
    s.add_argument("--external-data", action="store_true",
                   help="encoder weights in ENCODER.onnx.data even when small (always over 2 GB)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("out", metavar="OUT_DIR")
    c = sub.add_parser("clip", help="open_clip image + text towers and tokenizer")
    c.add_argument("--model", default="ViT-B-16", help="open_clip model name, or tiny (tests)")
    w = c.add_mutually_exclusive_group()
    w.add_argument("--pretrained", help="open_clip pretrained tag, e.g. openai (downloads)")
    w.add_argument("--random", action="store_true", help="random weights (timing, tests)")
    c.add_argument("--fp16", action="store_true", help="half-precision towers, f32 I/O")
    c.add_argument("--fuse", action="store_true",
                   help="image tower with ONNX Runtime's fused attention, LayerNorm and GELU")
    c.add_argument("--u8-pixels", action="store_true",
                   help="image tower input pixels u8[B,3,224,224]: CLIP's scaling and "
                        "normalisation in the graph (scripts/clip-u8-pixels.py)")
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("out", metavar="OUT_DIR")
    a = p.parse_args()
    if a.cmd == "sam":
        if a.checkpoint and not os.path.isfile(a.checkpoint):
            die(f"--checkpoint {a.checkpoint}: no such file")
        export_sam(a)
    else:
        export_clip(a)


if __name__ == "__main__":
    main()
