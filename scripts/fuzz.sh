#!/usr/bin/env bash
# Runs every libFuzzer target of fuzz/ for N seconds each (default 600), two at a time.
# NOT part of CI. Needs cargo-fuzz (`cargo install cargo-fuzz`); the stable toolchain is used with
# RUSTC_BOOTSTRAP=1 (cargo-fuzz passes nightly-only -Z flags). Sanitizer: none by default (the
# parsers are safe Rust; `unsafe_code` is denied workspace-wide), override with SANITIZER=address.
#
#   scripts/fuzz.sh [SECONDS] [TARGET...]
#
# Corpora grow in fuzz/corpus/<target> (seeds are committed, growth is not: see fuzz/.gitignore);
# crashes land in fuzz/artifacts/<target>/ and make the script exit non-zero. Logs: fuzz/logs/.
set -euo pipefail
cd "$(dirname "$0")/../fuzz"
secs=${1:-600}
shift || true
targets=("$@")
if [ ${#targets[@]} -eq 0 ]; then
  targets=(ply colmap transforms_json shard_decode mixture_decode query_params manifest)
fi
export RUSTC_BOOTSTRAP=1
san=${SANITIZER:-none}
cargo fuzz build -s "$san"
mkdir -p logs
run() {
  local t=$1
  mkdir -p "corpus/$t" "artifacts/$t"
  # A scratch corpus so the committed seeds stay small; -max_len 65536 keeps inputs file-sized.
  local work="logs/corpus-$t"
  mkdir -p "$work"
  cargo fuzz run -s "$san" "$t" "$work" "corpus/$t" -- -max_total_time="$secs" -max_len=65536 \
    -print_final_stats=1 >"logs/$t.log" 2>&1
}
status=0
pids=()
for t in "${targets[@]}"; do
  run "$t" &
  pids+=($!)
  if [ ${#pids[@]} -ge 2 ]; then
    wait "${pids[0]}" || status=1
    pids=("${pids[@]:1}")
  fi
done
for p in "${pids[@]}"; do wait "$p" || status=1; done
for t in "${targets[@]}"; do
  printf '%-16s ' "$t"
  { grep -E '^(Done|#[0-9]+.*cov: )' "logs/$t.log" || true; } | tail -2 | tr '\n' ' '
  echo
done
exit $status
