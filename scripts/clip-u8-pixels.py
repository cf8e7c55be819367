#!/usr/bin/env python3
"""Give a CLIP image tower byte pixels: IN -> OUT.

slag's CLIP crops are bytes: each crop is resized (PIL bicubic) and centre-cropped to 224 x 224
as RGB bytes, and only then scaled (`/255`) and normalised with CLIP's mean and std. A tower
exported with `pixel_values f32[B,3,224,224]` makes slag do that scaling on the host and copy four
bytes per value to the GPU: 38.5 MB per batch of 64 crops, which took about as long as the fused
fp16 tower's own run on an H100. This script puts the scaling into the graph instead: OUT takes
`pixels u8[B,3,224,224]` (RGB, channel-major, 0..255) and computes
`pixel_values = (pixels / 255 - mean) / std` in f32, the same operations slag does, before the
original graph. The embeddings are the same; each batch copies a quarter of the bytes.

Every output, weight and metadata entry of IN is kept (the CLIP pair id among them: the text
tower still pairs; an IN without one gets the id slag gives it, its file stem without
`-visual`), and `slag.pixels = u8` is added. Works on any export of
`scripts/export-models.py clip` (f32 or fp16, fused or not), under 2 GB;
`export-models.py clip --u8-pixels` applies it to its own export.

usage: python3 scripts/clip-u8-pixels.py IN-visual.onnx OUT-visual.onnx
needs: pip install onnx
"""
import sys

# open_clip's OPENAI_DATASET_MEAN / OPENAI_DATASET_STD (slag's CLIP_MEAN / CLIP_STD).
MEAN = [0.48145466, 0.4578275, 0.40821073]
STD = [0.26862954, 0.26130258, 0.27577711]


def u8_pixels(model, pair_id=None):
    """Rewrites `model` in place: input `pixel_values` f32[B,3,224,224] becomes `pixels`
    u8[B,3,224,224] followed by the scaling and normalisation; exits on any other input.
    `pair_id`: the CLIP pair id to record when the model carries none (slag then takes the
    file stem, which a new name would change)."""
    import numpy as np
    from onnx import TensorProto, helper, numpy_helper

    g = model.graph
    if len(g.input) != 1 or g.input[0].name != "pixel_values":
        sys.exit(f"expected one input pixel_values f32[B,3,224,224], found "
                 f"{[i.name for i in g.input]}: pass a CLIP image tower of "
                 "scripts/export-models.py clip")
    old = g.input[0]
    if old.type.tensor_type.elem_type != TensorProto.FLOAT:
        sys.exit("pixel_values is not f32: this tower already takes other pixels")
    dims = old.type.tensor_type.shape.dim
    batch = dims[0].dim_param or (dims[0].dim_value if dims[0].dim_value > 0 else "batch")
    new = helper.make_tensor_value_info("pixels", TensorProto.UINT8, [batch, 3, 224, 224])
    consts = {
        "pixels_255": np.array(255.0, dtype=np.float32),
        "pixels_mean": np.array(MEAN, dtype=np.float32).reshape(1, 3, 1, 1),
        "pixels_std": np.array(STD, dtype=np.float32).reshape(1, 3, 1, 1),
    }
    g.initializer.extend(numpy_helper.from_array(v, name=k) for k, v in consts.items())
    prelude = [
        helper.make_node("Cast", ["pixels"], ["pixels_f32"], to=TensorProto.FLOAT,
                         name="pixels_cast"),
        helper.make_node("Div", ["pixels_f32", "pixels_255"], ["pixels_unit"], name="pixels_div255"),
        helper.make_node("Sub", ["pixels_unit", "pixels_mean"], ["pixels_centred"],
                         name="pixels_sub_mean"),
        helper.make_node("Div", ["pixels_centred", "pixels_std"], ["pixel_values"],
                         name="pixels_div_std"),
    ]
    nodes = list(g.node)
    del g.node[:]
    g.node.extend(prelude + nodes)
    g.input.remove(old)
    g.input.append(new)
    props = {p.key: p.value for p in model.metadata_props}
    if pair_id and not props.get("slag.clip_pair_id", "").strip():
        props["slag.clip_pair_id"] = pair_id
    helper.set_model_props(model, {**props, "slag.pixels": "u8"})


def main(argv):
    if len(argv) != 3 or argv[1].startswith("-"):
        sys.exit(__doc__)
    import onnx

    from pathlib import Path

    model = onnx.load(argv[1])
    stem = Path(argv[1]).stem
    u8_pixels(model, stem[:-len("-visual")] if stem.endswith("-visual") else stem)
    onnx.checker.check_model(model)
    onnx.save(model, argv[2])
    print(f"{argv[2]}: input pixels u8[B,3,224,224], outputs "
          f"{[o.name for o in model.graph.output]}")


if __name__ == "__main__":
    main(sys.argv)
