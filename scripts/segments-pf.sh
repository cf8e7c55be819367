#!/usr/bin/env bash
# Segments and prediction filtering on the 2D held-out protocol, one encode for every
# segmentation: encode SCENE with color-sam (16×16, pred-IoU 0.8, stability 0.5) and color-clip at
# --every N, raster 0.5 (it writes segments.safetensors and mask-record.safetensors), redo the
# segments from the geometry alone (`slag-encoder segment --geometry-only`, the segments before
# the mask term) and with the mask term, measure both (purity, sizes), then one
# `eval-colors --held-out --prediction-filtering` pass scores slag with and without PF over both.
# Usage: scripts/segments-pf.sh BINARY SCENE OUTDIR [EVERY]   (needs $SLAG_SHARED, ONNX Runtime)
# SKIP_ENCODE=1 reuses OUTDIR/enc; SKIP_HELDOUT=1 stops after the 3D measures.
set -euo pipefail
B=$1; S=$2; R=$3; N=${4:-4}
F=$SLAG_SHARED/fixtures
E=$R/enc
mkdir -p "$R/geometric"
if [ -z "${SKIP_ENCODE:-}" ]; then
  t0=$(date +%s)
  "$B" encode --scene "$S" --masks sam --sam-encoder $F/sam-amg/color-sam-encoder.onnx \
    --sam-decoder $F/sam-amg/color-sam-decoder.onnx --sam-points-per-side 16 \
    --sam-pred-iou-thresh 0.8 --sam-stability-score-thresh 0.5 \
    --clip-visual $F/clip/color-clip-visual.onnx --every "$N" --raster-scale 0.5 --quiet \
    --out "$E" > "$R/encode.log" 2>&1
  echo "encode $(( $(date +%s) - t0 )) s"
fi
"$B" segment --scene "$S" --geometry-only --out "$R/geometric/segments.safetensors" 2> "$R/geometric.log"
"$B" segment --scene "$S" --out "$E/segments-masks.safetensors" 2> "$R/masks.log"
"$B" eval-colors --scene "$S" --embeddings "$E/embeddings.safetensors" --color-clip $F/clip --pf \
  --segments "$R/geometric/segments.safetensors" --more-segments "$E/segments-masks.safetensors" \
  > "$R/pf-3d.json"
[ -n "${SKIP_HELDOUT:-}" ] && exit 0
"$B" eval-colors --held-out --scene "$S" --embeddings "$E/embeddings.safetensors" --color-clip $F/clip \
  --pf --segments "$R/geometric/segments.safetensors" --more-segments "$E/segments-masks.safetensors" \
  > "$R/heldout.json"
python3 - "$R/heldout.json" <<'PY'
import json, sys
o = json.load(open(sys.argv[1])); e = o["held_out"]
print(f"every {e['every']}: slag {e['slag']['miou']:.4f}  oracle {e['oracle']['miou']:.4f}  majority {e['majority']['miou']:.4f}")
for v in e["variants"]: print(f"  {v['name']:<48} {v['score']['miou']:.4f}")
for q in o.get("segment_quality", []): print(f"  {q['source']}: purity {q['purity']['purity']:.4f}, {q['sizes']['segments']} segments")
PY
