#!/usr/bin/env bash
# Lifting before/after on the GPU machine, same scene, same run: binaries slag-encoder-main.gz and
# slag-encoder-lifting.gz (stripped, gzip), libonnxruntime.so.gz and the color-sam / color-clip
# ONNX files in .devcarry-lifting/ (carried with .gl). VIEWS (32) and EVERY (2) set the workload.
set -uo pipefail
for f in .gl/*.deb; do dpkg -x "$f" / >/dev/null 2>&1; done; ldconfig
VK_DRIVER_FILES=$(bash scripts/vulkan-icd.sh) && [ -n "$VK_DRIVER_FILES" ] && export VK_DRIVER_FILES  # the NVIDIA ICD that works headless
C=$PWD/.devcarry-lifting; R=${OUT:-/tmp/out}; W=/root/lw; mkdir -p $W/bin $R
for b in main lifting; do [ -f $C/slag-encoder-$b.gz ] && gunzip -c $C/slag-encoder-$b.gz > $W/bin/$b && chmod +x $W/bin/$b; done
gunzip -c $C/libonnxruntime.so.gz > $W/libonnxruntime.so; export ORT_DYLIB_PATH=$W/libonnxruntime.so
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader; echo "cores $(nproc)"
V=${VIEWS:-32}
t0=$(date +%s); $W/bin/lifting synth-scene --gaussians 2M --view-count $V --width 990 --height 742 --out $W/scene > $R/synth.json; echo "synth $(( $(date +%s)-t0 )) s"
SAM=(--masks sam --sam-encoder $C/color-sam-encoder.onnx --sam-decoder $C/color-sam-decoder.onnx --sam-points-per-side 16 --sam-pred-iou-thresh 0.8 --sam-stability-score-thresh 0.5)
run() { # name bin timeout args...
  local n=$1 b=$2 to=$3; shift 3; local t=$(date +%s)
  timeout $to /usr/bin/time -v $W/bin/$b bench --scene-dir $W/scene --raster-scale 0.5 --rasterizer gpu --ep cpu \
    --clip-visual $C/color-clip-visual.onnx --quiet --out $W/$n "$@" > $R/$n.txt 2>&1; local rc=$?
  cp $W/$n/report.json $R/report-$n.json 2>/dev/null
  python3 - $R/report-$n.json $n $rc $(( $(date +%s)-t )) <<'PY'
import json,sys
try: r=json.load(open(sys.argv[1]))
except Exception as e: print(sys.argv[2],"rc",sys.argv[3],"no report",sys.argv[4],"s"); sys.exit()
c=r["counts"]; v=max(1,c["views_used"]); t=r["timings"]
ph={}
for w in r.get("workers",[]):
  for k,x in (w.get("raster_phases_ms") or {}).items(): ph[k]=ph.get(k,0)+x
print(f"{sys.argv[2]}: rc {sys.argv[3]} wall {sys.argv[4]} s views {v} masks/img {c['masks']/v:.1f} dsv {c['device_sum_views']} "
      f"raster {t['raster']/v*1e3:.1f} ms/v a_kj-host {t['image_aggregate']/v*1e3:.1f} ms/v rss {c['peak_rss_bytes']/2**30:.2f} GiB "
      + " ".join(f"{k} {x/v:.1f}" for k,x in ph.items()))
PY
}
run graph-main main 150 --masks graph
run graph-lifting lifting 150 --masks graph
run sam-lifting lifting 150 "${SAM[@]}" --every ${EVERY:-2}
run sam-main main 120 "${SAM[@]}" --every ${EVERY:-2}
