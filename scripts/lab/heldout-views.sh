#!/usr/bin/env bash
# View selection on the 2D held-out protocol: hold out every HOLD-th view (index ≡ ⌊HOLD/2⌋ mod
# HOLD; HOLD defaults to 4), then encode the training views several ways with color-sam 16×16
# (pred-IoU 0.8, stability 0.5), color-clip and raster 0.5: all of them, the ones coverage
# selection picks (at most COUNT), and COUNT evenly spaced ones (`--views uniform`, the same
# count); then `eval-colors --held-out` on each. Prints encode wall, views, pass seconds and
# held-out mIoU per run. RUNS picks the runs (default "coverage uniform all"); a run named
# `default` passes no --views flag (the encoder's default selection with its own stopping rule;
# COUNT unused); a run named everyE encodes every E-th view (`--every E`; with the hold-out of
# every 4th view, --every 2 keeps 25 of snowmiku's 97 views, so COUNT=25 gives coverage the same
# count). EXTRA_ENCODE: more encode flags for every run, split on spaces.
# Usage: scripts/lab/heldout-views.sh BINARY SCENE OUTDIR [COUNT]   (needs $SLAG_SHARED, ONNX Runtime)
set -uo pipefail
B=$1; S=$2; R=$3; COUNT=${4:-36}; W=${WORK:-/tmp/slag-views}; HOLD=${HOLD:-4}
F=$SLAG_SHARED/fixtures
read -r -a EXTRA <<< "${EXTRA_ENCODE:-}"
mkdir -p "$R" "$W"
SAM=(--masks sam --sam-encoder $F/sam-amg/color-sam-encoder.onnx --sam-decoder $F/sam-amg/color-sam-decoder.onnx
     --sam-points-per-side 16 --sam-pred-iou-thresh 0.8 --sam-stability-score-thresh 0.5)
CLIP=(--clip-visual $F/clip/color-clip-visual.onnx)
for name in ${RUNS:-coverage uniform all}; do
  case $name in
    all) V=(--views all) ;;
    default) V=() ;;
    coverage) V=(--views coverage --view-count "$COUNT") ;;
    uniform) V=(--views uniform --view-count "$COUNT") ;;
    every*) V=(--every "${name#every}") ;;
    *) echo "unknown run $name (default, coverage, uniform, all, everyE)" >&2; exit 2 ;;
  esac
  t0=$(date +%s.%N)
  "$B" encode --scene-dir "$S" "${SAM[@]}" "${CLIP[@]}" --hold-out-every "$HOLD" ${V[@]+"${V[@]}"} ${EXTRA[@]+"${EXTRA[@]}"} --raster-scale 0.5 --dense \
    --write-segments off --quiet --out "$W/$name" > "$W/$name.log" 2>&1 || { tail -n 5 "$W/$name.log"; exit 1; }
  t1=$(date +%s.%N)
  "$B" eval-colors --held-out --scene-dir "$S" --embeddings "$W/$name/embeddings.safetensors" \
    --color-clip $F/clip > "$R/heldout-views-$name.json" 2> "$R/heldout-views-$name.err" \
    || { tail -n 5 "$R/heldout-views-$name.err"; exit 1; }
  cp "$W/$name/report.json" "$R/report-views-$name.json"
  python3 - "$name" "$t0" "$t1" "$R/heldout-views-$name.json" "$W/$name/report.json" <<'PY'
import json, sys
name, t0, t1 = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
e = json.load(open(sys.argv[4]))["held_out"]; r = json.load(open(sys.argv[5]))
s = r["view_selection"]
print(f"{name:<9} views {r['counts']['views_used']:>3} of {s['candidates']}  encode wall {t1 - t0:6.1f} s "
      f"(report total {r['timings']['total']:.1f} s, pass {s['pass_s']:.1f} s)  observed {r['counts']['observed']}  "
      f"held-out mIoU {e['slag']['miou']:.4f} acc {e['slag']['pixel_accuracy']:.4f}  "
      f"oracle {e['oracle']['miou']:.4f}  held-out views {len(e['held_out_views'])}")
PY
done
