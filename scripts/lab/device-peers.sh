#!/usr/bin/env bash
# slag's lifting beside gsplat's, and the encoder's host memory, on the lent GPU machine (x86_64,
# NVIDIA, torch + nvcc, no Rust, no network); NOT part of CI.
#
# Carried (folder $CARRY, default .devcarry): slag-encoder.gz (gzip release build; .zst only
# where the machine has zstd), libonnxruntime.so.gz (ONNX Runtime's CPU library of the build), gsplat-*.whl
# (`pip download gsplat==1.5.3 --no-deps`; torch, jaxtyping, ninja, numpy, rich are on the
# machine), the fixtures color-sam-encoder.onnx, color-sam-decoder.onnx, color-clip-visual.onnx,
# and device_peers.py (scripts/lab/); plus .gl/ (the Vulkan loader debs, README "GPU machine").
#
#   scripts/lab/device-peers.sh peers [N] [V] [EVERY]
#       synth-scene of N Gaussians (2M), V views (250) at 990x742; slag-encoder bench on every
#       EVERY-th view (5) with color-sam 16x16 (0.8 / 0.5) masks + color-clip, raster 0.5, GPU
#       raster; then gsplat on the same scene, views and raster size: forward RGB render, forward
#       + backward of a 1-channel render and of a 64-label render (a_kj of 64 disjoint masks),
#       and the ratios slag / gsplat. gsplat's CUDA compiles (JIT, sm_90) while the scene is made.
#   scripts/lab/device-peers.sh memory [N] [V] [EVERY] [FRONTS...]
#       the same scene and masks, once per front-worker count (default 1 8): peak RSS
#       (/usr/bin/time and report.json), queue high-water marks, masks per image.
# Results (reports, logs, peers.json) go to $OUT, packed into one archive.
set -uo pipefail
CARRY=${CARRY:-.devcarry}
for f in .gl/*.deb; do [ -f "$f" ] && dpkg -x "$f" / >/dev/null 2>&1; done; ldconfig
VK_DRIVER_FILES=$(bash scripts/vulkan-icd.sh) && [ -n "$VK_DRIVER_FILES" ] && export VK_DRIVER_FILES  # the NVIDIA ICD that works headless
export NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1
export XDG_RUNTIME_DIR=/tmp PYTHONUNBUFFERED=1
R=${OUT:-/tmp/out}; W=/root/work; B=/root/bin/slag-encoder; FX=$CARRY
mkdir -p "$R" "$W" /root/bin /root/lib
# The machine has gzip but no zstd: carry NAME.gz (or NAME.zst where a zstd is on the PATH).
unz() { if [ -f "$1.gz" ]; then gzip -dc "$1.gz" > "$2"; else zstd -dqf "$1.zst" -o "$2"; fi; }
[ -f "$B" ] || unz "$CARRY/slag-encoder" "$B"
[ -f /root/lib/libonnxruntime.so ] || unz "$CARRY/libonnxruntime.so" /root/lib/libonnxruntime.so
chmod +x "$B"
export ORT_DYLIB_PATH=/root/lib/libonnxruntime.so
nvidia-smi --query-gpu=index,name,driver_version,memory.total --format=csv,noheader
echo "cores: $(nproc)  memory: $(free -g | awk '/Mem/ {print $2}') GiB"
mode=${1:-peers}; n=${2:-2M}; v=${3:-250}; every=${4:-5}
scene=/root/scene-$n-$v
MASKS=(--masks sam --sam-encoder "$FX/color-sam-encoder.onnx" --sam-decoder "$FX/color-sam-decoder.onnx"
  --sam-points-per-side 16 --sam-pred-iou-thresh 0.8 --sam-stability-score-thresh 0.5
  --clip-visual "$FX/color-clip-visual.onnx" --ep cpu --raster-scale 0.5 --every "$every")

make_scene() {
  [ -f "$scene/sparse/0/images.txt" ] && return 0
  local t0; t0=$(date +%s)
  "$B" synth-scene --gaussians "$n" --view-count "$v" --width 990 --height 742 --out "$scene" > "$R/synth.json" || exit 1
  echo "synth-scene $n Gaussians, $v views: $(( $(date +%s) - t0 )) s"
}

encode() { # name, fronts
  echo "### slag-encoder bench: $n Gaussians, every $every of $v views, color-sam 16x16 (0.8/0.5), $2 fronts"
  /usr/bin/time -v "$B" bench --scene-dir "$scene" "${MASKS[@]}" --front-workers "$2" --quiet \
    --out "$W/$1" > "$R/$1.txt" 2>&1
  echo "exit $?"
  grep -E "^\| (masks|raster|a_kj|total)|^views|peak resident|between the stages|Maximum resident|Elapsed" "$R/$1.txt"
  cp "$W/$1/report.json" "$R/report-$1.json" 2>/dev/null
}

case "$mode" in
peers)
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /root/site "$CARRY"/gsplat-*.whl || exit 1
  export PYTHONPATH=/root/site TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=${MAX_JOBS:-$(nproc)}
  # gsplat compiles its CUDA on first use: start it now, beside the scene generation.
  (t0=$(date +%s); python3 -c "
import torch, gsplat
from gsplat import rasterization
d = 'cuda'
m = torch.zeros(1, 3, device=d); m[0, 2] = 2
K = torch.tensor([[[10., 0, 8], [0, 10, 8], [0, 0, 1]]], device=d)
rasterization(m, torch.tensor([[1., 0, 0, 0]], device=d), torch.full((1, 3), .1, device=d),
              torch.ones(1, device=d), torch.ones(1, 3, device=d), torch.eye(4, device=d)[None], K, 16, 16)
torch.cuda.synchronize()" > "$R/gsplat-build.log" 2>&1; echo "gsplat build exit $? in $(( $(date +%s) - t0 )) s" >> "$R/gsplat-build.log") &
  build=$!
  make_scene
  wait "$build"; tail -3 "$R/gsplat-build.log"
  encode peers-slag "${FRONTS:-8}"
  python3 "$CARRY/device_peers.py" "$scene" "$R/peers.json" --every "$every" --raster-scale 0.5 \
    --labels 64 --repeats "${REPEATS:-3}" --slag-report "$W/peers-slag/report.json" 2>&1 | tee "$R/peers.txt"
  ;;
memory)
  make_scene
  shift 4 2>/dev/null || shift $#
  for f in ${@:-1 8}; do encode "memory-f$f" "$f"; done
  ;;
*) echo "unknown mode $mode (peers, memory)"; exit 2 ;;
esac
# At most 8 files come back from a call: pack the results into one archive.
(cd "$R" && shopt -s nullglob && f=(*) && [ ${#f[@]} -gt 6 ] && tar czf "results-$mode.tgz" --exclude='*.tgz' "${f[@]}" && rm -f -- "${f[@]}")
true
