#!/usr/bin/env bash
# Runs on a GPU machine of two GPUs (x86_64, NVIDIA, torch, no Rust toolchain); NOT part of CI.
# Two slag-encoder builds against each other on the 2M / 250-view e2e workload of
# device-gpu-models.sh (SAM ViT-H fp16 timing model, color-sam masks downstream, CLIP ViT-B/16
# fp16 fused taking bytes, every view), on one and on two GPUs, in one call so that every run
# shares the machine. Needs what device-gpu-models.sh e2e needs (/root/og assembled, .whl, .gl,
# .devcarry/sam-amg), and .devcarry/slag-encoder.zst ("new") and .devcarry/slag-encoder-old.zst
# ("old"), zstd-compressed release builds.
# Usage (source it, then one line per run):
#   . scripts/lab/device-gpus-ab.sh
#   one new-g1 new 1; one new-g2 new 2; one old-g2 old 2; one old-g1 old 1
#   summary > $OUT/summary.txt
# A variable set before `one` reaches that run alone, e.g. `ENCDIR=f16x one fused-g1 new 1`: the
# timing model's encoder with fused attention (export-models.py --fuse), exported on first use;
# `FRONTS=6 one f6 new 1`: six fronts per GPU. `UTIL=1 one ...` also samples each GPU's
# utilization every 200 ms (nvidia-smi) into /root/ab/util-TAG.csv, and prints it over the
# fronts' window (scripts/lab/gpu-util.py).
# Each run's output, report, RSS samples and debug lines go to /root/ab/TAG*; `pack` puts them
# in $OUT/ab.tar.gz (the device returns few files).
export RUST_LOG="info,slag_encoder::pipeline=debug,slag_encoder::memory=debug"
export MASKMODEL=$PWD/.devcarry/sam-amg LOWRES=1 PREC=f16 DECDIR=f16d ENCDIR=f16d F16M=1 CLIPDIR=f16fuse-u8 LINES_SHOWN=0
mkdir -p /root/ab
one() { # TAG BINARY(new|old) GPUS
  local bin=/root/bin/slag-encoder sampler=; [ "$2" = old ] && bin=/root/bin/slag-encoder-old
  # The sampler writes beside /root/ab: device-gpu-models.sh bundles and removes what is in it.
  if [ "${UTIL:-0}" = 1 ]; then
    nvidia-smi --query-gpu=timestamp,index,utilization.gpu,utilization.memory,power.draw,clocks.sm \
      --format=csv,noheader -lms 200 > "/root/util-$1.csv" & sampler=$!
  fi
  SLAG_ENCODER=$bin TAG=$1 EXTRA="--views all --gpus $3" OUT=/root/ab \
    bash scripts/lab/device-gpu-models.sh e2e 2M 250 > "/root/ab/$1.out" 2>&1
  [ -n "$sampler" ] && { kill "$sampler"; mv "/root/util-$1.csv" /root/ab/; }
  # device-gpu-models.sh bundles a run's files into results-e2e-TAG-*.tgz: unpack the newest.
  tar xzf "$(ls -t /root/ab/results-e2e-"$1"-*.tgz | head -1)" -C /root/ab e2e-f16-"$1".txt
  local f=/root/ab/e2e-f16-$1.txt
  echo "== $1 ($2, $3 GPUs)"
  grep -E "^\| total|^\| reduce|Elapsed|Maximum resident|rss-timeline: wall" "$f"
  grep -E "^\| front-" "$f" | awk -F'|' '{print "  " $2 $4}' | tr '\n' ' '; echo
  grep -E "scene loaded|workers done|handed over|exchanged|let go|device reduction tiles|geometric segments written" "$f" | cut -c12-27,50-230
  [ -n "$sampler" ] && python3 scripts/lab/gpu-util.py "/root/ab/util-$1.csv" "$f"
  return 0
}
summary() { for f in /root/ab/*.out; do echo "== $f"; tail -3 "$f"; done; }
pack() { tar -czf "$OUT/ab.tar.gz" -C /root ab; }
