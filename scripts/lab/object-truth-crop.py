"""Does the white fill of a CLIP crop pull an object's colour towards white? For one object of the
labelled-object room, project its Gaussians' means into every view (a 3 × 3 pixel patch each: an
approximate mask, without occlusion), cut the crop of its whole surface, of its top and of its
sides, and run color-clip's visual tower on two crops of each: masked at the image's resolution
and then resized (bicubic, shortest side 224, centre crop: what the encoder does), and masked
after the resize (the mask resized the same way, white where it falls below one half). Needs
numpy, pillow and onnxruntime (pip) and SLAG_SHARED; not part of CI.

    python3 scripts/lab/object-truth-crop.py OUT/default-s1 OBJECT_INDEX

OBJECT_INDEX indexes the scene's objects.json (8: the pink box of `synth-scene --objects 10
--room`). Prints per view and part: pixels, mean colour, class masked before / after the resize.
"""

import json
import os
import sys

import numpy as np
import onnxruntime as ort
from PIL import Image

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
why = __import__("object-truth-why")

MEAN = np.array([0.48145466, 0.4578275, 0.40821073])
STD = np.array([0.26862954, 0.26130258, 0.27577711])


def quat(w, x, y, z):
    n = np.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def prep(img):
    w, h = img.size
    s = 224 / min(w, h)
    nw, nh = max(224, round(w * s)), max(224, round(h * s))
    r = img.resize((nw, nh), Image.BICUBIC)
    left, top = (nw - 224) // 2, (nh - 224) // 2
    return r.crop((left, top, left + 224, top + 224))


def main(d, k, clip_dir):
    classes = json.load(open(f"{d}/scene/truth.json"))["classes"]
    objects = json.load(open(f"{d}/scene/objects.json"))
    o = objects[k]
    a, b = o["gaussians"]
    g = why.ply(f"{d}/scene/point_cloud.ply")
    pts = np.stack([g["x"], g["y"], g["z"]], 1)[a:b]
    top = pts[:, 2] > o["aabb"][1][2] - 1e-3
    text = why.text_directions(clip_dir, classes)
    visual = ort.InferenceSession(os.path.join(clip_dir, "color-clip-visual.onnx"))

    def classify(img):
        x = ((np.asarray(img, np.float32) / 255.0 - MEAN) / STD).transpose(2, 0, 1)[None]
        e = visual.run(None, {"pixel_values": x.astype(np.float32)})[0][0]
        return classes[int((text @ (e / np.linalg.norm(e))).argmax())]

    cam = [line.split() for line in open(f"{d}/scene/sparse/0/cameras.txt") if line[0] != "#"][0]
    width, height = int(cam[2]), int(cam[3])
    fx, fy, cx, cy = map(float, cam[4:8])
    print(f"{o['name']} {o['shape']}: part pixels mean-colour masked-before / masked-after")
    for line in open(f"{d}/scene/sparse/0/images.txt"):
        f = line.split()
        if not f or f[0] == "#" or len(f) < 10:
            continue
        r, t = quat(*map(float, f[1:5])), np.array(list(map(float, f[5:8])))
        pc = pts @ r.T + t
        ahead = pc[:, 2] > 0
        uv = np.stack([fx * pc[:, 0] / pc[:, 2] + cx, fy * pc[:, 1] / pc[:, 2] + cy], 1)
        image = np.asarray(Image.open(f"{d}/scene/images/{f[9]}").convert("RGB"))
        out = []
        for part, sel in [("whole", ahead), ("top", ahead & top), ("sides", ahead & ~top)]:
            mask = np.zeros((height, width), bool)
            for u, v in uv[sel]:
                ui, vi = int(round(u)), int(round(v))
                if -1 <= ui <= width and -1 <= vi <= height:
                    mask[max(0, vi - 1):vi + 2, max(0, ui - 1):ui + 2] = True
            if mask.sum() < 4:
                continue
            ys, xs = np.where(mask)
            crop = image[ys.min():ys.max() + 1, xs.min():xs.max() + 1].copy()
            m = mask[ys.min():ys.max() + 1, xs.min():xs.max() + 1]
            before = crop.copy()
            before[~m] = 255
            resized_mask = np.asarray(prep(Image.fromarray((m * 255).astype(np.uint8)).convert("RGB")))[:, :, 0] > 127
            after = np.asarray(prep(Image.fromarray(crop))).copy()
            after[~resized_mask] = 255
            mean = np.round(crop[m].mean(0) / 255, 2)
            out.append(f"{part} {m.sum()} px {mean} {classify(prep(Image.fromarray(before)))} / "
                       f"{classify(Image.fromarray(after))}")
        print(f[9], " | ".join(out))


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    shared = os.environ.get("SLAG_SHARED") or sys.exit("set SLAG_SHARED")
    main(sys.argv[1].rstrip("/"), int(sys.argv[2]), os.path.join(shared, "fixtures", "clip"))
