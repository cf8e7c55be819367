#!/usr/bin/env bash
# Runs on the lent GPU machine (x86_64, NVIDIA, no Rust toolchain): the per-stage bench of encode on
# snowmiku with wgpu on Vulkan (the NVIDIA driver) and ONNX Runtime on the CPU cores.
# Expects .devcarry/ (made by scripts/make-devcarry.sh): slag-encoder, scene/, fixtures/.
set -uo pipefail
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig
if [ -f /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json ]; then
  export VK_DRIVER_FILES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
fi
ORT_LIB=$(python3 -c 'import onnxruntime, os, glob; print(sorted(glob.glob(os.path.join(os.path.dirname(onnxruntime.__file__), "capi", "libonnxruntime.so*")))[0])')
export ORT_DYLIB_PATH=$ORT_LIB SLAG_SHARED=$PWD/.devcarry/shared
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
echo "ORT: $ORT_LIB  cores: $(nproc)"
B=.devcarry/slag-encoder; S=.devcarry/scene; F=.devcarry/shared/fixtures
OUT=${OUT:-/tmp/slag-out}
run() { echo "### $*"; "$B" "$@" 2>&1 | grep -v '^\s*$' ; }
SAM=(--masks sam --sam-encoder $F/sam-amg/color-sam-encoder.onnx --sam-decoder $F/sam-amg/color-sam-decoder.onnx
     --sam-points-per-side 16 --sam-pred-iou-thresh 0.8 --sam-stability-score-thresh 0.5)
CLIP=(--clip-visual $F/clip/color-clip-visual.onnx)
for scale in 1.0 0.5; do
  run bench --scene $S "${SAM[@]}" "${CLIP[@]}" --every 2 --raster-scale $scale --quiet --out $OUT/sam-$scale
  cp $OUT/sam-$scale/report.json "$OUT_DIR/report-sam-$scale.json" 2>/dev/null
done
run bench --scene $S --masks graph "${CLIP[@]}" --every 2 --raster-scale 0.5 --quiet --out $OUT/graph
[ -n "${OUT_DIR:-}" ] && cp $OUT/graph/report.json "$OUT_DIR/report-graph.json"
exit 0
