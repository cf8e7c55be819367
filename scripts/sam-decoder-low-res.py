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

usage: python3 scripts/sam-decoder-low-res.py sam-vit_h-decoder.onnx sam-vit_h-decoder-low-res.onnx
needs: pip install onnx
"""
import sys

INPUTS = ["image_embeddings", "point_coords", "point_labels", "mask_input", "has_mask_input",
          "orig_im_size"]
OUTPUTS = ["iou_predictions", "low_res_masks"]


def main(argv):
    if len(argv) != 3:
        sys.exit(__doc__)
    import onnx
    import onnx.utils
    src, dst = argv[1], argv[2]
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
        onnx.save(out, dst)
    print(f"{dst}: {len(out.graph.node)} nodes (from {len(model.graph.node)}), outputs {OUTPUTS}")


if __name__ == "__main__":
    main(sys.argv)
