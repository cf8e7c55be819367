#!/usr/bin/env python3
"""Derive a SAM decoder that returns only what slag reads: IN -> OUT.

segment_anything's `SamOnnxModel` decoder returns `masks` (P x 4 x H x W: the low-resolution
logits upsampled to 1024 x 1024, cropped, and upsampled again to the image size),
`iou_predictions` and `low_res_masks` (P x 4 x 256 x 256). ONNX Runtime computes every output of
a graph on every run, asked for or not, and slag's default mask post-processing
(`MaskPostprocess::LowRes`) reads only the last two: it upsamples the candidates that pass the
predicted-IoU filter itself, the same way. This script cuts the graph down to the nodes those two
outputs need (onnx.utils.extract_model). The six inputs stay, `orig_im_size` unused, so the file
drops in wherever the full decoder does, with identical masks; `--sam-postprocess graph` refuses
it. Works on any SamOnnxModel export (ViT-B/L/H, MobileSAM; f32 or fp16), under 2 GB.

--f16-multimask (for a decoder that computes its mask logits in f16, `export-models.py sam
--fp16-decoder`): `low_res_masks` becomes f16[P, 3, 256, 256], the multimask channels 1..3
only (automatic mask generation never reads channel 0) taken before the decoder's last cast to
f32. The values are the decoder's own, bit for bit; what each call copies from the GPU to the
host shrinks from 4 x 4 to 3 x 2 bytes per logit (268 MB -> 101 MB for 256 prompts). A decoder
whose logits are f32 is refused: rounding them to f16 would move mask borders.

usage: python3 scripts/sam-decoder-low-res.py [--f16-multimask] IN.onnx OUT.onnx
  e.g. sam-vit_h-decoder.onnx sam-vit_h-decoder-low-res.onnx
needs: pip install onnx
"""
import sys

INPUTS = ["image_embeddings", "point_coords", "point_labels", "mask_input", "has_mask_input",
          "orig_im_size"]
OUTPUTS = ["iou_predictions", "low_res_masks"]


def f16_multimask(model, path):
    """Rewrites `model` (already cut to OUTPUTS) in place so that `low_res_masks` is the f16
    tensor its final Cast widens, sliced to channels 1..3; exits when the logits are not f16."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper
    import numpy as np

    g = model.graph
    producer = next((n for n in g.node if "low_res_masks" in n.output), None)
    inferred = onnx.shape_inference.infer_shapes(model)
    types = {v.name: v.type.tensor_type.elem_type
             for v in list(inferred.graph.value_info) + list(inferred.graph.input)}
    to = next((a.i for a in producer.attribute if a.name == "to"), None) if producer else None
    if (producer is None or producer.op_type != "Cast" or to != TensorProto.FLOAT
            or types.get(producer.input[0]) != TensorProto.FLOAT16):
        sys.exit(f"{path}: its low_res_masks are not an f16 tensor cast to f32 at the end, so "
                 "--f16-multimask would round them; export the decoder with "
                 "`export-models.py sam --fp16-decoder`, or leave the flag out")
    half = producer.input[0]
    if any(half in n.input for n in g.node if n is not producer) or any(
            o.name == half for o in g.output):
        sys.exit(f"{path}: the f16 logits feed other nodes too; this decoder's graph is not "
                 "SamOnnxModel's")
    g.node.remove(producer)
    consts = {"lrm_starts": [1], "lrm_ends": [4], "lrm_axes": [1]}
    g.initializer.extend(numpy_helper.from_array(np.array(v, dtype=np.int64), name=k)
                         for k, v in consts.items())
    g.node.append(helper.make_node("Slice", [half, *consts], ["low_res_masks"],
                                   name="low_res_masks_multimask_f16"))
    out = next(o for o in g.output if o.name == "low_res_masks")
    out.type.tensor_type.elem_type = TensorProto.FLOAT16
    out.type.tensor_type.shape.dim[1].ClearField("dim_param")
    out.type.tensor_type.shape.dim[1].dim_value = 3
    onnx.checker.check_model(model)


def main(argv):
    args = [a for a in argv[1:] if a != "--f16-multimask"]
    if len(args) != 2 or any(a.startswith("--") for a in args):
        sys.exit(__doc__)
    import onnx
    import onnx.utils
    src, dst = args
    model = onnx.load(src)
    have_in = [i.name for i in model.graph.input]
    have_out = [o.name for o in model.graph.output]
    if have_in != INPUTS or have_out != ["masks"] + OUTPUTS:
        sys.exit(f"{src}: not a SamOnnxModel decoder (inputs {have_in}, outputs {have_out}); "
                 f"expected inputs {INPUTS} and outputs {['masks'] + OUTPUTS}")
    onnx.utils.extract_model(src, dst, INPUTS, OUTPUTS, check_model=True)
    out = onnx.load(dst)
    got_in = [i.name for i in out.graph.input]
    if got_in != INPUTS:
        # extract_model keeps the listed inputs; if a version drops the unused one, add it back
        # so the signature stays SamOnnxModel's.
        missing = [i for i in model.graph.input if i.name not in got_in]
        out.graph.input.extend(missing)
        order = {n: k for k, n in enumerate(INPUTS)}
        ins = sorted(out.graph.input, key=lambda i: order[i.name])
        del out.graph.input[:]
        out.graph.input.extend(ins)
    if "--f16-multimask" in argv:
        f16_multimask(out, src)
    onnx.save(out, dst)
    print(f"{dst}: {len(out.graph.node)} nodes (from {len(model.graph.node)}), outputs "
          f"{[(o.name, onnx.TensorProto.DataType.Name(o.type.tensor_type.elem_type)) for o in out.graph.output]}")


if __name__ == "__main__":
    main(sys.argv)
