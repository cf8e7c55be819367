#!/usr/bin/env bash
# How many views the default view selection keeps on the ring of the GPU workload: the synthetic
# terrain of N Gaussians (2M) and V views (250) at 990×742 (`synth-scene`), encoded with the
# default views (coverage, its own stopping rule), graph masks and color-clip (the count does not
# depend on the masks or the models: the pass and the greedy see the geometry alone), raster 0.5,
# segments off. Prints the views kept of the candidates, why the choice ended, the pass's
# seconds, and the count the default rule gives from the recorded greedy order (a check).
# EXTRA="ARGS" adds encode arguments (e.g. "--view-coverage-min-gain 0.05"); SYNTH="ARGS" adds
# synth-scene arguments (e.g. "--width 313 --height 235" with N 200K: the same pixels per
# Gaussian at a tenth of the work); the scene is written once into WORK (default /tmp/slag-ring).
# Usage: scripts/lab/ring-views.sh BINARY CLIP_VISUAL.onnx [N] [V]   (needs ONNX Runtime)
set -euo pipefail
B=$1; CLIP=$2; N=${3:-2M}; V=${4:-250}; W=${WORK:-/tmp/slag-ring}
TAG="$N-$V${SYNTH:+-$(echo "$SYNTH" | tr -c 'A-Za-z0-9.\n-' _)}"
S="$W/ring-$TAG"; O="$W/out-$TAG"
# shellcheck disable=SC2086
[ -f "$S/point_cloud.ply" ] || "$B" synth-scene --gaussians "$N" --view-count "$V" ${SYNTH:-} --out "$S"
rm -rf "$O"
# shellcheck disable=SC2086
"$B" encode --scene-dir "$S" --masks graph --clip-visual "$CLIP" --raster-scale 0.5 --write-segments off \
  --quiet --out "$O" ${EXTRA:-}
python3 - "$O/report.json" <<'PY'
import json, sys
r = json.load(open(sys.argv[1])); s = r["view_selection"]; c = s.get("coverage") or {}
kept = r["counts"]["views_used"]
print(f"views kept {kept} of {s['candidates']} ({100 * kept / s['candidates']:.1f} %), mode {s['mode']}, "
      f"stop {c.get('stop')}, pass {s['pass_s']:.1f} s, encode total {r['timings']['total']:.1f} s")
if c:
    order, g = c["order"], c["rule"]["min_gain"]
    first = order[0]["gain_px"] if order else 0.0
    by_rule = next((i for i, st in enumerate(order) if st["gain_px"] < g * first), len(order))
    print(f"the rule from the recorded order: {by_rule} views (min_gain {g}, first view {first:.0f} px); "
          f"pairs {c['pairs_chosen']} of {c['pairs_wanted']}, footprint {c['pairs_chosen_px']:.0f} of "
          f"{c['pairs_wanted_px']:.0f} px; greedy order {len(order)} views")
PY
