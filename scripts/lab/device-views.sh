#!/usr/bin/env bash
# Runs on the GPU machine (x86_64, NVIDIA, no Rust toolchain); NOT part of CI. The view-count
# table of docs/results/scaling.md: a synthetic scene of N Gaussians at each view count, then one
# `bench` (graph masks, color-clip on the CPU provider, raster 0.5, one GPU, the default outputs)
# per run named in RUNS:
#   all    --views all, otherwise default flags       all2  the same again
#   cover  the default views (coverage selection)      b16   --views all --device-reduce-memory-mb 16384
#   host   --views all --reduce host (its outputs are compared with the last `all` run's)
# Usage: bash scripts/lab/device-views.sh N VIEW_COUNTS RUNS [LAYOUT]
#   e.g. bash scripts/lab/device-views.sh 30M 16,128 all,all2,cover,b16
# Expects .devcarry/slag-encoder.xz (stripped release build) and .devcarry/shared/fixtures/clip,
# and .gl/ (Vulkan loader debs). Writes $OUT/views.txt (one line per run: process wall, peak RSS,
# peak GPU memory, the reduction's waves and peak, observed Gaussians, the coverage pass) and
# $OUT/views-N-COUNTS.tgz (each run's report.json, log tail, RSS timeline and GPU memory samples).
set -uo pipefail
for f in .gl/*.deb; do dpkg -x "$f" / >/dev/null 2>&1; done; ldconfig
VK_DRIVER_FILES=$(bash scripts/vulkan-icd.sh) && [ -n "$VK_DRIVER_FILES" ] && export VK_DRIVER_FILES
ORT_LIB=$(python3 -c 'import onnxruntime, os, glob; print(sorted(glob.glob(os.path.join(os.path.dirname(onnxruntime.__file__), "capi", "libonnxruntime.so*")))[0])')
export ORT_DYLIB_PATH=$ORT_LIB SLAG_SHARED=$PWD/.devcarry/shared XDG_RUNTIME_DIR=/tmp
n=${1:-30M}; counts=${2:-16}; runs=${3:-all}; layout=${4:-ring}
R=${OUT:-/tmp/out}; W=/tmp/slag-views; L=$W/logs; mkdir -p "$R" "$L"
B=/tmp/slag-encoder
[ -x "$B" ] || python3 -c "import lzma, shutil; shutil.copyfileobj(lzma.open('.devcarry/slag-encoder.xz'), open('$B', 'wb'))"
chmod +x "$B"
nvidia-smi --query-gpu=index,name,driver_version,memory.total --format=csv,noheader | tee -a "$R/views.txt"
echo "cores: $(nproc); scene: $n Gaussians, layout $layout" | tee -a "$R/views.txt"
T=(/usr/bin/env time -v)
for v in ${counts//,/ }; do
  rm -rf "$W/scene" "$W"/out-*
  start=$(date +%s.%N)
  "$B" synth-scene --gaussians "$n" --view-count "$v" --layout "$layout" --out "$W/scene" > /dev/null \
    || { echo "synth-scene $n $v failed" | tee -a "$R/views.txt"; continue; }
  echo "## $n / $v views: synth-scene $(python3 -c "import time; print(round(time.time()-$start,1))") s" | tee -a "$R/views.txt"
  last_all=
  for run in ${runs//,/ }; do
    case $run in
      all|all2) flags=(--views all) ;;
      cover) flags=() ;;
      b16) flags=(--views all --device-reduce-memory-mb 16384) ;;
      host) flags=(--views all --reduce host) ;;
      *) echo "unknown run $run"; continue ;;
    esac
    tag=$n-$v-$run; out=$W/out-$run
    nvidia-smi --query-gpu=memory.used --format=csv,noheader,nounits -lms 250 > "$L/gpu-$tag.csv" 2>/dev/null & watch=$!
    start=$(date +%s.%N)
    timeout 560 python3 scripts/lab/rss-timeline.py --every 0.25 --out "$L/rss-$tag.tsv" --report "$out/report.json" -- \
      "${T[@]}" "$B" bench --scene-dir "$W/scene" --masks graph \
      --clip-visual .devcarry/shared/fixtures/clip/color-clip-visual.onnx --ep cpu --raster-scale 0.5 \
      --gpus 1 "${flags[@]}" --quiet --out "$out" > "$L/run-$tag.txt" 2>&1
    rc=$?
    wall=$(python3 -c "import time; print(round(time.time()-$start,1))")
    kill $watch 2>/dev/null
    cp "$out/report.json" "$L/report-$tag.json" 2>/dev/null
    python3 scripts/lab/views-row.py "$tag" "$rc" "$wall" "$out/report.json" "$L/run-$tag.txt" "$L/gpu-$tag.csv" \
      | tee -a "$R/views.txt"
    if [ "$run" = host ] && [ -n "$last_all" ]; then
      for f in "$out"/*.safetensors; do
        echo "  host vs device, $(basename "$f"): $(cmp -s "$f" "$last_all/$(basename "$f")" && echo identical || echo DIFFERENT)" | tee -a "$R/views.txt"
      done
    fi
    if [ "$run" = all ] || [ "$run" = all2 ]; then
      rm -rf "$W/keep-all"; mv "$out" "$W/keep-all"; last_all=$W/keep-all
    else
      rm -rf "$out"
    fi
  done
done
tar czf "$R/views-$n-${counts//,/_}.tgz" -C "$L" . && rm -rf "$L"
exit 0
