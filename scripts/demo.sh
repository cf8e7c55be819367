#!/usr/bin/env bash
# The main job on the embedded default scene (data/snowmiku-mini): set up, build, encode with
# color-sam masks + color-clip (stand-ins with SAM/CLIP's ONNX signatures from ../shared), then
# query "red" and "pink" (TEXT="..." to change) and write highlighted .ply copies.  Outputs go to out/demo/.
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/setup.sh
F=$SLAG_SHARED/fixtures
SCENE=${SCENE:-data/snowmiku-mini}
OUT=${OUT:-out/demo}
cargo build --release --locked -p slag-encoder
BIN=target/release/slag-encoder
$BIN encode --scene "$SCENE" --masks sam \
  --sam-encoder "$F/sam-amg/color-sam-encoder.onnx" --sam-decoder "$F/sam-amg/color-sam-decoder.onnx" \
  --sam-points-per-side 16 --sam-pred-iou-thresh 0.8 --sam-stability-score-thresh 0.5 \
  --clip-visual "$F/clip/color-clip-visual.onnx" --out "$OUT"
for text in ${TEXT:-red pink}; do
  $BIN query --embeddings "$OUT/embeddings.safetensors" \
    --clip-textual "$F/clip/color-clip-textual.onnx" --tokenizer "$F/clip/clip-tokenizer.json" \
    --text "$text" --top-k 5 --ply "$SCENE/point_cloud.ply" --highlight-out "$OUT/highlighted-$text.ply"
done
echo "demo: wrote $OUT/embeddings.safetensors, $OUT/report.json, $OUT/highlighted-*.ply" >&2
