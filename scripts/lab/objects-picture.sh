#!/usr/bin/env bash
# The picture of the objects that `slag-encoder query` returns on a real scene, for two prompts,
# with geometric segments: encode the scene (graph masks, the color-clip stand-in, every second
# view, raster scale 0.5; the encode writes segments.safetensors), query each prompt with
# `--smooth segment` (each Gaussian scored with its segment's mean cosine; objects are the matches
# within the gap of each other), then draw the objects' oriented boxes over the scene (scripts/lab/plot_objects.py).
#
# Usage: scripts/lab/objects-picture.sh BINARY SCENE OUT.png [PROMPT ...]   (default prompts: pink brown)
# MASKS=sam encodes instead with color-sam 16x16 (pred-IoU 0.8, stability 0.5) at every 4th view,
# the encode of docs/results/prediction-filtering.md, whose segments carry the mask term of SAM masks.
# Needs $SLAG_SHARED and ONNX Runtime (`. scripts/setup.sh`), numpy and matplotlib.
# WORK (default /tmp/slag-objects-picture) keeps the encode; an existing encode there is reused.
# MAX_OBJECTS (default 10) boxes are drawn per prompt.
set -euo pipefail
B=$1; S=$2; PNG=$3; shift 3
PROMPTS=("$@"); [ ${#PROMPTS[@]} -gt 0 ] || PROMPTS=(pink brown)
W=${WORK:-/tmp/slag-objects-picture}
F=$SLAG_SHARED/fixtures/clip
HERE=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
mkdir -p "$W"
if [ ! -e "$W/enc/segments.safetensors" ]; then
  t0=$(date +%s)
  if [ "${MASKS:-graph}" = sam ]; then
    A=$SLAG_SHARED/fixtures/sam-amg
    MASK_ARGS=(--masks sam --sam-encoder "$A/color-sam-encoder.onnx" --sam-decoder "$A/color-sam-decoder.onnx"
      --sam-points-per-side 16 --sam-pred-iou-thresh 0.8 --sam-stability-score-thresh 0.5 --every 4)
  else
    MASK_ARGS=(--masks graph --every 2)
  fi
  "$B" encode --scene-dir "$S" "${MASK_ARGS[@]}" --clip-visual "$F/color-clip-visual.onnx" \
    --raster-scale 0.5 --quiet --out "$W/enc" > "$W/encode.log" 2>&1 || { tail -n 5 "$W/encode.log"; exit 1; }
  echo "encode: $(( $(date +%s) - t0 )) s"
fi
answers=()
for p in "${PROMPTS[@]}"; do
  "$B" query --embeddings "$W/enc/embeddings.safetensors" --clip-textual "$F/color-clip-textual.onnx" \
    --tokenizer "$F/clip-tokenizer.json" --text "$p" --smooth segment --top-k 1000000 \
    --max-objects "${MAX_OBJECTS:-10}" --ply "$S/point_cloud.ply" --highlight-out "$W/$p.ply" \
    > "$W/$p.json"
  python3 - "$W/$p.json" <<'PY'
import json, sys
a = json.load(open(sys.argv[1]))
print(f"{a['query']}: {a['summary']['count']} matches, {len(a['objects'])} objects shown")
for k, o in enumerate(a["objects"][:5]):
    print(f"  #{k + 1} {o['gaussians']} Gaussians, mass {o['score_mass']:.1f}, mean {o['mean_score']:.3f},"
          f" max {o['max_score']:.3f}, extents {[round(e, 2) for e in o['obb']['extents']]}")
PY
  answers+=("$W/$p.json")
done
python3 "$HERE/plot_objects.py" "$S/point_cloud.ply" "$PNG" "${answers[@]}"
echo "wrote $PNG ($(stat -c %s "$PNG") bytes)"
