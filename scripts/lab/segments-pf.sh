#!/usr/bin/env bash
# Segments and prediction filtering (PF) on the 2D held-out protocol, for one or more splits of
# the views, in one command. Per split (--every N): encode SCENE once with color-sam (16×16,
# pred-IoU 0.8, stability 0.5) and color-clip at --every N, raster 0.5 (the encode writes
# segments.safetensors and mask-record.safetensors); redo the segments of that encode with
# `slag-encoder segment` in five ways:
#   geometric   --geometry-only (the segments before the mask term)
#   masks       the defaults (mask term w_m 1, unknown 0.5, pairwise veto 0.5, min size 20)
#   masks-min5  the same, --segment-min-size 5
#   masks-min2  the same, --segment-min-size 2
#   region      the same, --segment-region-veto 0.5 (the region mask veto)
# measure them against the colour truth (`eval-colors --prediction-filtering`: purity, sizes, what limits them),
# then one `eval-colors --held-out --prediction-filtering` pass scores slag with and without PF over all five (and
# their purity against the lifted photo classes). Writes OUTDIR/table.md (one table per split)
# and keeps every JSON under OUTDIR/e<N>/.
#
# Usage: scripts/lab/segments-pf.sh BINARY SCENE OUTDIR [EVERY ...]     (default EVERY: 4 5)
#   BINARY  a release slag-encoder;  SCENE  e.g. ../shared/scenes/snowmiku
# Needs: $SLAG_SHARED (fixtures/sam-amg, fixtures/clip) and ONNX Runtime ($ORT_DYLIB_PATH, or the
# Python package `onnxruntime`, whose library is then used). On an NVIDIA host without a display
# the Vulkan driver file is picked by scripts/vulkan-icd.sh (VK_DRIVER_FILES, when unset).
# SKIP_ENCODE=1 reuses OUTDIR/e<N>/enc; SKIP_HELDOUT=1 stops after the 3D measures.
# EXTRA_ENCODE: more encode flags, split on spaces (e.g. EXTRA_ENCODE="--mask-erode 15").
set -euo pipefail
[ $# -ge 3 ] || { sed -n '2,25p' "$0"; exit 2; }
B=$(realpath "$1"); S=$2; R=$3; shift 3
EVERYS=("$@"); [ ${#EVERYS[@]} -gt 0 ] || EVERYS=(4 5)
here=$(cd "$(dirname "$0")" && pwd)
: "${SLAG_SHARED:?set SLAG_SHARED to the shared folder (fixtures/sam-amg, fixtures/clip)}"
F=$SLAG_SHARED/fixtures
if [ -z "${ORT_DYLIB_PATH:-}" ]; then
  ORT_DYLIB_PATH=$(python3 -c 'import onnxruntime, os, glob; print(sorted(glob.glob(os.path.join(os.path.dirname(onnxruntime.__file__), "capi", "libonnxruntime.so*")))[0])')
  export ORT_DYLIB_PATH
fi
if [ -z "${VK_DRIVER_FILES:-}" ] && command -v nvidia-smi > /dev/null; then
  VK_DRIVER_FILES=$(bash "$here/../vulkan-icd.sh") && [ -n "$VK_DRIVER_FILES" ] && export VK_DRIVER_FILES
fi
read -r -a EXTRA <<< "${EXTRA_ENCODE:-}"
mkdir -p "$R"
echo "# Segments and PF, held-out protocol ($(date -u +%F), $(hostname), $("$B" --version 2>/dev/null || echo slag-encoder)${EXTRA_ENCODE:+, encode $EXTRA_ENCODE})" > "$R/table.md"
NAMES=(geometric masks masks-min5 masks-min2 region)
for N in "${EVERYS[@]}"; do
  D=$R/e$N; E=$D/enc; mkdir -p "$D/seg"
  if [ -z "${SKIP_ENCODE:-}" ]; then
    t0=$(date +%s)
    "$B" encode --scene-dir "$S" --masks sam --sam-encoder "$F/sam-amg/color-sam-encoder.onnx" \
      --sam-decoder "$F/sam-amg/color-sam-decoder.onnx" --sam-points-per-side 16 \
      --sam-pred-iou-thresh 0.8 --sam-stability-score-thresh 0.5 \
      --clip-visual "$F/clip/color-clip-visual.onnx" --every "$N" --raster-scale 0.5 --dense --quiet \
      ${EXTRA[@]+"${EXTRA[@]}"} --out "$E" > "$D/encode.log" 2>&1
    echo "every $N: encode $(( $(date +%s) - t0 )) s"
  fi
  rec=(--mask-record "$E/mask-record.safetensors")
  seg() { # name, flags...
    local name=$1; shift
    "$B" segment --scene-dir "$S" "$@" --out "$D/seg/$name.safetensors" > "$D/seg/$name.json" 2> "$D/seg/$name.log"
  }
  seg geometric --geometry-only
  seg masks "${rec[@]}"
  seg masks-min5 "${rec[@]}" --segment-min-size 5
  seg masks-min2 "${rec[@]}" --segment-min-size 2
  seg region "${rec[@]}" --segment-region-veto 0.5
  more=(); for n in "${NAMES[@]:1}"; do more+=(--more-segments "$D/seg/$n.safetensors"); done
  "$B" eval-colors --scene-dir "$S" --embeddings "$E/embeddings.safetensors" --color-clip "$F/clip" \
    --prediction-filtering --segments "$D/seg/geometric.safetensors" "${more[@]}" "${rec[@]}" \
    > "$D/pf-3d.json" 2> "$D/pf-3d.log"
  [ -n "${SKIP_HELDOUT:-}" ] && continue
  t0=$(date +%s)
  "$B" eval-colors --held-out --scene-dir "$S" --embeddings "$E/embeddings.safetensors" \
    --color-clip "$F/clip" --prediction-filtering --segments "$D/seg/geometric.safetensors" "${more[@]}" \
    --photo-classes-out "$D/photo-classes.u8" > "$D/heldout.json" 2> "$D/heldout.log"
  echo "every $N: held-out pass $(( $(date +%s) - t0 )) s"
  python3 - "$D" "$N" "${NAMES[@]}" >> "$R/table.md" <<'PY'
import json, sys
d, n, names = sys.argv[1], sys.argv[2], sys.argv[3:]
h = json.load(open(f"{d}/heldout.json")); e = h["held_out"]
p3 = json.load(open(f"{d}/pf-3d.json"))
v = {x["name"]: x["score"]["miou"] for x in e["variants"]}
print(f"\n## --every {n}: {len(e['held_out_views'])} views held out, {e['encoded_views']} encoded\n")
print(f"no PF: slag {e['slag']['miou']:.4f}, mixture top-4 {v.get('mixture-mean-S4', float('nan')):.4f}, "
      f"argmax {v.get('argmax', float('nan')):.4f}; pixel oracle {e['oracle']['miou']:.4f}, "
      f"majority {e['majority']['miou']:.4f}; 3D mIoU without PF {h['colour_3d']['miou']:.4f}\n")
print("| segments | count | median / p90 / max | purity (colour) | purity (photo) | pf-majority | pf-mean | pf-weighted | pf-confident | mixture+pf-confident |")
print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
photo = (h.get("photo_truth") or {}).get("purity", [])
for i, (name, q) in enumerate(zip(names, h["segment_quality"])):
    at = "" if i == 0 else f"@seg/{name}"
    z = q["sizes"]
    ph = f"{photo[i]['purity']:.4f}" if i < len(photo) else "–"
    cells = [f"{v.get(k + at, float('nan')):.4f}" for k in
             ("pf-majority", "pf-mean", "pf-weighted", "pf-confident", "mixture-mean-S4+pf-confident")]
    print(f"| {name} | {z['segments']:,} | {z['median']} / {z['p90']} / {z['max']} | "
          f"{q['purity']['purity']:.4f} | {ph} | " + " | ".join(cells) + " |")
lim = p3["segment_limits"]
for a in lim["neighbour_agreement"]:
    print(f"\nColour truth, k = {a['k']}: {a['same_share']:.4f} of the neighbours share the class, "
          f"{a['local_majority']:.4f} hold their ball's majority.", end="")
pt = h.get("photo_truth")
if pt:
    for a in pt["neighbour_agreement"]:
        print(f"\nLifted photo classes, k = {a['k']}: {a['same_share']:.4f} / {a['local_majority']:.4f}.", end="")
    print(f"\nLifted photo class = SH-DC class for {pt['agrees_with_colour_truth']:.4f} of the Gaussians.", end="")
    if pt.get("mask_purity"):
        m, ev = pt["mask_purity"], pt["mask_evidence"]
        print(f"\nMask purity (photo classes): {m['best_view']:.4f} best view, {m['all_slots']:.4f} all slots; "
              f"disagreement same class {ev['same_label']['mean_disagreement']:.3f}, different class "
              f"{ev['different_label']['mean_disagreement']:.3f}.", end="")
if lim.get("mask_purity"):
    m = lim["mask_purity"]
    print(f"\nMask purity (colour truth): {m['best_view']:.4f} best view, {m['all_slots']:.4f} all slots.", end="")
print()
PY
done
cat "$R/table.md"
