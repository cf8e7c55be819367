#!/usr/bin/env bash
# Tampering with signed manifests through the command lines, on loopback (127.0.0.1 only):
# `slag-shards keygen`, `partition --synthetic --signing-key` (generation 1, then 2 with another
# tiling, and another scene of the same publisher), `export`; OpenSSL verifies an exported
# `manifest.sig`; then each case is a (tampered) copy of an export served statically, fetched
# with `slag-edge fetch --trusted-key`: a flipped byte in a tile, an edited manifest, another
# key's signature, no signature, another scene's tile, and generation 1 after generation 2.
# Prints each command and what it printed; exits 1 unless every tampered fetch is refused and
# the genuine ones succeed.
#
#   bash scripts/probe-tampering.sh           # target/debug binaries (cargo test builds them)
#   B=target/release bash scripts/probe-tampering.sh
set -u
B=${B:-target/debug}
S="$B/slag-shards"; E="$B/slag-edge"
W=$(mktemp -d)
PORT=${PORT:-18731}
trap 'kill $SRV 2>/dev/null; rm -rf "$W"' EXIT
fails=0
run() { # expect-status command...
    local want=$1; shift
    echo "\$ ${*//$W/W}"
    "$@" 2>&1 | sed "s#$W#W#g"
    local rc=${PIPESTATUS[0]}
    echo "(exit $rc)"
    if { [ "$want" = ok ] && [ "$rc" != 0 ]; } || { [ "$want" = refused ] && [ "$rc" = 0 ]; }; then
        echo "FAIL: expected $want"; fails=$((fails + 1))
    fi
}
part() { "$S" partition --synthetic 20000:16 --shard-store "$W/$1" --scene "$2" --max-per-shard "$3" \
    --signing-key "$W/keys/manifest-key.pem" >/dev/null 2>&1; }
run ok "$S" keygen --out "$W/keys"
run refused "$S" keygen --out "$W/keys"
"$S" keygen --out "$W/other" >/dev/null
part store lab 2000 && "$S" export --shard-store "$W/store" --scene lab --out "$W/srv/g1" >/dev/null
part store lab 600 && "$S" export --shard-store "$W/store" --scene lab --out "$W/srv/g2" >/dev/null
part store2 lac 600 && "$S" export --shard-store "$W/store2" --scene lac --out "$W/srv/other-scene" >/dev/null
"$S" export --shard-store "$W/store" --scene lab --signing-key "$W/other/manifest-key.pem" \
    --out "$W/srv/otherkey" >/dev/null
python3 -c "import json,sys;open(sys.argv[2],'wb').write(bytes.fromhex(json.load(open(sys.argv[1]))['signature']))" \
    "$W/srv/g2/manifest.sig" "$W/sig.bin"
run ok openssl pkeyutl -verify -pubin -inkey "$W/keys/manifest-key.pub.pem" -rawin \
    -in "$W/srv/g2/manifest.json" -sigfile "$W/sig.bin"
cp -r "$W/srv/g2" "$W/srv/tile"
python3 -c "import sys;p=sys.argv[1];b=bytearray(open(p,'rb').read());b[len(b)//2]^=0x5a;open(p,'wb').write(b)" \
    "$W/srv/tile/shards/0"
cp -r "$W/srv/g2" "$W/srv/manifest"
sed -i 's/"max_per_shard": 600/"max_per_shard": 601/' "$W/srv/manifest/manifest.json"
cp -r "$W/srv/g2" "$W/srv/unsigned"; rm "$W/srv/unsigned/manifest.sig"
cp -r "$W/srv/g2" "$W/srv/swap"; cp "$W/srv/other-scene/shards/0" "$W/srv/swap/shards/0"
echo g1 > "$W/srv/CURRENT"
# /v1/scenes/<scene>/{manifest,manifest.sig,shards/N} from the folder CURRENT names.
python3 - "$W/srv" "$PORT" <<'PY' &
import http.server, os, sys
root, port = sys.argv[1], int(sys.argv[2])
class H(http.server.BaseHTTPRequestHandler):
    def log_message(self, *a): pass
    def do_GET(self):
        parts = self.path.split('?')[0].strip('/').split('/')
        if len(parts) < 4 or parts[:2] != ['v1', 'scenes']:
            return self.send_error(404)
        rest = parts[3:]
        name = {'manifest': 'manifest.json', 'manifest.sig': 'manifest.sig'}.get(rest[0])
        cur = open(os.path.join(root, 'CURRENT')).read().strip()
        path = os.path.join(root, cur, *(rest if name is None else [name]))
        if not os.path.isfile(path):
            return self.send_error(404)
        body = open(path, 'rb').read()
        self.send_response(200)
        self.send_header('Content-Length', str(len(body)))
        self.end_headers()
        self.wfile.write(body)
http.server.ThreadingHTTPServer(('127.0.0.1', port), H).serve_forever()
PY
SRV=$!
sleep 1
F=("$E" fetch --from "http://127.0.0.1:$PORT" --scene lab --center 1000,1000 --radius 3000
    --store "$W/edge" --retries 0 --trusted-key "$W/keys/manifest-key.pub.pem")
echo "== generation 1, signed"; run ok "${F[@]}"
for c in tile manifest otherkey unsigned swap; do
    echo "$c" > "$W/srv/CURRENT"; echo "== $c"; run refused "${F[@]}"
done
echo g2 > "$W/srv/CURRENT"; echo "== generation 2, signed"; run ok "${F[@]}"
echo g1 > "$W/srv/CURRENT"; echo "== generation 1 again (replay)"; run refused "${F[@]}"
echo "$fails failed"
[ "$fails" = 0 ]
