#!/usr/bin/env bash
# Prediction filtering (PF) on object truth: per seed and texture level, write the labelled-object
# room (`synth-scene --objects 10 --room`), encode it with color-sam (16×16, pred-IoU 0.8,
# stability 0.5) and color-clip, every 4th view held out (`--hold-out-every 4`; the encode writes
# the mask-term segments and the masks' record), make the geometric segments
# (`segment --geometry-only`), and score every predictor and PF variant on both segmentations
# against the object truth in one pass (`eval-objects --held-out`: per-pixel and per-Gaussian
# mIoU), with the object AP50 and box IoU of each class's query at the default object gap (its
# scores smoothed also over the geometric segments: OUTDIR/<level>-s<seed>/objects-geometric.json).
# Writes OUTDIR/table.md and keeps every JSON under OUTDIR/<level>-s<seed>/.
#
# Usage: scripts/lab/object-truth-pf.sh BINARY OUTDIR [SEED ...]          (default SEED: 1 2)
# Texture levels: default (the flags' defaults) and heavy (speckles 0.2, stripes 0.3, shading 0.5).
# Scene size: GAUSSIANS (30000), VIEWS (16), WIDTH×HEIGHT (320×240), room side EXTENT (6).
# EXTRA_ENCODE: more encode flags, split on spaces (e.g. EXTRA_ENCODE="--mask-erode 2").
# LEVELS: the texture levels to run, split on spaces (default "default heavy").
set -euo pipefail
[ $# -ge 2 ] || { sed -n '2,15p' "$0"; exit 2; }
B=$(realpath "$1"); R=$2; shift 2
SEEDS=("$@"); [ ${#SEEDS[@]} -gt 0 ] || SEEDS=(1 2)
: "${SLAG_SHARED:?set SLAG_SHARED to the shared folder (fixtures/sam-amg, fixtures/clip)}"
F=$SLAG_SHARED/fixtures
G=${GAUSSIANS:-30000}; V=${VIEWS:-16}; W=${WIDTH:-320}; H=${HEIGHT:-240}; X=${EXTENT:-6}
read -r -a EXTRA <<< "${EXTRA_ENCODE:-}"
read -r -a LEVEL_LIST <<< "${LEVELS:-default heavy}"
mkdir -p "$R"
echo "# PF on object truth ($(date -u +%F), $(hostname), $("$B" --version 2>/dev/null || echo slag-encoder)${EXTRA_ENCODE:+, encode $EXTRA_ENCODE})" > "$R/table.md"
for seed in "${SEEDS[@]}"; do
  for level in "${LEVEL_LIST[@]}"; do
    tex=(); [ "$level" = heavy ] && tex=(--speckles 0.2 --stripes 0.3 --shading 0.5)
    D=$R/$level-s$seed; S=$D/scene; E=$D/enc; mkdir -p "$D"
    t0=$(date +%s)
    "$B" synth-scene --gaussians "$G" --view-count "$V" --width "$W" --height "$H" --extent "$X" \
      --seed "$seed" --objects 10 --room "${tex[@]}" --out "$S" > "$D/scene.json"
    "$B" encode --scene-dir "$S" --masks sam --sam-encoder "$F/sam-amg/color-sam-encoder.onnx" \
      --sam-decoder "$F/sam-amg/color-sam-decoder.onnx" --sam-points-per-side 16 \
      --sam-pred-iou-thresh 0.8 --sam-stability-score-thresh 0.5 \
      --clip-visual "$F/clip/color-clip-visual.onnx" --hold-out-every 4 --dense --quiet \
      ${EXTRA[@]+"${EXTRA[@]}"} --out "$E" > "$D/encode.log" 2>&1
    "$B" segment --scene-dir "$S" --geometry-only --out "$D/geometric.safetensors" \
      > "$D/geometric.json" 2> "$D/geometric.log"
    "$B" eval-objects --scene-dir "$S" --embeddings "$E/embeddings.safetensors" \
      --color-clip "$F/clip" --smooth none --smooth segment --held-out \
      --more-segments "$D/geometric.safetensors" > "$D/eval.json" 2> "$D/eval.log"
    "$B" eval-objects --scene-dir "$S" --embeddings "$E/embeddings.safetensors" \
      --color-clip "$F/clip" --smooth segment --segments "$D/geometric.safetensors" \
      > "$D/objects-geometric.json" 2> "$D/objects-geometric.log"
    echo "$level seed $seed: $(( $(date +%s) - t0 )) s"
  done
done
LEVELS="${LEVEL_LIST[*]}" python3 - "$R" "${SEEDS[@]}" >> "$R/table.md" <<'PY'
import json, os, sys
r, seeds = sys.argv[1], sys.argv[2:]
names = ["slag", "mixture-mean-S4", "argmax"]
pf = ["pf-majority", "pf-strict", "pf-mean", "pf-weighted", "pf-confident",
      "mixture-mean-S4+pf-weighted", "mixture-mean-S4+pf-confident", "mixture-mean-S4+pf-strict"]
for level in os.environ["LEVELS"].split():
    for seed in seeds:
        e = json.load(open(f"{r}/{level}-s{seed}/eval.json"))
        t = e["object_truth"]
        p = {x["name"]: x for x in t["predictors"]}
        geo = [k for k in p if k.startswith("pf-majority@")]
        tag = geo[0][len("pf-majority"):] if geo else ""
        print(f"\n## texture {level}, seed {seed}: {len(t['held_out_views'])} views held out, "
              f"{t['counted_pixels']} pixels, {t['observed_gaussians']} Gaussians observed\n")
        print("| predictor | pixel mIoU (mask term) | 3D mIoU (mask term) | pixel mIoU (geometry only) | 3D mIoU (geometry only) |")
        print("|---|---:|---:|---:|---:|")
        f = lambda k, w: (f"{p[k][w]['miou']:.4f}" if k in p and p[k].get(w) else "–")
        for k in names + pf:
            g = k + tag if k in pf else k
            print(f"| `{k}` | {f(k,'pixel')} | {f(k,'gaussian')} | {f(g,'pixel') if k in pf else '–'} | {f(g,'gaussian') if k in pf else '–'} |")
        for s in t["segments"]:
            print(f"\nsegments {s['source'].split('/')[-1]}: {s['segments']} segments, class purity "
                  f"{s['class_purity']['purity']:.4f}, object purity {s['object_purity']['purity']:.4f}; "
                  f"over the objects' Gaussians: class {s['objects_class_purity']['purity']:.4f}, "
                  f"object {s['objects_object_purity']['purity']:.4f}")
        geo_runs = json.load(open(f"{r}/{level}-s{seed}/objects-geometric.json"))["runs"]
        for run, on in [(x, "") for x in e["runs"]] + [(x, " (geometric segments)") for x in geo_runs]:
            sc = run["score"]
            print(f"\nobjects, smooth {run['smooth']}{on}: AP50 {sc['ap50']:.4f}, box AP50 "
                  f"{sc['box_ap50']:.4f}, mean box IoU {sc['mean_box_iou']:.4f}")
PY
cat "$R/table.md"
