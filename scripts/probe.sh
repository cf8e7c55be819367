#!/usr/bin/env bash
# Hostile-client probe of the two servers on loopback (127.0.0.0/8 only), bounded in time and count:
# stalled sockets under `ulimit -n 1024` (the well-behaved client on a second loopback address,
# 127.0.0.2), stalled request bodies (/health latency from another address; every one closed by
# the body timeout), the 3.6 KB request that asks for 640,000 matches, slow readers on both
# servers, error bodies (405/413/414/431/416), the bearer scheme's case, two Authorization
# headers, a shard-server URL with a password (refused; not in /stats or the store), a `text`
# that is not a JSON string, query strings that are not UTF-8, blank tokens, and the store's
# damage cases (flipped bytes, truncated, appended, swapped shard files, a
# directory in place of one: one `slag-edge fetch` must repair, `slag-edge check` must tell), and the store's
# integrity (reload racing fetch serves only committed states; a manifest listing a tile twice is
# refused; a FIFO, a link to /dev/zero, a dangling link in a shard's place: check, query and
# serve answer, RSS stays bounded, one fetch repairs).
# Prints `case | expected | observed | pass/fail` with RSS figures; exits 1 if a case fails.
#
#   bash scripts/probe.sh             # release binaries (built here), 60,000 Gaussians, 2,000 stalls
#   bash scripts/probe.sh --short     # 8,000 Gaussians, 300 stalls, store cases (about 75 s; CI)
#   bash scripts/probe.sh --debug     # take target/debug binaries (built by cargo test) instead
#   bash scripts/probe.sh --skip-store   # leave out the store damage cases
#   SLAG_PROBE_PRELOAD=/usr/lib/x86_64-linux-gnu/libjemalloc.so.2 bash scripts/probe.sh --rss-only
#                                     # memory cases only, the edge under another allocator (for
#                                     # a binary on the system allocator: slag-edge's own Rust heap
#                                     # is jemalloc, which LD_PRELOAD does not replace)
#   SLAG_EDGE_BIN=... SLAG_SHARDS_BIN=... bash scripts/probe.sh   # probe other binaries
set -euo pipefail
cd "$(dirname "$0")/.."
short=0; profile=release; store=1; rss_only=0
for a in "$@"; do
  case "$a" in
    --short) short=1 ;;
    --debug) profile=debug ;;
    --skip-store) store=0 ;;
    --rss-only) rss_only=1 ;;
    *) echo "probe: unknown argument $a" >&2; exit 2 ;;
  esac
done
. scripts/setup.sh >/dev/null
T=${CARGO_TARGET_DIR:-target}
EDGE=${SLAG_EDGE_BIN:-$T/$profile/slag-edge}
SHARDS=${SLAG_SHARDS_BIN:-$T/$profile/slag-shards}
if [ -z "${SLAG_EDGE_BIN:-}" ] && [ "$profile" = release ]; then
  cargo build --release --locked -p slag-edge -p slag-shards
fi
[ -x "$EDGE" ] && [ -x "$SHARDS" ] || { echo "probe: no binaries at $EDGE, $SHARDS" >&2; exit 2; }
F=$SLAG_SHARED/fixtures/clip
W=$(mktemp -d)
trap 'rm -rf "$W"' EXIT
if [ "$short" = 1 ]; then N=8000; PER=1000; else N=60000; PER=7500; fi
"$SHARDS" partition --synthetic "$N:512" --shard-store "$W/shards" --scene probe --dtype f16 \
  --max-per-shard "$PER" >/dev/null
args=(--edge "$EDGE" --shards "$SHARDS" --work "$W" --text-model "$F/color-clip-textual.onnx"
  --tokenizer "$F/clip-tokenizer.json")
[ "$short" = 1 ] && args+=(--short)
[ "$store" = 0 ] && args+=(--skip-store)
[ "$rss_only" = 1 ] && args+=(--rss-only)
echo "probe: $EDGE, $SHARDS; $(nproc) cores; $(date -u +%FT%TZ); probe at commit $(git rev-parse --short HEAD 2>/dev/null || echo '?')"
timeout 900 python3 scripts/probe.py "${args[@]}"
