#!/usr/bin/env bash
# SAM and CLIP on the GPU, on a GPU machine (x86_64, NVIDIA, torch, no Rust, no
# network); NOT part of CI. Needs, on that machine, ONNX Runtime's CUDA provider assembled in
# /root/og (../shared/tools/ort-gpu-chunks.sh: four carries), and carried: .whl/ (segment_anything,
# open_clip_torch, ftfy, wcwidth wheels), .devcarry/ (zstd-compressed release slag-encoder and
# slag-bench, scene/ = snowmiku images + COLMAP + a geometry+DC .ply) and .gl/ (Vulkan loader debs).
#   scripts/lab/device-gpu-models.sh prep        # wheels, binaries, real-size random-weight exports:
#                                            # SAM ViT-B and ViT-H, CLIP ViT-B/16, f32 and fp16;
#                                            # device facts (rates, FLOPs); torch fp16/fp32 peers
#                                            # DECF16=1: also SAM with a half-precision mask
#                                            # decoder (--fp16-decoder) in models/f16d
#   scripts/lab/device-gpu-models.sh stages      # slag-bench stages per model, CUDA and CPU
#   scripts/lab/device-gpu-models.sh e2e [N] [V] # synthetic scene of N Gaussians (2M), V views (250)
#                                            # at 990x742: ViT-H 16x16 + CLIP ViT-B/16 on CUDA
#                                            # MASKMODEL=DIR: timing model + mask model: ViT-H
#                                            # runs on every image for its cost, DIR's color-sam
#                                            # 16x16 (0.8/0.5) masks (~84 / image) go downstream
#                                            # LOWRES=1: both SAM decoders cut down by
#                                            # scripts/sam-decoder-low-res.py (needs python onnx)
#                                            # DECDIR=f16d: ViT-H's half-precision decoder
#                                            # ENCDIR=f16x: the fused-attention encoder (exported
#                                            # here when missing; sam mode exports it too)
#                                            # F16M=1: ViT-H's low-res decoder returns f16
#                                            # multimask channels (--f16-multimask)
#                                            # TAG=NAME: the run's files named e2e-PREC-NAME
#                                            # EXTRA="ARGS": more slag-encoder bench arguments
#   scripts/lab/device-gpu-models.sh paper [N] [V] # the paper's large scene: N Gaussians (38M), V
#                                            # views (1657) at 990x742 on a drone's sweep
#                                            # (synth-scene --layout sweep), e2e's models (ViT-H
#                                            # 16x16 + CLIP ViT-B/16, PREC), every view and the
#                                            # default views (SELECTIONS="all coverage"); GNU
#                                            # time, an RSS timeline and GPU memory each
#                                            # MASKMODEL=DIR: e2e's timing + mask models
#   scripts/lab/device-gpu-models.sh models      # per-model table: slag-bench models (CLIP f32 / fp16 /
#                                            # fused, SAM ViT-H) + torch fp16 + ORT profiles
#                                            # (CLIPDIR=f16fuse: e2e with the fused CLIP tower)
#   scripts/lab/device-gpu-models.sh sam         # SAM ViT-H fp16: plain vs fused-attention encoder,
#                                            # f32 4-channel vs f16 multimask low-res logits;
#                                            # ORT profiles; torch fp16 + its CUDA profile
#   scripts/lab/device-gpu-models.sh graphs      # per model: host copies vs IO binding vs CUDA graph
#                                            # (device_ort_cuda_graph.py; carry .pyort/)
#   scripts/lab/device-gpu-models.sh clipu8      # CLIP fp16 fused: f32 pixel_values vs u8 pixels
#                                            # (clip-u8-pixels.py), slag-bench models
#   scripts/lab/device-gpu-models.sh fronts      # 8 front workers on CUDA (crashed before sessions
#                                            # were shared per GPU)
#   scripts/lab/device-gpu-models.sh scaling [C] # slag-bench scaling --counts C (1,2) on the e2e scene
#   scripts/lab/device-gpu-models.sh clipbatch   # CLIP ViT-B/16 fp16 on CUDA at --clip-batch 8..128
#                                            # (snowmiku every 2nd view, graph masks, 4 fronts)
#   scripts/lab/device-gpu-models.sh reduce      # slag-bench reduce at the e2e scene's size (2M
#                                            # Gaussians, 250 views x 250k a_kj, D 512): both loop
#                                            # orders of the reduction + the f16 write (CPU only)
# Files under /root survive between calls while the machine is held. Results go to $OUT.
# SLAG_ENCODER=PATH runs another slag-encoder build (e.g. a base to compare with, in the same call).
set -uo pipefail
for f in .gl/*.deb; do dpkg -x "$f" / >/dev/null 2>&1; done; ldconfig
VK_DRIVER_FILES=$(bash scripts/vulkan-icd.sh) && [ -n "$VK_DRIVER_FILES" ] && export VK_DRIVER_FILES  # the NVIDIA ICD that works headless
export NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1
export XDG_RUNTIME_DIR=/tmp PYTHONPATH=/root/site PYTHONUNBUFFERED=1 SLAG_EXPORT_NO_CHECK=1
# shellcheck disable=SC1091
source /root/og/assemble.sh
R=${OUT:-/tmp/out}; W=/root/work; M=/root/models; B=${SLAG_ENCODER:-/root/bin/slag-encoder}; BB=/root/bin/slag-bench
mkdir -p "$R" "$W" "$M" /root/bin
if [ -d .devcarry ]; then
  for z in .devcarry/*.zst; do [ -f "$z" ] && LD_LIBRARY_PATH=/root/og /root/og/zstd -dqf "$z" -o "/root/bin/$(basename "$z" .zst)"; done
  chmod +x /root/bin/* 2>/dev/null
  [ -d .devcarry/scene ] && rm -rf /root/scene && cp -r .devcarry/scene /root/scene
fi
nvidia-smi --query-gpu=index,name,driver_version,memory.total --format=csv,noheader
echo "cores: $(nproc)  ORT: $ORT_DYLIB_PATH"
mode=${1:-prep}
SAMARGS=(--masks sam --sam-points-per-side 16 --sam-pred-iou-thresh 0 --sam-stability-score-thresh 0)
samm() { echo --sam-encoder "$M/$1/sam-$2-encoder.onnx" --sam-decoder "$M/$1/sam-$2-decoder.onnx"; }
clipm() { echo --clip-visual "$M/${CLIPDIR:-$1}/"*visual*.onnx; }
# SAM ViT-H fp16 with the fp16 decoder (the image's work once per call) in $M/f16d, its decoder
# cut to the low-res outputs, and the same cut returning f16 multimask logits (-f16m).
vith_f16d() {
  if [ ! -f "$M/f16d/sam-vit_h-decoder-low-res.onnx" ]; then
    python3 scripts/export-models.py sam --kind vit_h --random --fp16 --fp16-decoder "$M/f16d" > "$R/export-vith.json" 2> "$R/export-vith.err" || tail -3 "$R/export-vith.err"
    python3 scripts/sam-decoder-low-res.py "$M/f16d/sam-vit_h-decoder.onnx" "$M/f16d/sam-vit_h-decoder-low-res.onnx"
  fi
  [ -f "$M/f16d/sam-vit_h-decoder-low-res-f16m.onnx" ] || python3 scripts/sam-decoder-low-res.py --f16-multimask \
    "$M/f16d/sam-vit_h-decoder.onnx" "$M/f16d/sam-vit_h-decoder-low-res-f16m.onnx"
}
# SAM ViT-H fp16 with fused attention in its encoder ($M/f16x: export-models.py --fuse, its fp16
# decoder with it), unless an earlier call left it.
vith_f16x() {
  [ -f "$M/f16x/sam-vit_h-encoder.onnx" ] && return
  python3 scripts/export-models.py sam --kind vit_h --random --fp16 --fp16-decoder --fuse "$M/f16x" > "$R/export-vith-fused.json" 2> "$R/export-vith-fused.err" || tail -3 "$R/export-vith-fused.err"
  grep -A14 fused_encoder "$R/export-vith-fused.json"
}
# The carried wheels (segment_anything, open_clip_torch, ftfy, wcwidth) into /root/site.
# MA = the timing model + mask model arguments: SAM ViT-H (encoder $2, decoder $3) runs on every
# image for its cost, $MASKMODEL's color-sam 16x16 (0.8 / 0.5; decoder $1) gives the masks that go
# downstream (about 100 an image on a synthetic scene, as a trained SAM keeps), so CLIP and the
# lifting see a real mask count while a random-weight ViT-H keeps almost none.
timed_masks() {
  MA=(--masks sam --sam-points-per-side 16 --sam-pred-iou-thresh 0.8 --sam-stability-score-thresh 0.5
    --sam-encoder "$MASKMODEL/color-sam-encoder.onnx" --sam-decoder "$1"
    --sam-timing-encoder "$2" --sam-timing-decoder "$3")
  echo "### timing model SAM ViT-H $prec, mask model color-sam 16x16 (0.8/0.5)"
}
wheels() { python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /root/site .whl/*.whl; }
# CLIP ViT-B/16 fp16 fused ($M/f16fuse) and the same file given byte input ($M/f16fuse-u8,
# scripts/clip-u8-pixels.py), each exported unless an earlier call left it.
clip_f16fuse() {
  local f=$M/f16fuse/ViT-B-16-random-visual.onnx u=$M/f16fuse-u8/ViT-B-16-random-visual.onnx
  [ -f "$f" ] || python3 scripts/export-models.py clip --model ViT-B-16 --random --fp16 --fuse "$M/f16fuse" > "$R/export-clip.json" 2> "$R/export-clip.err" || tail -3 "$R/export-clip.err"
  [ -f "$u" ] || { mkdir -p "$M/f16fuse-u8" && python3 scripts/clip-u8-pixels.py "$f" "$u"; }
}
case "$mode" in
prep)
  wheels
  t0=$(date +%s)
  if [ ! -f "$M/f16/sam-vit_h-encoder.onnx" ]; then
  for k in ${KINDS:-vit_b vit_h}; do
    [ "${QUICK:-0}" = 1 ] || python3 scripts/export-models.py sam --kind $k --random "$M/f32" > "$R/export-$k.json" 2>"$R/export-$k.err" || tail -5 "$R/export-$k.err"
    python3 scripts/export-models.py sam --kind $k --random --fp16 "$M/f16" > "$R/export-$k-fp16.json" 2>"$R/export-$k-fp16.err" || tail -5 "$R/export-$k-fp16.err"
    echo "exported $k ($(( $(date +%s) - t0 )) s)"
  done
  if [ "${DECF16:-0}" = 1 ]; then
    # The decoders with a half-precision mask decoder too (export-models.py --fp16-decoder).
    for k in ${KINDS:-vit_b vit_h}; do
      python3 scripts/export-models.py sam --kind $k --random --fp16 --fp16-decoder "$M/f16d" > "$R/export-$k-fp16d.json" 2>"$R/export-$k-fp16d.err" || tail -5 "$R/export-$k-fp16d.err"
    done
  fi
  [ "${QUICK:-0}" = 1 ] || python3 scripts/export-models.py clip --model ViT-B-16 --random "$M/f32" > "$R/export-clip.json" 2>&1 | tail -3
  python3 scripts/export-models.py clip --model ViT-B-16 --random --fp16 "$M/f16" > "$R/export-clip-fp16.json" 2>&1 | tail -3
  fi
  ls -la "$M"/f32 "$M"/f16
  [ "${QUICK:-0}" = 1 ] && exit 0
  python3 scripts/lab/device_facts.py "$R/facts.json" "$M"/f32/sam-vit_b-encoder.onnx \
    "$M"/f32/sam-vit_b-decoder.onnx $(ls "$M"/f32/*visual*.onnx) > "$R/facts.log" 2>&1 || tail -5 "$R/facts.log"
  cp "$R/facts.json" /root/facts.json
  python3 scripts/lab/device_torch_peers.py "$R/torch-peers.json" 2>&1 | tail -12
  cp "$R/torch-peers.json" /root/torch-peers.json
  ;;
stages)
  S=(--scene-dir /root/scene --raster-scale 0.5 --quiet --facts /root/facts.json)
  st() { # name, ep, every, args...
    local name=$1 ep=$2 every=$3; shift 3
    echo "### $name ($ep, every $every)"
    "$BB" stages "${S[@]}" --ep "$ep" --every "$every" "$@" --out "$W/$name" --table "$R/stages-$name.md" 2>&1 \
      | grep -v "^\s*$" | tail -4
    cp "$W/$name/report.json" "$R/report-$name.json" 2>/dev/null
  }
  for prec in f16 f32; do
    st "vitb-$prec-cuda" cuda 4 "${SAMARGS[@]}" $(samm $prec vit_b) $(clipm $prec)
    st "vith-$prec-cuda" cuda 4 "${SAMARGS[@]}" $(samm $prec vit_h) $(clipm $prec)
    st "clip-$prec-cuda" cuda 2 --masks graph $(clipm $prec)
  done
  st vitb-f32-cpu cpu 49 "${SAMARGS[@]}" $(samm f32 vit_b) $(clipm f32)
  st clip-f32-cpu cpu 49 --masks graph $(clipm f32)
  ;;
fronts)
  echo "### 8 front workers, SAM ViT-B fp16 + CLIP ViT-B/16 fp16, CUDA"
  /usr/bin/time -v "$B" bench --scene-dir /root/scene --ep cuda --every 4 --raster-scale 0.5 --front-workers 8 \
    "${SAMARGS[@]}" $(samm f16 vit_b) $(clipm f16) --quiet --out "$W/fronts8" > "$R/fronts8.txt" 2>&1
  echo "exit $?"; grep -E "wall|masks|CLIP|Maximum resident|peak|execution" "$R/fronts8.txt" | head -20
  cp "$W/fronts8/report.json" "$R/report-fronts8.json" 2>/dev/null
  ;;
paper)
  n=${2:-38M}; v=${3:-1657}; d=/root/paper-$n-$v
  if [ ! -f "$d/report-synth.json" ]; then
    echo "### synth-scene $n Gaussians, $v views 990x742, drone sweep"
    t0=$(date +%s.%N)
    /usr/bin/time -v "$B" synth-scene --gaussians "$n" --view-count "$v" --width 990 --height 742 \
      --layout sweep --out "$d" > /root/paper-synth.json 2> "$R/paper-synth.txt"
    echo "exit $? synth-scene took $(python3 -c "import time; print(round(time.time()-$t0,1))") s"
    grep -E "Maximum resident|Elapsed" "$R/paper-synth.txt"
    cp /root/paper-synth.json "$d/report-synth.json"
  fi
  cp "$d/report-synth.json" "$R/paper-synth.json"
  prec=${PREC:-f16}
  MA=("${SAMARGS[@]}" $(samm $prec vit_h))
  [ -n "${MASKMODEL:-}" ] && timed_masks "$MASKMODEL/color-sam-decoder.onnx" "$M/$prec/sam-vit_h-encoder.onnx" "$M/$prec/sam-vit_h-decoder.onnx"
  for sel in ${SELECTIONS:-all coverage}; do
    echo "### encode $sel views: SAM ViT-H $prec 16x16 + CLIP ViT-B/16 $prec, CUDA"
    gpu_mem() { nvidia-smi --query-gpu=index,memory.used --format=csv,noheader,nounits -lms 500; }
    gpu_mem > "$R/gpu-mem-paper-$sel.csv" 2>/dev/null & watch=$!
    python3 scripts/lab/rss-timeline.py --out "$R/rss-paper-$sel.tsv" --report "$W/paper-$sel/report.json" -- \
      /usr/bin/time -v "$B" bench --scene-dir "$d" --ep cuda --raster-scale 0.5 --views "$sel" \
      "${MA[@]}" $(clipm $prec) ${EXTRA:-} --quiet --out "$W/paper-$sel" \
      > "$R/paper-$sel.txt" 2>&1
    echo "exit $?"; kill $watch 2>/dev/null
    grep -E "wall|views|observed|Maximum resident|Elapsed" "$R/paper-$sel.txt" | tail -12
    cp "$W/paper-$sel/report.json" "$R/report-paper-$sel.json" 2>/dev/null
  done
  ;;
e2e)
  n=${2:-2M}; v=${3:-250}
  if [ ! -f /root/big/report-synth.json ]; then
    echo "### synth-scene $n Gaussians, $v views 990x742"
    t0=$(date +%s.%N)
    "$B" synth-scene --gaussians "$n" --view-count "$v" --width 990 --height 742 --out /root/big > /root/big-synth.json
    echo "synth-scene took $(python3 -c "import time; print(round(time.time()-$t0,1))") s"; cp /root/big-synth.json /root/big/report-synth.json
  fi
  cp /root/big/report-synth.json "$R/synth.json"
  prec=${PREC:-f16}
  # The models this run names, exported here if an earlier call did not (DECDIR=f16d: ViT-H
  # fp16 with its fp16 decoder; CLIPDIR=f16fuse[-u8]: CLIP fp16 fused [taking bytes]).
  if [ "${DECDIR:-}" = f16d ]; then
    wheels
    vith_f16d
  fi
  # ENCDIR=f16x: the timing model's encoder with fused attention (its decoder stays DECDIR's).
  [ "${ENCDIR:-}" = f16x ] && { wheels; vith_f16x; }
  case "${CLIPDIR:-}" in f16fuse|f16fuse-u8) clip_f16fuse ;; esac
  t=$prec${TAG:+-$TAG}
  MA=("${SAMARGS[@]}" $(samm $prec vit_h))
  if [ -n "${MASKMODEL:-}" ]; then
    dec=("$MASKMODEL/color-sam-decoder.onnx" "$M/${DECDIR:-$prec}/sam-vit_h-decoder.onnx")
    if [ "${LOWRES:-0}" = 1 ]; then
      # Both decoders cut down to iou_predictions + low_res_masks (same masks, less GPU work).
      python3 scripts/sam-decoder-low-res.py "${dec[0]}" /root/color-sam-decoder-low-res.onnx
      low=$M/${DECDIR:-$prec}/sam-vit_h-decoder-low-res${F16M:+-f16m}.onnx
      python3 scripts/sam-decoder-low-res.py ${F16M:+--f16-multimask} "${dec[1]}" "$low"
      dec=(/root/color-sam-decoder-low-res.onnx "$low")
    fi
    timed_masks "${dec[0]}" "$M/${ENCDIR:-$prec}/sam-vit_h-encoder.onnx" "${dec[1]}"
  fi
  echo "### encode: SAM ViT-H $prec 16x16 + CLIP ViT-B/16 $prec, CUDA, ${FRONTS:-default} fronts"
  # RSS over time (rss-e2e-*.tsv: seconds, bytes): where the peak falls against the report's phases.
  python3 scripts/lab/rss-timeline.py --out "$R/rss-e2e-$t.tsv" --report "$W/e2e/report.json" -- \
    /usr/bin/time -v "$B" bench --scene-dir /root/big --ep cuda --raster-scale 0.5 ${FRONTS:+--front-workers $FRONTS} \
    "${MA[@]}" $(clipm $prec) ${EXTRA:-} --quiet --out "$W/e2e" > "$R/e2e-$t.txt" 2>&1
  echo "exit $?"; grep -vE "^\s+(Page|Vol|Invol|Swaps|File|Socket|Signals|Average|Exit|Minor|Major|Percent|System|User|Elapsed)" "$R/e2e-$t.txt" | tail -${LINES_SHOWN:-40}
  cp "$W/e2e/report.json" "$R/report-e2e-$t.json" 2>/dev/null
  ;;
models)
  # The per-model table: slag's ONNX Runtime sessions one model at a time (`slag-bench models` on
  # data/snowmiku-mini's real images: CLIP on graph-mask crops at batch 64, SAM ViT-H per image
  # with 256 prompts), beside torch fp16 in the same call, and ONNX Runtime's per-node profile of
  # each CLIP tower. CLIP variants: f32 (the reference of the cosines), fp16 (the plain export),
  # fp16 + fused (export-models.py --fuse), f32 + fused.
  wheels
  for v in "f32:" "f16:--fp16" "f16fuse:--fp16 --fuse" "f32fuse:--fuse"; do
    d=${v%%:*}
    [ -f "$M/$d/ViT-B-16-random-visual.onnx" ] && continue
    # shellcheck disable=SC2086
    python3 scripts/export-models.py clip --model ViT-B-16 --random ${v#*:} "$M/$d" > "$R/export-clip-$d.json" 2> "$R/export-clip-$d.err" \
      || tail -3 "$R/export-clip-$d.err"
  done
  # SAM ViT-H fp16 with the fp16 decoder (the e2e's), its decoder doing the image's work once
  # per call (f16d: broadcast products; f16e: copied to the prompts) and once per prompt as
  # segment_anything traces it (f16r, the earlier export): same weights.
  vith_f16d
  if [ ! -f "$M/f16r/sam-vit_h-decoder-low-res.onnx" ]; then
    for v in f16r:repeated f16e:expanded; do
      python3 scripts/export-models.py sam --kind vit_h --random --fp16 --fp16-decoder --decoder-only --image-work "${v#*:}" "$M/${v%%:*}" > "$R/export-vith-${v%%:*}.json" 2> "$R/export-vith-${v%%:*}.err" || tail -3 "$R/export-vith-${v%%:*}.err"
    done
    for d in f16r f16e; do python3 scripts/sam-decoder-low-res.py "$M/$d/sam-vit_h-decoder.onnx" "$M/$d/sam-vit_h-decoder-low-res.onnx"; done
    mkdir -p "$M/f16"; ln -sf "$M/f16d/sam-vit_h-encoder.onnx" "$M/f16/sam-vit_h-encoder.onnx"
  fi
  [ "${EXPORT_ONLY:-0}" = 1 ] && exit 0  # the models for e2e, no timing
  CL=(); for d in f32 f16 f16fuse f32fuse; do CL+=(--clip-visual "$M/$d/ViT-B-16-random-visual.onnx"); done
  SA=(); for d in f16r f16d f16e; do SA+=(--sam-encoder "$M/f16d/sam-vit_h-encoder.onnx" --sam-decoder "$M/$d/sam-vit_h-decoder-low-res.onnx"); done
  echo "### slag-bench models: CLIP ViT-B/16 x4, SAM ViT-H fp16 (256 prompts in 1 call, then in 4)"
  "$BB" models --scene-dir data/snowmiku-mini --images 8 "${CL[@]}" "${SA[@]}" --repeats ${REPEATS:-5} > "$R/models.md" 2> "$R/models.jsonl"; echo "exit $?"
  "$BB" models --scene-dir data/snowmiku-mini --images 8 "${SA[@]}" --prompt-batch 64 --repeats ${REPEATS:-5} > "$R/models-pb64.md" 2>> "$R/models.jsonl"; echo "exit $?"
  cat "$R/models.md" "$R/models-pb64.md"
  rm -rf "$W/prof"; mkdir -p "$W/prof"
  SLAG_ORT_PROFILE=$W/prof/p "$BB" models --scene-dir data/snowmiku-mini --images 2 "${CL[@]}" "${SA[@]}" --repeats 3 > /dev/null 2>&1
  python3 scripts/lab/ort-profile-summary.py "$W"/prof/*.json > "$R/profile.md" 2>&1; grep -E "^## |^model runs|by provider" "$R/profile.md"
  SAM_KINDS=vit_h python3 scripts/lab/device_torch_peers.py "$R/torch-peers.json" 2>&1 | tail -14
  ;;
sam)
  # SAM ViT-H fp16 (fp16 decoder, the image's work once per call, cut to its low-res outputs):
  # the plain encoder (f16d) beside the one with fused attention (f16x: export-models.py --fuse),
  # same weights; `slag-bench models` times both pairs and compares the second's masks with the
  # first's; ONNX Runtime's per-node profiles; torch fp16 in the same call, and torch's own CUDA profile of its decoder.
  # EXPORT_ONLY=1: the exports alone (they take most of a call).
  wheels
  vith_f16d
  vith_f16x
  f16m=$M/f16d/sam-vit_h-decoder-low-res-f16m.onnx
  [ "${EXPORT_ONLY:-0}" = 1 ] && exit 0
  SA=(--sam-encoder "$M/f16d/sam-vit_h-encoder.onnx" --sam-decoder "$M/f16d/sam-vit_h-decoder-low-res.onnx"
      --sam-encoder "$M/f16x/sam-vit_h-encoder.onnx" --sam-decoder "$M/f16d/sam-vit_h-decoder-low-res.onnx"
      --sam-encoder "$M/f16x/sam-vit_h-encoder.onnx" --sam-decoder "$f16m")
  echo "### slag-bench models: SAM ViT-H fp16, plain vs fused encoder, f32 vs f16 multimask logits, 256 prompts per call"
  timeout 300 "$BB" models --scene-dir data/snowmiku-mini --images 8 "${SA[@]}" --prompt-batch 256 --repeats ${REPEATS:-5} > "$R/sam-256.md" 2>> "$R/sam.jsonl"; echo "exit $?"
  cat "$R/sam-256.md"
  rm -rf "$W/prof"; mkdir -p "$W/prof"
  SLAG_ORT_PROFILE=$W/prof/p timeout 100 "$BB" models --scene-dir data/snowmiku-mini --images 2 "${SA[@]}" --repeats 3 > /dev/null 2>&1
  python3 scripts/lab/ort-profile-summary.py "$W"/prof/*.json > "$R/profile.md" 2>&1; grep -E "^## |^model runs|by provider" "$R/profile.md"
  SAM_KINDS=vit_h TORCH_PROFILE=1 timeout 120 python3 scripts/lab/device_torch_peers.py "$R/torch-peers.json" > "$R/torch-peers.txt" 2>&1
  grep -vE "^clip|^ *\{|^ *\}|^ *\"" "$R/torch-peers.txt" | cut -c1-160 | head -70
  ;;
graphs)
  # Where each model's run goes on the CUDA provider (scripts/lab/device_ort_cuda_graph.py): host
  # copies, per-node launches (IO binding without and with a captured CUDA graph), the GPU.
  # Needs .pyort/ort.tar.xz (onnxruntime-gpu 1.31.1's Python package without its two large
  # libraries, which come from /root/og). Models: CLIP ViT-B/16 fp16 fused, SAM ViT-H fp16 with
  # the fused encoder and the fp16 decoder cut to low-res outputs (f32; f16 multimask).
  wheels
  if [ ! -d /root/pyort/onnxruntime ]; then
    mkdir -p /root/pyort && tar xJf .pyort/ort.tar.xz -C /root/pyort
    ln -sf /root/og/libonnxruntime_providers_cuda.so /root/og/libonnxruntime.so.1.31.1 /root/pyort/onnxruntime/capi/
  fi
  t0=$(date +%s)
  clip_f16fuse
  X=$M/f16x
  if [ ! -f "$X/sam-vit_h-decoder-low-res-f16m.onnx" ]; then
    python3 scripts/export-models.py sam --kind vit_h --random --fp16 --fp16-decoder --fuse "$X" > "$R/export-vith-fused.json" 2> "$R/export-vith-fused.err" || tail -3 "$R/export-vith-fused.err"
    python3 scripts/sam-decoder-low-res.py "$X/sam-vit_h-decoder.onnx" "$X/sam-vit_h-decoder-low-res.onnx"
    python3 scripts/sam-decoder-low-res.py --f16-multimask "$X/sam-vit_h-decoder.onnx" "$X/sam-vit_h-decoder-low-res-f16m.onnx"
  fi
  echo "exports: $(( $(date +%s) - t0 )) s"
  [ "${EXPORT_ONLY:-0}" = 1 ] && exit 0
  PYTHONPATH=/root/pyort:/root/site timeout 400 python3 scripts/lab/device_ort_cuda_graph.py --repeats ${REPEATS:-10} \
    "$M/f16fuse/ViT-B-16-random-visual.onnx:batch=64" "$X/sam-vit_h-encoder.onnx" \
    "$X/sam-vit_h-decoder-low-res.onnx:num_prompts=256,num_points=2" \
    "$X/sam-vit_h-decoder-low-res-f16m.onnx:num_prompts=256,num_points=2" \
    "$X/sam-vit_h-decoder-low-res-f16m.onnx:num_prompts=128,num_points=2" 2>&1 | grep -v "^\s*$" | tee "$R/graphs.txt" | cut -c1-600
  ;;
clipu8)
  # CLIP ViT-B/16 fp16 fused with f32 pixel_values (normalised on the host) against the same
  # file given byte input (scripts/clip-u8-pixels.py): slag-bench models on real crops, twice,
  # the second call with the towers in the other order.
  wheels
  clip_f16fuse
  F=$M/f16fuse/ViT-B-16-random-visual.onnx; U=$M/f16fuse-u8/ViT-B-16-random-visual.onnx
  for order in "$F $U" "$U $F"; do
    set -- $order
    "$BB" models --scene-dir data/snowmiku-mini --images 8 --clip-visual "$1" --clip-visual "$2" \
      --repeats ${REPEATS:-5} 2>> "$R/clipu8.jsonl"; echo "exit $?"
  done | tee "$R/clipu8.md"
  # torch fp16's ViT-B/16 image tower on the same GPU (inputs already on it), the peer of the table.
  SAM_KINDS="" python3 scripts/lab/device_torch_peers.py "$R/torch-clip.json" 2>&1 | tail -6
  ;;
clipbatch)
  for b in ${BATCHES:-8 16 32 64 128}; do
    "$B" bench --scene-dir /root/scene --ep cuda --every 2 --raster-scale 0.5 --masks graph $(clipm f16) \
      --clip-batch "$b" --quiet --out "$W/cb$b" 2>&1 | sed 's/\x1b\[[0-9;]*m//g' > "$R/clipbatch-$b.txt"
    rc=${PIPESTATUS[0]}
    echo "batch $b exit $rc | $(grep -o 'runs=[0-9]* crops=[0-9]* run_s=[0-9.]*' "$R/clipbatch-$b.txt" | tr '\n' ' ')| $(grep -E '^\| (CLIP crops|total)' "$R/clipbatch-$b.txt" | tr '\n' ' ')"
  done
  ;;
reduce)
  echo "### slag-bench reduce, 2M Gaussians, 250 views x 250k entries, D 512"
  "$BB" reduce --gaussians 2000000 --images 250 --entries-per-image 250000 --dim 512 --repeats 1 \
    > "$R/reduce.md" 2>&1; echo "exit $?"; cat "$R/reduce.md"
  ;;
scaling)
  counts=${2:-1,2}; prec=${PREC:-f16}
  [ -f /root/big/report-synth.json ] || { "$B" synth-scene --gaussians 2M --view-count 250 --width 990 --height 742 --out /root/big > /root/big-synth.json && cp /root/big-synth.json /root/big/report-synth.json; }
  echo "### scaling $counts: e2e scene, ViT-H $prec + CLIP $prec on CUDA"
  "$BB" scaling --scene-dir /root/big --ep cuda --raster-scale 0.5 ${FRONTS:+--front-workers $FRONTS} "${SAMARGS[@]}" $(samm $prec vit_h) $(clipm $prec) \
    --quiet --counts "$counts" --out "$W/scaling" --table "$R/scaling.md" 2>&1 | tail -30
  for g in ${counts//,/ }; do cp "$W/scaling/g$g/report.json" "$R/report-scaling-g$g.json" 2>/dev/null; done; true
  ;;
esac
# At most 8 files come back from a call: pack the results into one archive (one per run, so
# that a second run in the same call neither overwrites nor removes the first one's). A run
# with a TAG is one of several in a call: its files are always packed, so that each archive
# holds its own run's files only.
(cd "$R" && shopt -s nullglob && f=() && for x in *; do [[ $x == *.tgz ]] || f+=("$x"); done &&
  { [ ${#f[@]} -gt 6 ] || { [ -n "${TAG:-}" ] && [ ${#f[@]} -gt 0 ]; }; } &&
  tar czf "results-$mode${TAG:+-$TAG}-$(date +%s).tgz" "${f[@]}" && rm -f -- "${f[@]}")

