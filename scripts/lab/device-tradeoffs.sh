#!/usr/bin/env bash
# Runs on a GPU machine (x86_64, NVIDIA, no Rust toolchain): `slag-bench tradeoffs` on snowmiku,
# every encode point scored by held-out 2D mIoU (the views no point encodes) with the 3D colour
# mIoU beside it. One device call is limited to 10 minutes, so the plan runs in parts that share
# one work folder (target/slag-bench/snowmiku-device, kept while the machine stays warm):
#   bash scripts/lab/device-tradeoffs.sh graph        # the 14 graph-mask points (baseline, reference, …)
#   bash scripts/lab/device-tradeoffs.sh sam          # color-sam 8/16/32 at every 8th view
#   bash scripts/lab/device-tradeoffs.sh aggregation  # color-sam 16x16 at every 4th view, 4 a_kj rules
#   bash scripts/lab/device-tradeoffs.sh table        # tabulate (encodes nothing) + the plot's CSV
#   bash scripts/lab/device-tradeoffs.sh all          # everything in one call (when time allows)
# Each part writes $OUT/tradeoffs/tradeoffs.{md,csv} of what the work folder holds so far, and
# $OUT/tw.tgz (the points' record/eval/report JSON): on a fresh machine, carry it back as
# .devwork/tw.tgz and the next part continues from it (the baseline's embeddings are then
# re-encoded: pass `graph` again first).
# Expects .devcarry/ (release slag-bench, scene/ = snowmiku images + COLMAP + a geometry+DC .ply,
# shared/fixtures/{sam-amg,clip}) and .gl/ (Vulkan loader debs), as scripts/lab/device-heldout.sh.
set -uo pipefail
# shellcheck source=scripts/lab/device-snowmiku-env.sh
. scripts/lab/device-snowmiku-env.sh
BB=.devcarry/slag-bench
TW=target/slag-bench/snowmiku-device; mkdir -p "$TW"
[ -f .devwork/tw.tgz ] && [ ! -f "$TW/.restored" ] && tar xzf .devwork/tw.tgz -C "$TW" && touch "$TW/.restored"
GRAPH=graph-e4-r0.5-kall,graph-e1-r0.5-kall,graph-e4-r0.5-kall-mix,graph-e20-r0.5-kall,graph-e10-r0.5-kall,graph-e5-r0.5-kall,graph-e2-r0.5-kall,graph-e4-r0.25-kall,graph-e4-r0.5-k1,graph-e4-r0.5-k8,graph-e8-r0.5-kall,graph-e4-r1-kall,graph-e4-r0.5-k2,graph-e4-r0.5-k4
SAMS=sam8-e8-r0.5-kall,sam16-e8-r0.5-kall,sam32-e8-r0.5-kall
AGG=sam16-e4-r0.5-kall,sam16-e4-r0.5-kall-area,sam16-e4-r0.5-kall-finest,sam16-e4-r0.5-kall-finest-area
case "${1:-all}" in
  graph) IDS=$GRAPH;; sam) IDS=$SAMS;; aggregation) IDS=$AGG;; table) IDS=;;
  all) IDS=$GRAPH,$SAMS,$AGG;;
  *) echo "unknown part ${1:-}: graph, sam, aggregation, table or all"; exit 2;;
esac
# Start from the committed document so that its hand-written text below the recommendations
# marker is kept (slag-bench replaces only the generated tables).
mkdir -p "$R/tradeoffs"; cp docs/results/tradeoffs.md "$R/tradeoffs/tradeoffs.md"
timeout "${TW_TIMEOUT:-560}" "$BB" tradeoffs --scene-dir "$S" --fixtures "$F" --work "$TW" \
  --out "$R/tradeoffs" --front-workers 8 --cached-only ${IDS:+--encode "$IDS"} \
  --note "$(nvidia-smi --query-gpu=name --format=csv,noheader | head -1), $(nproc) cores, GPU raster (wgpu/Vulkan), ORT CPU EP" \
  2>&1 | grep -v XDG_RUNTIME | tee "$R/tradeoffs.log"
(cd "$TW" && find . \( -name record.json -o -name eval.json -o -name report.json \) -print0 \
  | tar czf "$R/tw.tgz" --null -T -)
exit 0
