#!/usr/bin/env bash
# Load test of `slag-edge serve` on loopback (robustness under load): a synthetic scene of
# N Gaussians (default 1,000,000 × 512, f16 shards) is partitioned, served by `slag-encoder serve`,
# fetched by `slag-edge fetch`, then `slag-edge serve` takes `wrk` load with a mix of valid and
# invalid queries (scripts/load/mix.lua). Prints requests/s, p50/p90/p99 latency, status classes,
# and the server's peak memory (VmHWM) before and after the load; fails if the server died, any
# 5xx was answered, or no invalid query got a 4xx.
#   N=1000000 DTYPE=f16 DURATION=30 CONNECTIONS=8 bash scripts/load-test.sh
set -euo pipefail
cd "$(dirname "$0")/.."
N=${N:-1000000}
DTYPE=${DTYPE:-f16}
DURATION=${DURATION:-30}
CONNECTIONS=${CONNECTIONS:-8}
. scripts/setup.sh
command -v wrk >/dev/null || { apt-get install -y -qq wrk >/dev/null 2>&1 || sudo apt-get install -y -qq wrk; }
cargo build --release --locked --bin slag-encoder --bin slag-edge
ENC=target/release/slag-encoder
EDGE=target/release/slag-edge
F=$SLAG_SHARED/fixtures/clip
W=$(mktemp -d)
pids=()
cleanup() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done; rm -rf "$W"; }
trap cleanup EXIT
$ENC partition --synthetic "$N:512" --shard-store "$W/shards" --scene synth --dtype "$DTYPE" --max-per-shard 65536
$ENC serve --shard-store "$W/shards" --listen 127.0.0.1:18090 >/dev/null &
pids+=($!)
for _ in $(seq 50); do curl -fs http://127.0.0.1:18090/v1/scenes >/dev/null && break; sleep 0.2; done
$EDGE fetch --from http://127.0.0.1:18090 --scene synth --center 1000,1000 --radius 100000 --store "$W/edge"
$EDGE serve --store "$W/edge" --scene synth --listen 127.0.0.1:18080 \
  --clip-textual "$F/color-clip-textual.onnx" --tokenizer "$F/clip-tokenizer.json" 2>"$W/serve.log" &
SERVER=$!
pids+=($SERVER)
for _ in $(seq 300); do curl -fs http://127.0.0.1:18080/health >/dev/null && break; sleep 0.2; done
curl -fs http://127.0.0.1:18080/health >/dev/null || { cat "$W/serve.log"; exit 1; }
hwm() { awk '/VmHWM/ {print $2 / 1024 " MiB"}' "/proc/$SERVER/status"; }
rss() { awk '/VmRSS/ {print $2 / 1024 " MiB"}' "/proc/$SERVER/status"; }
echo "loaded: $(curl -fs http://127.0.0.1:18080/stats | tr -d '\n' | head -c 600)"
echo "server memory before load: peak $(hwm), resident $(rss)"
out=$(wrk -t2 -c"$CONNECTIONS" -d"${DURATION}s" --timeout 30s --latency -s scripts/load/mix.lua \
  http://127.0.0.1:18080)
echo "$out"
echo "server memory after load: peak $(hwm), resident $(rss)"
curl -fs http://127.0.0.1:18080/health >/dev/null || { echo "server is down" >&2; exit 1; }
echo "$out" | grep -q ' 5xx=0 ' || { echo "5xx answers under load" >&2; exit 1; }
echo "$out" | grep -Eq ' 4xx=[1-9]' || { echo "no 4xx for the invalid queries" >&2; exit 1; }
echo "load test: server up, no 5xx"
