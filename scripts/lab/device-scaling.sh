#!/usr/bin/env bash
# Runs on a multi-GPU machine (x86_64, NVIDIA, no Rust toolchain); NOT part of CI.
#   scripts/lab/device-scaling.sh scaling [GPU_COUNTS]   # slag-bench scaling: same scene on 1,2,4 GPUs
#   scripts/lab/device-scaling.sh clip                   # CLIP ViT-B/16: torch (GPU) vs ONNX Runtime
#   scripts/lab/device-scaling.sh big [N] [VIEWS]        # synthetic terrain of N Gaussians (default 30M)
#                                                    # on one GPU, peak host + GPU memory
#   scripts/lab/device-scaling.sh reduce [N] [VIEWS] [MODES]  # synthetic terrain (default 30M, 16 views; every
#                                                    # view unless VIEWS="--views ..." is set),
#                                                    # one bench per --reduce mode in MODES (default
#                                                    # host,auto,auto; `default` passes no --reduce),
#                                                    # GNU time, GPU memory and an RSS timeline each
#   scripts/lab/device-scaling.sh stages                 # slag-bench stages: each stage vs its floor
#                                                    # (color-clip all views; ViT-B/16 and color-sam
#                                                    # every 8th view); rates from device_facts.py
#   scripts/lab/device-scaling.sh stages-color [FRONTS]  # the color-clip stage table again per front count
#   scripts/lab/device-scaling.sh tradeoffs IDS          # slag-bench tradeoffs --cached-only --encode IDS
#                                                    # on the snowmiku copy; the work folder's records
#                                                    # go back as tw.tgz and come in as .devwork/tw.tgz
# Expects .devcarry/ (release slag-encoder, scene/ = snowmiku geometry + DC .ply and images,
# shared/fixtures/) and .gl/ (Vulkan loader debs), as scripts/lab/device-bench.sh. Reports, logs and
# timing tables go to $OUT.
set -uo pipefail
for f in .gl/*.deb; do dpkg -x "$f" / >/dev/null; done; ldconfig
VK_DRIVER_FILES=$(bash scripts/vulkan-icd.sh) && [ -n "$VK_DRIVER_FILES" ] && export VK_DRIVER_FILES  # the NVIDIA ICD that works headless
ORT_LIB=$(python3 -c 'import onnxruntime, os, glob; print(sorted(glob.glob(os.path.join(os.path.dirname(onnxruntime.__file__), "capi", "libonnxruntime.so*")))[0])')
export ORT_DYLIB_PATH=$ORT_LIB SLAG_SHARED=$PWD/.devcarry/shared XDG_RUNTIME_DIR=/tmp
export NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1
B=.devcarry/slag-encoder; BB=.devcarry/slag-bench; F=.devcarry/shared/fixtures
R=${OUT:-/tmp/out}; W=/tmp/slag-work; mkdir -p "$R" "$W"
nvidia-smi --query-gpu=index,name,driver_version,memory.total --format=csv,noheader
echo "cores: $(nproc)  ORT: $ORT_LIB"
CLIP=(--clip-visual $F/clip/color-clip-visual.onnx)
mode=${1:-scaling}

gpu_mem_watch() { # samples the GPUs' used memory every 0.5 s into $1 until killed
  nvidia-smi --query-gpu=index,memory.used --format=csv,noheader,nounits -lms 500 > "$1" 2>/dev/null
}

case "$mode" in
scaling)
  counts=${2:-1,2,4}
  fronts=${FRONTS:-12}
  echo "### scaling: snowmiku, 97 views, graph masks, raster 1.0, GPUs $counts, $fronts front workers"
  "$BB" scaling --scene-dir .devcarry/scene --masks graph "${CLIP[@]}" --raster-scale 1.0 \
    --front-workers "$fronts" --quiet --counts "$counts" --out "$W/scaling" --table "$R/scaling.md" \
    2>&1 | grep -v XDG_RUNTIME
  for g in ${counts//,/ }; do cp "$W/scaling/g$g/report.json" "$R/report-scaling-g$g.json"; done
  ;;
big)
  n=${2:-30M}; v=${3:-24}
  echo "### synth-scene $n Gaussians, $v views"
  /usr/bin/env time -v true >/dev/null 2>&1 && T=(/usr/bin/env time -v) || T=()
  start=$(date +%s.%N)
  "$B" synth-scene --gaussians "$n" --view-count "$v" --out "$W/big" | tee "$R/synth.json"
  echo "synth-scene took $(python3 -c "import time; print(round(time.time()-$start,1))") s"
  du -sh "$W/big"
  gpu_mem_watch "$R/gpu-mem-big.csv" & watch=$!
  "${T[@]}" "$B" bench --scene-dir "$W/big" --masks graph "${CLIP[@]}" --raster-scale 0.5 ${VIEWS:---views all} --gpus 1 \
    --contribution-memory-mb 4096 --accumulator-memory-mb 2048 --quiet --out "$W/big-out" 2>&1 \
    | grep -v XDG_RUNTIME | tee "$R/big.txt"
  kill $watch 2>/dev/null
  cp "$W/big-out/report.json" "$R/report-big.json"
  ls -l "$W/big-out"
  python3 - "$R/gpu-mem-big.csv" <<'EOF'
import sys
peak = {}
for line in open(sys.argv[1]):
    p = [x.strip() for x in line.split(",")]
    if len(p) == 2 and p[1].isdigit():
        peak[p[0]] = max(peak.get(p[0], 0), int(p[1]))
print("peak GPU memory used (MiB):", peak)
EOF
  ;;
reduce)
  n=${2:-30M}; v=${3:-16}; modes=${4:-host,auto,auto}
  echo "### synth-scene $n Gaussians, $v views; bench with --reduce in $modes"
  /usr/bin/env time -v true >/dev/null 2>&1 && T=(/usr/bin/env time -v) || T=()
  # A warm machine keeps the scene of an earlier call with the same size.
  [ -f "$W/big-$n-$v.done" ] || { rm -rf "$W/big" && "$B" synth-scene --gaussians "$n" \
    --view-count "$v" --out "$W/big" > /dev/null && touch "$W/big-$n-$v.done"; }
  i=0
  for m in ${modes//,/ }; do
    i=$((i+1))
    rm -rf "$W"/out-*  # the disk holds one 30M run's outputs (31 GB dense) at a time
    gpu_mem_watch "$W/gpu-mem-$i.csv" & watch=$!
    ra=(--reduce "$m"); [ "$m" = default ] && ra=()  # default: the encoder's own choice
    start=$(date +%s.%N)
    # RSS over time (rss-*.tsv: seconds, bytes) and its peak before, in and after the encode's tail.
    python3 scripts/lab/rss-timeline.py --every 0.25 --out "$R/rss-$i-$m.tsv" --report "$W/out-$i/report.json" -- \
    "${T[@]}" "$B" bench --scene-dir "$W/big" --masks graph "${CLIP[@]}" --ep cpu --raster-scale 0.5 ${VIEWS:---views all} \
      --gpus 1 --contribution-memory-mb 4096 --accumulator-memory-mb 2048 "${ra[@]}" --quiet \
      --out "$W/out-$i" > "$W/run-$i.txt" 2>&1
    wall=$(python3 -c "import time; print(round(time.time()-$start,1))")
    kill $watch 2>/dev/null
    python3 - "$W/out-$i/report.json" "$W/run-$i.txt" "$W/gpu-mem-$i.csv" "$m" "$wall" <<'EOF2' | tee -a "$R/reduce.txt"
import json, re, sys
rep, log, mem, mode, wall = sys.argv[1:]
r = json.load(open(rep))
t, c = r["timings"], r["counts"]
rss = re.search(r"Maximum resident set size \(kbytes\): (\d+)", open(log).read())
peak = 0
for line in open(mem):
    p = [x.strip() for x in line.split(",")]
    if len(p) == 2 and p[1].isdigit():
        peak = max(peak, int(p[1]))
keys = [k for k in t if isinstance(t[k], (int, float))]
print(f"--reduce {mode}: process wall {wall} s, device_reduce {c.get('device_reduce')}, "
      f"peak RSS {int(rss.group(1)) / 2**20 if rss else -1:.2f} GiB, peak GPU {peak} MiB, "
      f"observed {c['observed']}, chunks {c['reduce_chunks']}")
print("  " + ", ".join(f"{k} {t[k]:.2f}" for k in keys))
seg = r.get("segments")
if seg:
    st = seg["stats"]
    print(f"  segments {st['segments']} in {st['seconds']:.2f} s on {seg['threads']} threads "
          f"(widened to {seg['widened_to']}), waited {seg['waited_s']:.2f} s; stages "
          + ", ".join(f"{k} {v:.2f}" for k, v in st["stages"].items() if isinstance(v, (int, float))))
for line in open(log):
    if any(s in line for s in ("segments written", "rss-timeline", "device reduction", "neighbour search")) or "error" in line.lower():
        print("  " + line.strip()[-300:])
EOF2
    grep -v XDG_RUNTIME "$W/run-$i.txt" | tail -40 > "$R/run-$i-$m.txt"
  done
  ;;
clip)
  echo "### CLIP ViT-B/16 (random weights): torch on the GPU vs ONNX Runtime, batch 32"
  python3 scripts/lab/device_clip_vs_torch.py "$W/clip" 2>&1 | grep -v Warning | tee "$R/clip-vs-torch.txt"
  echo "### slag-encoder with that model (graph masks, every 8th view, 1 GPU)"
  "$B" bench --scene-dir .devcarry/scene --masks graph --clip-visual "$W/clip/vitb16-clip-visual.onnx" \
    --every 8 --raster-scale 0.5 --quiet --out "$W/clip-run" 2>&1 | grep -v XDG_RUNTIME | tee "$R/clip-run.txt"
  cp "$W/clip-run/report.json" "$R/report-clip-run.json"
  ;;
stages)
  echo "### facts: rates of this machine, FLOPs of the models; torch vs ORT for CLIP ViT-B/16"
  python3 scripts/lab/device_clip_vs_torch.py "$W/clip" 2>&1 | grep -v Warning | tee "$R/clip-vs-torch.txt"
  V=$W/clip/vitb16-clip-visual.onnx
  cp "$W/clip/clip-vs-torch.json" "$R/"
  python3 scripts/lab/device_facts.py "$R/facts.json" $F/clip/color-clip-visual.onnx \
    $F/sam-amg/color-sam-encoder.onnx $F/sam-amg/color-sam-decoder.onnx "$V" | tee "$R/facts.txt"
  S=(--scene-dir .devcarry/scene --raster-scale 1.0 --quiet --facts "$R/facts.json")
  echo "### stages: graph masks, color-clip, all views"
  "$BB" stages "${S[@]}" --masks graph "${CLIP[@]}" --front-workers 15 --out "$W/st-color" \
    --table "$R/stages-color.md" 2>&1 | grep -v XDG_RUNTIME
  echo "### stages: graph masks, CLIP ViT-B/16 (random weights), every 8th view"
  "$BB" stages "${S[@]}" --masks graph --clip-visual "$V" --every 8 --front-workers 4 \
    --torch "$R/clip-vs-torch.json" --out "$W/st-vit" --table "$R/stages-vitb16.md" 2>&1 | grep -v XDG_RUNTIME
  echo "### stages: color-sam 32x32 points, color-clip, every 8th view"
  "$BB" stages "${S[@]}" --masks sam --sam-encoder $F/sam-amg/color-sam-encoder.onnx \
    --sam-decoder $F/sam-amg/color-sam-decoder.onnx --sam-pred-iou-thresh 0.8 \
    --sam-stability-score-thresh 0.5 "${CLIP[@]}" --every 8 --front-workers 8 --out "$W/st-sam" \
    --table "$R/stages-sam.md" 2>&1 | grep -v XDG_RUNTIME
  for m in color vitb16 sam; do cp "$W/st-${m/vitb16/vit}/report.json" "$R/report-stages-$m.json" 2>/dev/null; done
  ;;
stages-color)
  # Re-time the color-clip stage table with facts measured before (.devwork/facts.json), once per
  # front-worker count given (default 15).
  for fw in ${2:-15}; do
    echo "### stages: graph masks, color-clip, all views, $fw front workers"
    "$BB" stages --scene-dir .devcarry/scene --raster-scale 1.0 --quiet --facts .devwork/facts.json \
      --masks graph "${CLIP[@]}" --front-workers "$fw" --out "$W/st-color-$fw" \
      --table "$R/stages-color-f$fw.md" 2>&1 | grep -v XDG_RUNTIME
  done
  ;;
tradeoffs)
  TW=target/slag-bench/snowmiku-dev; mkdir -p "$TW"
  [ -f .devwork/tw.tgz ] && tar xzf .devwork/tw.tgz -C "$TW"
  timeout "${TW_TIMEOUT:-540}" "$BB" tradeoffs --scene-dir .devcarry/scene --fixtures $F --work "$TW" \
    --out "$R/tradeoffs" --front-workers 8 --cached-only --encode "${2:-}" \
    --note "$(nvidia-smi --query-gpu=name --format=csv,noheader | head -1), $(nproc) cores, GPU raster (wgpu/Vulkan), ORT CPU EP" \
    2>&1 | grep -v XDG_RUNTIME | tee "$R/tradeoffs.log"
  (cd "$TW" && find . \( -name record.json -o -name eval.json -o -name report.json \) -print0 \
    | tar czf "$R/tw.tgz" --null -T -)
  ;;
*) echo "unknown mode $mode"; exit 2;;
esac
exit 0
