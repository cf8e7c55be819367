#!/usr/bin/env bash
# Runs on the GPU machine (x86_64, no Rust toolchain); NOT part of CI. Two slag-encoder builds'
# `segment` alone (no encode beside it) against each other on a synthetic terrain with a
# synthetic masks' record (scripts/lab/synthetic-mask-record.py: 8 slots, 16 views, masks
# coherent in space, 6 to 8 views per Gaussian): .devcarry/slag-encoder ("new") and
# .devcarry/slag-encoder-old ("old"), alternated, GNU time around each.
# Usage: bash scripts/lab/device-segment-ab.sh [N=30M] [ROUNDS=2] [extra segment flags...]
# Leaves $OUT/seg-TAG.json (the command's stages) and $OUT/seg-TAG.time (GNU time).
set -euo pipefail
n=${1:-30M}; rounds=${2:-2}; shift $(( $# < 2 ? $# : 2 ))
R=${OUT:-/tmp/out}; W=/tmp/slag-work/seg-$n; mkdir -p "$R" "$W"
PY=python3; python3 -c "import numpy" 2>/dev/null || PY=/opt/torch/.venv/bin/python3
cp .devcarry/slag-encoder /tmp/seg-new; cp .devcarry/slag-encoder-old /tmp/seg-old
if [ ! -e "$W/mask-record.safetensors" ]; then
  /tmp/seg-new synth-scene --gaussians "$n" --view-count 16 --width 64 --height 48 --out "$W/s" >/dev/null
  "$PY" scripts/lab/synthetic-mask-record.py "$W/s/point_cloud.ply" "$W/mask-record.safetensors" 16 2.0
fi
for r in $(seq 1 "$rounds"); do
  for b in new old; do
    tag=$b$r
    /usr/bin/time -v "/tmp/seg-$b" segment --ply "$W/s/point_cloud.ply" --out "$W/out-$b.safetensors" \
      --mask-record "$W/mask-record.safetensors" "$@" > "$R/seg-$tag.json" 2> "$R/seg-$tag.time"
    printf '%s %s s, peak %s KB\n' "$tag" \
      "$(grep -o '"seconds":[^,]*' "$R/seg-$tag.json" | head -n1 | cut -d: -f2)" \
      "$(grep 'Maximum resident' "$R/seg-$tag.time" | awk '{print $NF}')"
  done
done
cmp "$W/out-new.safetensors" "$W/out-old.safetensors" && echo "segment files: identical"
