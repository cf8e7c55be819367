#!/usr/bin/env bash
# Runs on a GPU machine (x86_64, NVIDIA, no Rust toolchain): per-stage bench of `encode` on
# snowmiku (every 2nd image) with wgpu on Vulkan (NVIDIA driver) and ONNX Runtime on the CPU cores,
# then colour mIoU. Expects .devcarry/ (release slag-encoder, scene/ with a geometry+DC .ply,
# shared/fixtures/) and .gl/ (Vulkan loader debs). Results go to $OUT (reports, eval JSON, log).
set -uo pipefail
# shellcheck source=scripts/lab/device-snowmiku-env.sh
. scripts/lab/device-snowmiku-env.sh
one() { # name, args...
  local name=$1; shift
  echo "### $name: $*"
  "$B" bench --scene-dir $S "$@" --dense --quiet --out $W/$name 2>&1 | grep -v XDG_RUNTIME
  cp $W/$name/report.json "$R/report-$name.json"
  "$B" eval-colors --scene-dir $S --embeddings $W/$name/embeddings.safetensors > "$R/eval-$name.json" 2>/dev/null
  python3 -c "import json,sys; e=json.load(open('$R/eval-$name.json')); print('$name mIoU', round(e['miou'],4), 'acc', round(e['accuracy'],4), 'observed', round(e['observed_fraction'],4), {c['name']: round(c['iou'],3) for c in e['classes'] if c['in_miou']})"
}
one sam-every2-s0.5 "${SAM[@]}" "${CLIP[@]}" --every 2 --raster-scale 0.5
one graph-every2-s0.5 --masks graph "${CLIP[@]}" --every 2 --raster-scale 0.5
one graph-every2-s1.0 --masks graph "${CLIP[@]}" --every 2 --raster-scale 1.0
echo "### real-architecture SAM (sam-tiny-random, 16x16, no filters) + tiny-clip, every 16th image"
"$B" bench --scene-dir $S --masks sam --sam-encoder $F/sam-amg/sam-tiny-random-encoder.onnx \
  --sam-decoder $F/sam-amg/sam-tiny-random-decoder.onnx --sam-points-per-side 16 \
  --sam-pred-iou-thresh 0 --sam-stability-score-thresh 0 --clip-visual $F/clip/tiny-clip-visual.onnx \
  --every 16 --raster-scale 0.5 --quiet --out $W/real-arch 2>&1 | grep -v XDG_RUNTIME
cp $W/real-arch/report.json "$R/report-real-arch.json"
exit 0
