#!/usr/bin/env bash
# The main job on the embedded default scene (data/snowmiku-mini): set up, build, encode with
# color-sam masks + color-clip (stand-ins with SAM/CLIP's ONNX signatures from ../shared), then
# query "red" and "pink" (TEXT="..." to change) and write highlighted .ply copies.  Outputs go to out/demo/.
# Ends with a short summary: matches per prompt, the objects found in them (how many; the first
# ones' sizes and centres), and where the highlighted .ply files are and how to look at them.
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/setup.sh
F=$SLAG_SHARED/fixtures
SCENE=${SCENE:-data/snowmiku-mini}
OUT=${OUT:-out/demo}
cargo build --release --locked -p slag-encoder-cli
BIN=target/release/slag-encoder
$BIN encode --scene-dir "$SCENE" --masks sam \
  --sam-encoder "$F/sam-amg/color-sam-encoder.onnx" --sam-decoder "$F/sam-amg/color-sam-decoder.onnx" \
  --sam-points-per-side 16 --sam-pred-iou-thresh 0.8 --sam-stability-score-thresh 0.5 \
  --clip-visual "$F/clip/color-clip-visual.onnx" --out "$OUT"
PROMPTS=()
for text in ${TEXT:-red pink}; do
  PROMPTS+=("$text")
  # The JSON answer is printed as before and kept in $OUT/query-<prompt>.json for the summary.
  $BIN query --embeddings "$OUT/mixture.safetensors" \
    --clip-textual "$F/clip/color-clip-textual.onnx" --tokenizer "$F/clip/clip-tokenizer.json" \
    --text "$text" --top-k 5 --ply "$SCENE/point_cloud.ply" --highlight-out "$OUT/highlighted-$text.ply" \
    | tee "$OUT/query-$text.json"
done
echo "demo: wrote $OUT/mixture.safetensors, $OUT/segments.safetensors, $OUT/report.json, $OUT/highlighted-*.ply" >&2

# ---- summary ------------------------------------------------------------------------------------
summary_line() { # prompt json-file
  if command -v python3 >/dev/null 2>&1; then
    python3 - "$1" "$2" <<'PY'
import json, sys
text, path = sys.argv[1], sys.argv[2]
a = json.load(open(path))
n = a["summary"]["count"]
line = f'  "{text}": {n:,} matching Gaussians (cosine >= {a["threshold"]:g})'
if n == 0 and a.get("nearest_below_threshold"):
    line += f'; best cosine {a["nearest_below_threshold"][0]["score"]:.3f}, below the threshold'
elif n:
    c = a["summary"]["centroid"]
    line += f', centred at ({c[0]:.2f}, {c[1]:.2f}, {c[2]:.2f})'
line += f' -> {a["highlighted_ply"]}'
print(line)
# The matches grouped into objects (docs/guide/objects.md): how many, then the first ones, each
# with its Gaussians, the full lengths of its oriented box (largest first) and its centroid.
objs = a.get("objects", [])
if n:
    shown = objs[:3]
    head = f'    {len(objs)} object{"" if len(objs) == 1 else "s"}'
    if len(objs) >= 20:  # the query's default --max-objects: there may be more groups
        head += ", the most one answer returns"
    if len(objs) > len(shown):
        head += f"; the first {len(shown)}"
    print(head + ":" if objs else "    no object (every group of matches is below the minimum size)")
    for k, o in enumerate(shown, 1):
        e, c = o["obb"]["extents"], o["centroid"]
        print(f'      #{k}: {o["gaussians"]:,} Gaussians, {e[0]:.2f} x {e[1]:.2f} x {e[2]:.2f}'
              f' at ({c[0]:.2f}, {c[1]:.2f}, {c[2]:.2f})')
PY
  else # no python3: the count is the first "count" field of the pretty JSON
    n=$(grep -m1 '"count"' "$2" | tr -dc '0-9')
    echo "  \"$1\": $n matching Gaussians in $(grep -c '"score_mass"' "$2") objects -> $OUT/highlighted-$1.ply"
  fi
}
{
  echo
  echo "==== demo summary: $SCENE, $(grep -o '"views_used": *[0-9]*' "$OUT/report.json" | tr -dc '0-9') views ===="
  for text in "${PROMPTS[@]}"; do summary_line "$text" "$OUT/query-$text.json"; done
  echo "  Object sizes are the full lengths of each object's oriented box (largest first), centres"
  echo "  its centroid, both in scene units (docs/guide/objects.md)."
  echo "  Matches are painted magenta in each highlighted .ply (a full 3DGS copy of the scene)."
  echo "  View one: drag it into https://playcanvas.com/supersplat/editor (or any 3DGS viewer);"
  echo "  on a robot, the same answer renders at / of \`slag-edge serve\` (docs/guide/robot.md, 'Showing the answer')."
} >&2
