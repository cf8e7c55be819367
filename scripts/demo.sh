#!/usr/bin/env bash
# The main job on the embedded default scene (data/snowmiku-mini): set up, build, encode with
# color-sam masks + color-clip (stand-ins with SAM/CLIP's ONNX signatures from ../shared), then
# query "red" and write a highlighted .ply.  Outputs go to out/demo/.
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
$BIN query --embeddings "$OUT/embeddings.safetensors" \
  --clip-textual "$F/clip/color-clip-textual.onnx" --tokenizer "$F/clip/clip-tokenizer.json" \
  --text "${TEXT:-red}" --top-k 5 --ply "$SCENE/point_cloud.ply" --highlight-out "$OUT/highlighted.ply"
echo "demo: wrote $OUT/embeddings.safetensors, $OUT/report.json, $OUT/highlighted.ply" >&2
