#!/usr/bin/env bash
# encode-cluster against encode on one machine, on loopback: the same arguments as the loopback
# test (cli/tests/encode_cluster.rs: data/snowmiku-mini, every 2nd view then the default views,
# graph masks, color-clip, CPU rasterizer at raster scale 0.25, --reduce host, f32, one thread a
# process), a one-process `encode` then 3 processes of `encode-cluster` with a shared secret,
# ROUNDS times; prints each run's wall and whether every output file but the report is
# byte-identical (cmp). With CHECKPOINT_EVERY=SECONDS the cluster runs with --checkpoint-every
# SECONDS (0.001: a checkpoint after every view a partition takes in) and each round also prints
# the checkpoints each partition wrote, their seconds and the largest one's bytes (report.json).
# With SLOW_MS=MS process 1 waits MS milliseconds before each view it maps (the test-only
# SLAG_TEST_MAP_DELAY_MS: a slow process) and each round prints the views each process mapped.
# NOT part of CI.
#   [CHECKPOINT_EVERY=S] [SLOW_MS=MS] scripts/lab/cluster-loopback.sh [SLAG_ENCODER] [ROUNDS]   (repo root)
set -uo pipefail
B=${1:-target/debug/slag-encoder}; rounds=${2:-2}
shared=${SLAG_SHARED:-../shared}
w=$(mktemp -d); trap 'rm -rf "$w"' EXIT
# shellcheck source=cluster-common.sh
source "$(dirname "${BASH_SOURCE[0]}")/cluster-common.sh"
cluster_secret "$w"
args=(--scene-dir data/snowmiku-mini --masks graph --clip-visual "$shared/fixtures/clip/color-clip-visual.onnx"
  --every 2 --reduce host --raster-scale 0.25 --rasterizer cpu --precision f32 --threads 1 --quiet)
now() { date +%s.%N; }
for r in $(seq "$rounds"); do
  t0=$(now); "$B" encode "${args[@]}" --out "$w/one-$r" > "$w/one-$r.log" 2>&1 || { echo "encode failed"; tail -5 "$w/one-$r.log"; exit 1; }
  t1=$(now)
  cluster_hosts "$w" 3
  t2=$(now); pids=()
  ckpt=(); [ -n "${CHECKPOINT_EVERY:-}" ] && ckpt=(--checkpoint-every "$CHECKPOINT_EVERY")
  for i in 0 1 2; do
    slow=(); [ "$i" = 1 ] && [ -n "${SLOW_MS:-}" ] && slow=(env SLAG_TEST_MAP_DELAY_MS="$SLOW_MS")
    "${slow[@]}" "$B" encode-cluster --process $i --hosts "$w/hosts" --cluster-secret-file "$w/secret" "${args[@]}" "${ckpt[@]}" \
      --out "$w/cluster-$r" > "$w/cluster-$r-$i.log" 2>&1 & pids+=($!)
  done
  rc=0; for p in "${pids[@]}"; do wait "$p" || rc=$?; done
  t3=$(now)
  [ $rc = 0 ] || { echo "encode-cluster failed ($rc)"; tail -5 "$w"/cluster-$r-*.log; exit 1; }
  same=yes
  for f in "$w/one-$r"/*; do
    n=$(basename "$f"); [ "$n" = report.json ] && continue
    cmp -s "$f" "$w/cluster-$r/$n" || { same="no ($n differs)"; break; }
  done
  printf 'round %s: encode %.1f s, encode-cluster (3 processes) %.1f s; files but the report byte-identical: %s (%s)\n' \
    "$r" "$(echo "$t1 - $t0" | bc)" "$(echo "$t3 - $t2" | bc)" "$same" "$(cd "$w/one-$r" && ls | tr '\n' ' ')"
  [ -n "${SLOW_MS:-}" ] && python3 -c 'import json,sys
for w in json.load(open(sys.argv[1]))["outputs"]["cluster"]["workers"]:
    print("  process %d: %d images %s, map wall %.1f s" % (w["worker"], w["images"], w.get("views", "?"), w["map_wall_s"]))' "$w/cluster-$r/report.json"
  [ -n "${CHECKPOINT_EVERY:-}" ] && python3 -c 'import json,sys
c=json.load(open(sys.argv[1]))["outputs"]["cluster"]
for p in c["partitions"]:
    print("  partition %d: %d checkpoints, %.4f s in all, largest %d bytes" % (p["partition"], p["checkpoints"], p["checkpoint_s"], p["checkpoint_bytes"]))' "$w/cluster-$r/report.json"
done
