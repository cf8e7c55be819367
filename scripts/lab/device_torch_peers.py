"""torch on the GPU as the peer of each model stage of slag-encoder: SAM ViT-B / ViT-H
image encoder (one 1024x1024 image), SAM's prompt decoder (256 prompts = a 16x16 grid, the
multimask output, low-resolution masks only, as slag asks for), CLIP ViT-B/16 image tower (54, 64 and
256 crops). fp16 and fp32, random weights, CUDA events, median of 20 after 5 warm-ups. Runs on
a GPU machine (torch, timm; segment_anything carried as a wheel); NOT part of CI.

    python3 scripts/lab/device_torch_peers.py OUT.json

SAM_KINDS (default "vit_b vit_h") picks the SAM models; TORCH_PROFILE=1 also prints torch's
per-operator CUDA time of the fp16 encoder and decoder.
"""

import copy
import json
import os
import sys

import timm
import torch
from segment_anything import sam_model_registry


def ms(fn, reps=20, warm=5):
    for _ in range(warm):
        fn()
    torch.cuda.synchronize()
    times = []
    for _ in range(reps):
        s, e = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        s.record()
        fn()
        e.record()
        torch.cuda.synchronize()
        times.append(s.elapsed_time(e))
    times.sort()
    return times[len(times) // 2]


out = {"gpu": torch.cuda.get_device_name(0), "torch": torch.__version__}
torch.manual_seed(0)
with torch.inference_mode():
    for kind in os.environ.get("SAM_KINDS", "vit_b vit_h").split():
        sam = sam_model_registry[kind](checkpoint=None).eval().cuda()
        for name in ["fp16", "fp32"]:
            # fp16: the encoder's weights in half precision; the decoder under autocast (its
            # prompt encoder casts the points to float itself).
            enc = copy.deepcopy(sam.image_encoder).half() if name == "fp16" else sam.image_encoder
            x = torch.randn(1, 3, 1024, 1024, device="cuda", dtype=torch.float16 if name == "fp16" else torch.float32)
            out[f"sam_{kind}_encoder_{name}_ms"] = ms(lambda: enc(x))
            emb = enc(x).float()
            pts = torch.rand(256, 1, 2, device="cuda") * 1024
            lbl = torch.ones(256, 1, device="cuda")

            def dec():
                with torch.autocast("cuda", dtype=torch.float16, enabled=name == "fp16"):
                    sp, de = sam.prompt_encoder(points=(pts, lbl), boxes=None, masks=None)
                    return sam.mask_decoder(image_embeddings=emb, image_pe=sam.prompt_encoder.get_dense_pe(),
                                            sparse_prompt_embeddings=sp, dense_prompt_embeddings=de,
                                            multimask_output=True)

            out[f"sam_{kind}_decoder_256_{name}_ms"] = ms(dec)
            print(kind, name, out[f"sam_{kind}_encoder_{name}_ms"], out[f"sam_{kind}_decoder_256_{name}_ms"], flush=True)
            if os.environ.get("TORCH_PROFILE") == "1" and name == "fp16":
                # Where the GPU's time goes, by operator (CUDA time of 5 calls each).
                from torch.profiler import ProfilerActivity, profile
                for what, fn in [("encoder", lambda: enc(x)), ("decoder_256", dec)]:
                    with profile(activities=[ProfilerActivity.CUDA]) as prof:
                        for _ in range(5):
                            fn()
                        torch.cuda.synchronize()
                    print(f"### torch profile: SAM {kind} {what} fp16, 5 calls")
                    print(prof.key_averages().table(sort_by="cuda_time_total", row_limit=18, max_name_column_width=60))
            del enc
        del sam
        torch.cuda.empty_cache()
    clip = timm.create_model("vit_base_patch16_clip_224", pretrained=False, num_classes=512).eval().cuda()
    for dt, name in [(torch.float16, "fp16"), (torch.float32, "fp32")]:
        m = clip.to(dt)
        for b in [54, 64, 256]:
            x = torch.randn(b, 3, 224, 224, device="cuda", dtype=dt)
            out[f"clip_vitb16_{b}_{name}_ms"] = ms(lambda: m(x))
            print("clip", b, name, out[f"clip_vitb16_{b}_{name}_ms"], flush=True)
json.dump(out, open(sys.argv[1], "w"), indent=1)
print(json.dumps(out, indent=1))
