#!/usr/bin/env bash
# Prediction filtering on the 2D held-out protocol: encode a scene with graph masks and with
# color-sam (16×16, pred-IoU 0.8, stability 0.5), both with color-clip at --every 4, raster 0.5
# (the encode also writes segments.safetensors), then `eval-colors --held-out
# --prediction-filtering`, which scores slag with and without PF on the same pixels.
# Usage: scripts/lab/heldout-pf.sh BINARY SCENE OUTDIR   (needs $SLAG_SHARED and ONNX Runtime)
set -uo pipefail
B=$1; S=$2; R=$3; W=${WORK:-/tmp/slag-pf}
F=$SLAG_SHARED/fixtures
mkdir -p "$R" "$W"
SAM=(--masks sam --sam-encoder $F/sam-amg/color-sam-encoder.onnx --sam-decoder $F/sam-amg/color-sam-decoder.onnx
     --sam-points-per-side 16 --sam-pred-iou-thresh 0.8 --sam-stability-score-thresh 0.5)
CLIP=(--clip-visual $F/clip/color-clip-visual.onnx)
for name in graph color-sam; do
  if [ $name = graph ]; then M=(--masks graph); else M=("${SAM[@]}"); fi
  t0=$(date +%s)
  "$B" encode --scene-dir "$S" "${M[@]}" "${CLIP[@]}" --every 4 --raster-scale 0.5 --dense --quiet \
    --out "$W/$name" > "$W/$name.log" 2>&1 || { tail -n 5 "$W/$name.log"; exit 1; }
  t1=$(date +%s)
  "$B" eval-colors --held-out --prediction-filtering --scene-dir "$S" \
    --embeddings "$W/$name/embeddings.safetensors" --color-clip $F/clip \
    > "$R/heldout-$name.json" 2> "$R/heldout-$name.err" || { tail -n 5 "$R/heldout-$name.err"; exit 1; }
  t2=$(date +%s)
  echo "$name: encode $((t1 - t0)) s, eval-colors --held-out --prediction-filtering $((t2 - t1)) s"
  python3 - "$R/heldout-$name.json" <<'PY'
import json, sys
o = json.load(open(sys.argv[1])); e = o["held_out"]
def line(n, s): return f"  {n:<14} mIoU {s['miou']:.4f}  acc {s['pixel_accuracy']:.4f}  " + ' '.join(f"{c['name']}={c['iou']:.3f}" for c in s['classes'] if c['in_miou'])
for k in ("slag", "majority", "oracle"): print(line(k, e[k]))
for v in e["variants"]: print(line(v["name"], v["score"]))
print(f"  3D mIoU {o['colour_3d']['miou']:.4f}  with PF {o['colour_3d_pf']['miou']:.4f}")
PY
done
