#!/usr/bin/env bash
# Runs on a GPU machine of two or more GPUs (x86_64, NVIDIA, no Rust toolchain) after
# `device-gpu-models.sh e2e` on the same machine; NOT part of CI. The e2e workload as
# `slag-encoder encode-cluster`: the command GNU time recorded for a reference run (REF_TXT, an
# e2e-*.txt: `bench --scene-dir /root/big …`) with `bench` replaced by `encode-cluster`, one
# process per GPU on loopback (CUDA_VISIBLE_DEVICES picks ONNX Runtime's GPU, SLAG_WGPU_ADAPTER=#i
# the rasterizer's), `--gpus 1` each and the encode's worker pool inside each process: the
# reference's `--front-workers` is dropped, so each process runs encode's default for one GPU
# (4 front workers with the models on the GPU), or FRONTS=n gives every process
# `--front-workers n`; a shared secret and `--checkpoint-every CKPT` seconds (0: none). Prints
# the job's wall, each process's fronts and rasterizers (its "map pool started" line), peak RSS
# and wall (GNU time), the views each process mapped and the checkpoints of each partition
# (report.json) and, when REF_OUT (the reference run's output folder) is given, whether every
# output file but the report is byte-identical to it (cmp).
# usage: [FRONTS=n] bash scripts/lab/device-cluster.sh REF_TXT TAG PROCESSES [CKPT] [REF_OUT]
#   e.g. bash scripts/lab/device-cluster.sh /root/ab/e2e-f16-g2.txt cl2 2 20 /root/ref-g2
# Output: $OUT/cluster-TAG.txt (the lines printed) and $OUT/cluster-TAG.tgz (logs, report).
set -uo pipefail
for f in .gl/*.deb; do dpkg -x "$f" / >/dev/null 2>&1; done; ldconfig
VK_DRIVER_FILES=$(bash scripts/vulkan-icd.sh) && [ -n "$VK_DRIVER_FILES" ] && export VK_DRIVER_FILES
export XDG_RUNTIME_DIR=/tmp
# shellcheck disable=SC1091
source /root/og/assemble.sh  # ONNX Runtime's CUDA provider, as device-gpu-models.sh assembles it
ref=$1; tag=$2; procs=$3; ckpt=${4:-0}; ref_out=${5:-}
fronts=()
[ -n "${FRONTS:-}" ] && fronts=(--front-workers "$FRONTS")
R=${OUT:-/tmp/out}; w=/root/cluster-$tag; mkdir -p "$R" "$w"
line=$(grep -m1 'Command being timed' "$ref" | sed -e 's/^[^"]*"//' -e 's/"$//')
[ -n "$line" ] || { echo "no GNU time command line in $ref"; exit 1; }
read -r -a cmd <<< "$line"
bin=${cmd[0]}; args=()
skip=0
for ((i = 2; i < ${#cmd[@]}; i++)); do  # cmd[1] is `bench`
  [ $skip = 1 ] && { skip=0; continue; }
  case "${cmd[$i]}" in
    --gpus|--out|--front-workers) skip=1 ;;
    *) args+=("${cmd[$i]}") ;;
  esac
done
# shellcheck source=cluster-common.sh
source "$(dirname "${BASH_SOURCE[0]}")/cluster-common.sh"
cluster_secret "$w"; cluster_hosts "$w" "$procs"
rm -rf "$w/out"
{
  echo "## encode-cluster $tag: $procs processes, one GPU each, front workers ${FRONTS:-default}, checkpoint every $ckpt s"
  echo "   $bin encode-cluster ${args[*]} --gpus 1 ${fronts[*]} --checkpoint-every $ckpt --out OUT"
} | tee "$R/cluster-$tag.txt"
start=$(date +%s.%N); pids=()
for ((i = 0; i < procs; i++)); do
  CUDA_VISIBLE_DEVICES=$i SLAG_WGPU_ADAPTER="#$i" /usr/bin/time -v "$bin" encode-cluster --process "$i" \
    --hosts "$w/hosts" --cluster-secret-file "$w/secret" --checkpoint-every "$ckpt" \
    "${args[@]}" --gpus 1 "${fronts[@]}" --out "$w/out" > "$w/process-$i.log" 2>&1 & pids+=($!)
done
rc=0; for p in "${pids[@]}"; do wait "$p" || rc=$?; done
wall=$(python3 -c "import time; print(round(time.time()-$start,1))")
{
  echo "exit $rc, job wall $wall s"
  for ((i = 0; i < procs; i++)); do
    echo "  process $i: $(grep -m1 -o 'map pool started.*' "$w/process-$i.log"); $(grep -E 'Elapsed \(wall|Maximum resident' "$w/process-$i.log" | sed 's/^\s*//' | tr '\n' ';')"
  done
  python3 - "$w/out/report.json" <<'EOF'
import json, sys
try:
    r = json.load(open(sys.argv[1]))
except Exception as e:
    print("  no report:", e); sys.exit(0)
c = r.get("outputs", {}).get("cluster", {})
for w in c.get("workers", []):
    print("  worker %s: %s views mapped" % (w.get("worker"), len(w.get("views", []))))
for p in c.get("partitions", []):
    print("  partition %s: %s checkpoints, %.3f s in all, largest %s bytes" % (
        p.get("partition"), p.get("checkpoints"), p.get("checkpoint_s", 0.0), p.get("checkpoint_bytes")))
t = r.get("timings", r.get("timing", {}))
print("  report total:", json.dumps(t)[:300])
EOF
  if [ -n "$ref_out" ]; then
    for f in "$ref_out"/*; do
      n=$(basename "$f"); [ "$n" = report.json ] && continue
      echo "  $n: $(cmp -s "$f" "$w/out/$n" && echo identical || echo DIFFERENT)"
    done
  fi
  tail -3 "$w/process-0.log"
} | tee -a "$R/cluster-$tag.txt"
(cd "$w" && tar czf "$R/cluster-$tag.tgz" hosts process-*.log out/report.json 2>/dev/null)
exit 0
