#!/usr/bin/env bash
# Runs on a GPU machine (x86_64, NVIDIA, no Rust toolchain): the held-out study of
# the stored forms on snowmiku, `--every 4`: each encode once with `--mixture-keep 16` (the dense
# `E_k` and the mixture come from the same run) and once without it (the mixture's encode-time
# cost), then `eval-colors --held-out`, which scores the dense rows, the mixture's mean form cut to
# S = 1, 2, 4, 8, 16 and its max form in one render pass, with the majority and pixel-oracle
# baselines. Expects .devcarry/ (release slag-encoder, scene/ = snowmiku images + COLMAP + a
# geometry+DC .ply, shared/fixtures/{sam-amg,clip}) and .gl/ (Vulkan loader debs), as
# scripts/lab/device-bench.sh. Reports, eval JSON and the log go to $OUT.
set -uo pipefail
# shellcheck source=scripts/lab/device-snowmiku-env.sh
. scripts/lab/device-snowmiku-env.sh
encode() { # name, args...
  local name=$1; shift
  echo "### encode $name: $*"
  local t0=$(date +%s%N)
  "$B" bench --scene-dir $S "$@" --dense --quiet --out $W/$name > $W/$name.log 2>&1 || tail -n 5 $W/$name.log
  echo "$name wall_s $(( ($(date +%s%N) - t0) / 1000000 ))e-3"
  mkdir -p "$R/reports"; cp $W/$name/report.json "$R/reports/report-$name.json"
}
heldout() { # name
  local name=$1
  echo "### eval-colors --held-out $name"
  "$B" eval-colors --held-out --scene-dir $S --embeddings $W/$name/embeddings.safetensors \
    --color-clip $F/clip > "$R/heldout-$name.json" 2> "$R/heldout-$name.err" || { tail -n 5 "$R/heldout-$name.err"; return; }
  python3 - "$R/heldout-$name.json" <<'PY'
import json, sys
e = json.load(open(sys.argv[1]))["held_out"]
def line(n, s): return f"  {n:<28} mIoU {s['miou']:.4f}  acc {s['pixel_accuracy']:.4f}  " + ' '.join(f"{c['name']}={c['iou']:.3f}" for c in s['classes'] if c['in_miou'])
for k in ("slag", "majority", "oracle"):
    if k in e: print(line(k, e[k]))
for v in e.get("variants", []): print(line(v["name"], v["score"]))
PY
}
if [ "${1:-}" = timing ]; then
  # The mixture's encode-time cost: with and without --mixture-keep 16, alternated, twice each.
  for rep in 1 2; do
    encode sam-finest-$rep "${SAM[@]}" "${CLIP[@]}" --every 4 --raster-scale 0.5
    encode sam-finest-mix-$rep "${SAM[@]}" "${CLIP[@]}" --every 4 --raster-scale 0.5 --mixture-keep 16
    encode graph-r1-$rep --masks graph "${CLIP[@]}" --every 4 --raster-scale 1.0
    encode graph-r1-mix-$rep --masks graph "${CLIP[@]}" --every 4 --raster-scale 1.0 --mixture-keep 16
  done
  ls -la $W/*/ | grep -E "safetensors|^/" > "$R/reports/sizes.txt"
  tar -C "$R" -czf "$R/reports.tgz" reports && rm -r "$R/reports"
  exit 0
fi
if [ "${1:-}" = every2 ]; then
  # A second split to check the choice of S made on --every 4: every 2nd view encoded (49), the
  # odd-indexed 48 held out.
  encode sam-e2-mix "${SAM[@]}" "${CLIP[@]}" --every 2 --raster-scale 0.5 --mixture-keep 16
  encode graph-e2-mix --masks graph "${CLIP[@]}" --every 2 --raster-scale 0.5 --mixture-keep 16
  for n in sam-e2-mix graph-e2-mix; do heldout $n; done
  tar -C "$R" -czf "$R/reports.tgz" reports && rm -r "$R/reports"
  exit 0
fi
# Time pairs first (each form with and without the mixture, back to back), then the rest.
encode sam-finest "${SAM[@]}" "${CLIP[@]}" --every 4 --raster-scale 0.5
encode sam-finest-mix "${SAM[@]}" "${CLIP[@]}" --every 4 --raster-scale 0.5 --mixture-keep 16
encode graph-r1 --masks graph "${CLIP[@]}" --every 4 --raster-scale 1.0
encode graph-r1-mix --masks graph "${CLIP[@]}" --every 4 --raster-scale 1.0 --mixture-keep 16
encode sam-finest-area-mix "${SAM[@]}" "${CLIP[@]}" --every 4 --raster-scale 0.5 --mixture-keep 16 --mask-weighting area
encode graph-r0.5-mix --masks graph "${CLIP[@]}" --every 4 --raster-scale 0.5 --mixture-keep 16
for n in sam-finest-mix graph-r1-mix sam-finest-area-mix graph-r0.5-mix; do heldout $n; done
ls -la $W/*/ | grep -E "safetensors|^/" > "$R/reports/sizes.txt"
tar -C "$R" -czf "$R/reports.tgz" reports && rm -r "$R/reports"
exit 0
