#!/usr/bin/env bash
# Encode outputs, byte for byte: encodes the embedded scene (data/snowmiku-mini) with the stand-in
# models (color-sam, color-clip from $SLAG_SHARED/fixtures) in the runs below and writes the sha256
# of every output file except report.json (it carries timings) to OUT/sha256sums. A refactor that
# changes no behaviour leaves that file identical:
#
#   bash scripts/lab/encode-identity.sh /tmp/before     # on the old commit
#   bash scripts/lab/encode-identity.sh /tmp/after      # on the new one
#   diff /tmp/before/sha256sums /tmp/after/sha256sums && echo identical
#
# Every run has one front worker: with several, the images reach the contribution store in the
# order the workers finish them, which changes the order of the mixture's codebook rows (and
# may change the last bits of the f64 sums), so two runs of the same binary differ there.
#
# The runs:
#   demo     the demo's encode (scripts/demo.sh) with one front worker: color-sam masks, GPU
#            rasterizer (lavapipe without a GPU), the default mixture (4 slots) and segments
#   levels   color-sam masks, --levels (one file per SAM level), CPU rasterizer, f32, --overlap all,
#            --mask-weighting area, mixture with 8 slots, no segments
#   cluster  `encode-cluster` with one process (graph masks, CPU rasterizer, f32; one process so
#            that the order of the reduction's sums is fixed)
# BIN (default target/debug/slag-encoder, built here when absent) picks the binary.
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT=${1:?usage: encode-identity.sh OUT_DIR}
. scripts/setup.sh
F=$SLAG_SHARED/fixtures
SCENE=data/snowmiku-mini
BIN=${BIN:-target/debug/slag-encoder}
if [ ! -x "$BIN" ]; then
  cargo build --workspace --locked --bin slag-encoder
fi
mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)
SAM=(--masks sam --sam-encoder "$F/sam-amg/color-sam-encoder.onnx"
  --sam-decoder "$F/sam-amg/color-sam-decoder.onnx" --sam-points-per-side 16
  --sam-pred-iou-thresh 0.8 --sam-stability-score-thresh 0.5)
CLIP=(--clip-visual "$F/clip/color-clip-visual.onnx")

rm -rf "$OUT/demo" "$OUT/levels" "$OUT/cluster"
"$BIN" encode --scene-dir "$SCENE" "${SAM[@]}" "${CLIP[@]}" --front-workers 1 --quiet --out "$OUT/demo"
"$BIN" encode --scene-dir "$SCENE" "${SAM[@]}" "${CLIP[@]}" --front-workers 1 --quiet --levels --rasterizer cpu \
  --precision f32 --overlap all --mask-weighting area --mixture-keep 8 --write-segments off \
  --every 2 --out "$OUT/levels"
PORT=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')
echo "127.0.0.1:$PORT" >"$OUT/hosts.txt"
"$BIN" encode-cluster --process 0 --hosts "$OUT/hosts.txt" --scene-dir "$SCENE" --masks graph \
  "${CLIP[@]}" --rasterizer cpu --precision f32 --every 2 --quiet --out "$OUT/cluster"

(cd "$OUT" && find demo levels cluster -type f ! -name report.json | LC_ALL=C sort \
  | xargs sha256sum) >"$OUT/sha256sums"
# The report's keys (not its values: timings differ run to run) must match too.
python3 - "$OUT" >"$OUT/report-keys" <<'PY'
import json, sys
def keys(v, p=""):
    if isinstance(v, dict):
        for k in sorted(v):
            yield from keys(v[k], f"{p}.{k}")
    elif isinstance(v, list):
        yield f"{p}[]"
        for x in v[:1]:
            yield from keys(x, f"{p}[]")
    else:
        yield p
for run in ("demo", "levels", "cluster"):
    for k in sorted(set(keys(json.load(open(f"{sys.argv[1]}/{run}/report.json"))))):
        print(run, k)
PY
cat "$OUT/sha256sums"
echo "encode-identity: wrote $OUT/sha256sums and $OUT/report-keys" >&2
