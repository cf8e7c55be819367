#!/usr/bin/env bash
# The cost of trusting a publisher's key, on loopback, for one or more builds in the same run:
#   1. the engine load of a 1 GB signed store without and with the trusted key
#      (edge/examples/load_cost: wall and CPU seconds, medians);
#   2. a 104-tile signed disc fetched into a new store without and with --trusted-key
#      (wall seconds and the fetch process's CPU seconds, medians, and their ratios), then
#      fetched again into the store that now holds it (every tile kept and checked: CRC-32s
#      only without the key, also hashed with it).
# Builds named NAME=DIR are run alternately, round by round; DIR holds slag-edge and
# examples/load_cost of that build (e.g. target/debug). slag-shards comes from the first DIR.
#
# usage: bash scripts/lab/trust-cost.sh [--load-rounds N] [--fetch-rounds N] [--fetch-only] NAME=DIR...
#   e.g. bash scripts/lab/trust-cost.sh main=/tmp/main-debug branch=target/debug
# --fetch-only: part 2 alone (the 1 GB store is then neither made nor loaded).
# Needs ~4 GB free under ${TMPDIR:-/tmp}; the stores are made once and kept in
# ${SLAG_TRUST_COST_DIR:-$TMPDIR/slag-trust-cost} for the next run.
set -euo pipefail
load_rounds=5
fetch_rounds=9
fetch_only=0
builds=()
while [ $# -gt 0 ]; do
    case "$1" in
        --load-rounds) load_rounds=$2; shift 2 ;;
        --fetch-rounds) fetch_rounds=$2; shift 2 ;;
        --fetch-only) fetch_only=1; shift ;;
        *=*) builds+=("$1"); shift ;;
        *) echo "usage: $0 [--load-rounds N] [--fetch-rounds N] [--fetch-only] NAME=DIR..." >&2; exit 2 ;;
    esac
done
[ ${#builds[@]} -gt 0 ] || { echo "usage: $0 [--load-rounds N] [--fetch-rounds N] [--fetch-only] NAME=DIR..." >&2; exit 2; }
first=${builds[0]#*=}
shards="$first/slag-shards"
work=${SLAG_TRUST_COST_DIR:-${TMPDIR:-/tmp}/slag-trust-cost}
mkdir -p "$work"
cd "$work"
key=keys/manifest-key.pub.pem
if [ ! -f "$key" ]; then
    "$shards" keygen --out keys >/dev/null
fi
[ $fetch_only = 1 ] || [ -d pub-big ] || "$shards" partition --synthetic 1000000:512 --max-per-shard 10000 \
    --signing-key keys/manifest-key.pem --shard-store pub-big --scene big >/dev/null
[ -d pub-small ] || "$shards" partition --synthetic 100000:512 --max-per-shard 1000 \
    --signing-key keys/manifest-key.pem --shard-store pub-small --scene small >/dev/null

# Two shard servers on free loopback ports, stopped on exit.
pids=()
trap 'for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done' EXIT
if [ $fetch_only = 0 ]; then
    "$shards" serve --shard-store pub-big --listen 127.0.0.1:0 >serve-big.log 2>&1 &
    pids+=($!)
fi
"$shards" serve --shard-store pub-small --listen 127.0.0.1:0 >serve-small.log 2>&1 &
pids+=($!)
url_of() { # LOG -> the URL the server logged
    for _ in $(seq 100); do
        url=$(grep -o 'http://127.0.0.1:[0-9]*' "$1" | head -1 || true)
        [ -n "$url" ] && { echo "$url"; return; }
        sleep 0.1
    done
    echo "a shard server did not start: $(cat "$1")" >&2
    exit 1
}
small=$(url_of serve-small.log)
if [ $fetch_only = 0 ]; then
    big=$(url_of serve-big.log)
    [ -d edge-big ] || "$first/slag-edge" fetch --from "$big" --scene big --center 1000,1000 \
        --radius 5000 --store edge-big --trusted-key "$key" >/dev/null
fi

echo "machine: $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), load average $(cut -d' ' -f1-3 /proc/loadavg)"
if [ $fetch_only = 0 ]; then
    echo "== load of the 1 GB store (128 tiles), $load_rounds rounds per build"
    for b in "${builds[@]}"; do
        echo "$b: $("${b#*=}/examples/load_cost" edge-big big "$key" "$load_rounds" | tail -1)"
    done
fi
echo "== fetch of the 104-tile disc into a new store, then again into that store, $fetch_rounds rounds"
python3 - "$small" "$key" "$fetch_rounds" "${builds[@]}" <<'EOF'
import json, resource, shutil, statistics, subprocess, sys, time
url, key, rounds, builds = sys.argv[1], sys.argv[2], int(sys.argv[3]), [b.split('=', 1) for b in sys.argv[4:]]
t, cpu = {}, {}
children = lambda: (lambda r: r.ru_utime + r.ru_stime)(resource.getrusage(resource.RUSAGE_CHILDREN))
def timed(key, cmd):
    s, c = time.monotonic(), children()
    p = subprocess.run(cmd, capture_output=True, text=True)
    e, c = time.monotonic() - s, children() - c
    if p.returncode != 0:
        sys.exit(f'{key}: {p.stderr}')
    t.setdefault(key, []).append(e)
    cpu.setdefault(key, []).append(c)
    return json.loads(p.stdout)
for _ in range(rounds):
    for name, d in builds:
        for mode in ('unsigned', 'signed'):
            store = f'fetch-{name}-{mode}'
            shutil.rmtree(store, ignore_errors=True)
            cmd = [f'{d}/slag-edge', 'fetch', '--from', url, '--scene', 'small', '--center',
                   '1000,1000', '--radius', '1000', '--store', store, '--json']
            if mode == 'signed':
                cmd += ['--trusted-key', key]
            tiles = timed((name, mode), cmd)['downloaded']
            kept = timed((name, mode, 'again'), cmd)['skipped']
for name, _ in builds:
    for again, what in (((), f'new store ({tiles} tiles)'), (('again',), f'again ({kept} kept)')):
        k = lambda m: (name, m) + again
        u, s = (statistics.median(t[k(m)]) for m in ('unsigned', 'signed'))
        runs = lambda m: ' '.join(f'{x:.3f}' for x in t[k(m)])
        cu, cs = (statistics.median(cpu[k(m)]) for m in ('unsigned', 'signed'))
        print(f'{name}, {what}: unsigned median {u:.3f} s ({runs("unsigned")}); '
              f'signed median {s:.3f} s ({runs("signed")}); ratio {s / u:.2f}; '
              f'client CPU median {cu:.3f} s unsigned, {cs:.3f} s signed, ratio {cs / cu:.2f}')
EOF
