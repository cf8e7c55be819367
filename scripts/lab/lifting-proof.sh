#!/usr/bin/env bash
# The GPU label sums at scale, on whatever Vulkan adapter wgpu picks (lavapipe on a machine
# without a GPU): a 2M-Gaussian, 4-view synthetic terrain (990x742 images, raster 0.5) encoded
# with color-sam masks (16x16 points, pred-IoU 0.8, stability 0.5) must take the GPU path
# (`counts.device_sum_views` of report.json) on every view. Prints the masks per image and the
# raster phases, and exits non-zero otherwise.
#   bash scripts/lab/lifting-proof.sh [WORK_DIR]      # SLAG_ENCODER=path/to/slag-encoder to pick a build
set -euo pipefail
cd "$(dirname "$0")/../.."
# shellcheck disable=SC1091
. scripts/setup.sh
B=${SLAG_ENCODER:-target/debug/slag-encoder}
W=${1:-/tmp/slag-lifting-proof}
F=$SLAG_SHARED/fixtures
mkdir -p "$W"
t0=$(date +%s)
[ -f "$W/scene/point_cloud.ply" ] ||
  "$B" synth-scene --gaussians 2M --view-count 4 --width 990 --height 742 --out "$W/scene" > "$W/synth.json"
t1=$(date +%s)
"$B" encode --scene-dir "$W/scene" --raster-scale 0.5 --rasterizer gpu --masks sam \
  --sam-encoder "$F/sam-amg/color-sam-encoder.onnx" --sam-decoder "$F/sam-amg/color-sam-decoder.onnx" \
  --sam-points-per-side 16 --sam-pred-iou-thresh 0.8 --sam-stability-score-thresh 0.5 \
  --clip-visual "$F/clip/color-clip-visual.onnx" --quiet --out "$W/out"
t2=$(date +%s)
echo "synth-scene $((t1 - t0)) s, encode $((t2 - t1)) s"
python3 - "$W/out/report.json" <<'PY'
import json, sys
r = json.load(open(sys.argv[1]))
c = r["counts"]
print(f"views {c['views_used']}, masks/image {c['masks'] / max(1, c['views_used']):.1f}, "
      f"device_sum_views {c['device_sum_views']}, peak RSS {c.get('peak_rss_bytes', 0) / 2**30:.2f} GiB")
for w in r.get("workers", []):
    if w.get("raster_phases_ms"):
        print(w["name"], {k: round(v / max(1, w["images"]), 1) for k, v in w["raster_phases_ms"].items()}, "ms/view")
sys.exit(0 if c["device_sum_views"] == c["views_used"] else 1)
PY
