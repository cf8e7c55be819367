#!/usr/bin/env bash
# Runs on the GPU machine (x86_64, NVIDIA, no Rust toolchain); NOT part of CI. Two slag-encoder
# builds against each other on the 30M synthetic terrain, in one call, so that both run on the
# same machine: .devcarry/slag-encoder ("new") and .devcarry/slag-encoder-old ("old"), each run
# by `device-scaling.sh reduce` (GNU time, GPU memory, RSS timeline) with the debug lines of the
# reduction's tiles, the segments and resident memory per stage.
# Usage (source it, then one line per run):
#   . scripts/lab/device-ab.sh
#   one new16a new 16; one old16a old 16; one new16b new 16; one old16b old 16
#   one new128 new 128 "--views all --device-reduce-memory-mb 65536"
# Each run leaves $OUT/TAG.txt (the script's output), $OUT/TAG-log.txt (the debug lines) and
# $OUT/TAG/ (reduce.txt, the RSS timeline).
export RUST_LOG="info,slag_encoder::segments=debug,slag_encoder::pipeline=debug,slag_encoder::memory=debug"
cp .devcarry/slag-encoder /tmp/bin-new; cp .devcarry/slag-encoder-old /tmp/bin-old
one() { # TAG BINARY(new|old) VIEWS [bench view flags; default --views all]
  cp "/tmp/bin-$2" .devcarry/slag-encoder
  VIEWS="${4:---views all}" OUT=$OUT/$1 bash scripts/lab/device-scaling.sh reduce 30M "$3" default > "$OUT/$1.txt" 2>&1
  grep -h "resident memory\|device reduction\|neighbour search\|minimum-size pass\|tile wave" /tmp/slag-work/run-1.txt | cut -c1-260 > "$OUT/$1-log.txt"
  echo "== $1"; head -3 "$OUT/$1/reduce.txt"
}
