#!/usr/bin/env bash
# Runs on a GPU machine (x86_64, NVIDIA, no Rust toolchain): scripts/lab/segments-pf.sh on snowmiku at
# --every 4 and --every 5 (one encode per split, five segmentations, the 3D measures and one
# held-out pass with and without PF each); OUT/table.md holds the tables, OUT/e4 and OUT/e5 the
# JSON and logs (the encodes' large files are left in /tmp). Expects .devcarry/ (release
# slag-encoder, scene/ = snowmiku images + COLMAP + the .ply, shared/fixtures/{sam-amg,clip}) and
# .gl/ (Vulkan loader debs), as scripts/lab/device-heldout.sh.
#   EVERYS="4 5" (default) names the splits.
set -uo pipefail
# shellcheck source=scripts/lab/device-snowmiku-env.sh
. scripts/lab/device-snowmiku-env.sh
W2=$W/segments-pf; mkdir -p "$W2"
bash scripts/lab/segments-pf.sh "$B" "$S" "$W2" ${EVERYS:-4 5}
rc=$?
for d in "$W2"/e*; do
  n=$(basename "$d"); mkdir -p "$R/$n"
  cp "$d"/*.json "$d"/*.log "$R/$n/" 2>/dev/null
  cp "$d"/enc/report.json "$R/$n/report.json" 2>/dev/null
  mkdir -p "$R/$n/seg"; cp "$d"/seg/*.json "$R/$n/seg/" 2>/dev/null
done
cp "$W2/table.md" "$R/table.md" 2>/dev/null
exit $rc
