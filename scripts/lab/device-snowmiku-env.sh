# Sourced by the device scripts that run the release slag-encoder on snowmiku (device-bench.sh,
# device-heldout.sh) on a GPU machine (x86_64, NVIDIA, no Rust toolchain): the Vulkan loader from
# .gl/, the NVIDIA Vulkan driver, ONNX Runtime from the machine's Python package, and the names
# they share: B (the binary), S (the scene), F (the fixtures), R (results: $OUT), W (work), SAM
# (color-sam 16x16 at 0.8 / 0.5) and CLIP (color-clip) arguments. Expects .devcarry/ (release
# slag-encoder, scene/ = snowmiku images + COLMAP + a geometry+DC .ply, shared/fixtures/).
for f in .gl/*.deb; do dpkg -x "$f" / >/dev/null 2>&1; done; ldconfig
VK_DRIVER_FILES=$(bash scripts/vulkan-icd.sh) && [ -n "$VK_DRIVER_FILES" ] && export VK_DRIVER_FILES  # the NVIDIA ICD that works headless
ORT_LIB=$(python3 -c 'import onnxruntime, os, glob; print(sorted(glob.glob(os.path.join(os.path.dirname(onnxruntime.__file__), "capi", "libonnxruntime.so*")))[0])')
export ORT_DYLIB_PATH=$ORT_LIB SLAG_SHARED=$PWD/.devcarry/shared
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
echo "ORT: $ORT_LIB  cores: $(nproc)  date: $(date -u +%FT%TZ)"
B=.devcarry/slag-encoder; S=.devcarry/scene; F=.devcarry/shared/fixtures
R=${OUT:-/tmp/out}; W=/tmp/slag-work; mkdir -p "$R" "$W"
SAM=(--masks sam --sam-encoder $F/sam-amg/color-sam-encoder.onnx --sam-decoder $F/sam-amg/color-sam-decoder.onnx
     --sam-points-per-side 16 --sam-pred-iou-thresh 0.8 --sam-stability-score-thresh 0.5)
CLIP=(--clip-visual $F/clip/color-clip-visual.onnx)
