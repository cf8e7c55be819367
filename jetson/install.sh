#!/usr/bin/env bash
# Install slag-edge on the Jetson (JetPack 6, aarch64): binary, ONNX Runtime library, CLIP text
# model + tokenizer, config, environment file, bearer token and the systemd unit. Idempotent: a
# re-run updates the binary, library, models and unit, and keeps an existing edge.toml, edge.env and
# token. Run as root on the Jetson (see jetson/README.md for the bundle to copy over).
#
#   sudo ./install.sh [--prefix /usr/local] [--bin slag-edge] [--ort DIR|LIB] \
#       [--clip-textual clip-textual.onnx] [--tokenizer clip-tokenizer.json] \
#       [--etc /etc/slag] [--unit-dir /etc/systemd/system] [--no-systemd] [--start]
#
# Defaults look beside this script first (a bundle: slag-edge, onnxruntime/, models/), then in the
# repository's cross-build output (target/aarch64/aarch64-unknown-linux-gnu/jetson/slag-edge, then
# .../release/slag-edge) and
# ~/.cache/slag/onnxruntime-1.23.2-aarch64.
#   --prefix DIR     binary in DIR/bin, ONNX Runtime in DIR/lib/slag/onnxruntime, models in
#                    DIR/share/slag/models (default /usr/local)
#   --ort DIR|LIB    the ONNX Runtime to ship: a directory holding libonnxruntime.so* (and, for a
#                    CUDA/TensorRT build, libonnxruntime_providers_*.so), or the library itself.
#                    Without one found, the install keeps ORT_DYLIB_PATH as edge.env has it.
#   --no-systemd     no system user, no unit enabling (staging into a --prefix, or tests)
#   --start          enable the unit and (re)start it
set -euo pipefail
here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
repo=$(cd "$here/.." && pwd)
PREFIX=/usr/local
ETC=/etc/slag
UNIT_DIR=/etc/systemd/system
BIN="" ORT="" TEXT_MODEL="" TOKENIZER=""
SYSTEMD=1 START=0
die() { echo "install.sh: ERROR: $*" >&2; exit 1; }
say() { echo "install.sh: $*" >&2; }
while [ $# -gt 0 ]; do
  case $1 in
    --prefix) PREFIX=${2:?--prefix needs a directory}; shift 2 ;;
    --bin) BIN=${2:?--bin needs a file}; shift 2 ;;
    --ort) ORT=${2:?--ort needs a directory or file}; shift 2 ;;
    --clip-textual|--text-model) TEXT_MODEL=${2:?$1 needs a file}; shift 2 ;;
    --tokenizer) TOKENIZER=${2:?--tokenizer needs a file}; shift 2 ;;
    --etc) ETC=${2:?--etc needs a directory}; shift 2 ;;
    --unit-dir) UNIT_DIR=${2:?--unit-dir needs a directory}; shift 2 ;;
    --no-systemd) SYSTEMD=0; shift ;;
    --start) START=1; shift ;;
    -h|--help) sed -n '2,/^set -euo/p' "$0" | sed '$d; s/^# \{0,1\}//'; exit 0 ;;
    *) die "unknown argument '$1' (see --help)" ;;
  esac
done
PREFIX=${PREFIX%/}
first() { for f in "$@"; do [ -e "$f" ] && { echo "$f"; return 0; }; done; return 0; }

# ---- what to install -----------------------------------------------------------------------------
[ -n "$BIN" ] || BIN=$(first "$here/slag-edge" \
  "$repo/target/aarch64/aarch64-unknown-linux-gnu/jetson/slag-edge" \
  "$repo/target/aarch64/aarch64-unknown-linux-gnu/release/slag-edge")
[ -n "$BIN" ] && [ -f "$BIN" ] ||
  die "no slag-edge binary: pass --bin FILE (build it with scripts/cross-aarch64.sh)"
if command -v file >/dev/null; then
  file -L "$BIN" | grep -q 'ARM aarch64' ||
    say "warning: $BIN is not an aarch64 executable ($(file -bL "$BIN" | cut -d, -f1-2))"
fi
[ -n "$ORT" ] || ORT=$(first "$here/onnxruntime" "$HOME/.cache/slag/onnxruntime-1.23.2-aarch64")
[ -n "$TEXT_MODEL" ] || TEXT_MODEL=$(first "$here/models/clip-textual.onnx")
[ -n "$TOKENIZER" ] || TOKENIZER=$(first "$here/models/clip-tokenizer.json")
for f in "$TEXT_MODEL" "$TOKENIZER"; do
  [ -z "$f" ] || [ -f "$f" ] || die "$f does not exist"
done
if [ $SYSTEMD -eq 1 ] && [ "$(id -u)" -ne 0 ]; then
  die "run as root (sudo), or pass --no-systemd with a --prefix/--etc/--unit-dir you can write"
fi

# ---- user ----------------------------------------------------------------------------------------
if [ $SYSTEMD -eq 1 ] && ! id -u slag >/dev/null 2>&1; then
  say "creating the system user slag"
  useradd --system --user-group --no-create-home --home-dir /var/lib/slag \
    --shell /usr/sbin/nologin slag
fi
# The state directory systemd would create at the first start (StateDirectory=slag), made now so
# that `sudo -u slag slag-edge fetch --store /var/lib/slag/store` works before the service runs.
if [ $SYSTEMD -eq 1 ]; then
  install -d -m 0750 -o slag -g slag /var/lib/slag
fi
# The service user needs the GPU device nodes for ep = "cuda" (group video on JetPack).
if [ $SYSTEMD -eq 1 ] && getent group video >/dev/null && ! id -nG slag | grep -qw video; then
  usermod -a -G video slag
fi

# ---- binary, ONNX Runtime, models ----------------------------------------------------------------
install -d -m 0755 "$PREFIX/bin" "$PREFIX/share/slag/models"
install -m 0755 "$BIN" "$PREFIX/bin/slag-edge.new"
mv -f "$PREFIX/bin/slag-edge.new" "$PREFIX/bin/slag-edge"
say "installed $PREFIX/bin/slag-edge"
ORT_PATH=""
if [ -n "$ORT" ]; then
  ortdir=$PREFIX/lib/slag/onnxruntime
  install -d -m 0755 "$ortdir"
  if [ -d "$ORT" ]; then
    libs=()
    for f in "$ORT"/libonnxruntime.so.* "$ORT"/libonnxruntime_providers_*.so; do
      [ -f "$f" ] && [ ! -L "$f" ] && libs+=("$f")
    done
    [ ${#libs[@]} -gt 0 ] || die "no libonnxruntime.so.* in $ORT"
  else
    libs=("$(readlink -f "$ORT")")
  fi
  main=""
  for f in "${libs[@]}"; do
    install -m 0755 "$f" "$ortdir/$(basename "$f")"
    case $(basename "$f") in libonnxruntime.so.*) main=$(basename "$f") ;; esac
  done
  [ -n "$main" ] || die "no libonnxruntime.so.VERSION among ${libs[*]}"
  ln -sfn "$main" "$ortdir/libonnxruntime.so"
  ORT_PATH=$ortdir/libonnxruntime.so
  say "installed ONNX Runtime $main into $ortdir"
fi
if [ -n "$TEXT_MODEL" ]; then
  install -m 0644 "$TEXT_MODEL" "$PREFIX/share/slag/models/clip-textual.onnx"
  say "installed $PREFIX/share/slag/models/clip-textual.onnx"
fi
if [ -n "$TOKENIZER" ]; then
  install -m 0644 "$TOKENIZER" "$PREFIX/share/slag/models/clip-tokenizer.json"
  say "installed $PREFIX/share/slag/models/clip-tokenizer.json"
fi

# ---- configuration (kept when present) -----------------------------------------------------------
install -d -m 0755 "$ETC"
if [ ! -e "$ETC/edge.toml" ]; then
  sed -e "s#/usr/local/share/slag#$PREFIX/share/slag#g" -e "s#/etc/slag/#$ETC/#g" \
    "$here/edge.toml" > "$ETC/edge.toml.tmp"
  chmod 0644 "$ETC/edge.toml.tmp"
  mv "$ETC/edge.toml.tmp" "$ETC/edge.toml"
  say "wrote $ETC/edge.toml (edit scene/addr/ep there)"
else
  say "kept $ETC/edge.toml"
  # slag-edge refuses a token over plain HTTP on a non-loopback addr unless allowed: say so for
  # a config from before that rule.
  if ! grep -Eq '^[[:space:]]*(tls_cert|allow_plain_http)[[:space:]]*=' "$ETC/edge.toml"; then
    say "note: $ETC/edge.toml sets neither tls_cert nor allow_plain_http; with token_file and a"
    say "      non-loopback addr slag-edge serve will not start: add tls_cert and tls_key (HTTPS)"
    say "      or allow_plain_http = true (see $here/edge.toml)"
  fi
fi
if [ ! -e "$ETC/edge.env" ]; then
  {
    echo "# Environment of slag-edge.service (systemd EnvironmentFile syntax)."
    echo "# The ONNX Runtime library slag-edge loads (the ort crate's load-dynamic; ORT >= 1.23)."
    if [ -n "$ORT_PATH" ]; then echo "ORT_DYLIB_PATH=$ORT_PATH"; else echo "#ORT_DYLIB_PATH=/path/to/libonnxruntime.so"; fi
    echo "RUST_LOG=info"
    echo "# DDS domain of the ROS 2 node (ros2 = true in edge.toml); the robot's ROS 2 graph uses the same."
    echo "ROS_DOMAIN_ID=0"
    echo "# Alternative to token_file in edge.toml:"
    echo "#SLAG_EDGE_TOKEN=..."
    echo "# JetPack ONNX Runtime with the CUDA / TensorRT providers may need the CUDA libraries:"
    echo "#LD_LIBRARY_PATH=/usr/local/cuda/lib64"
  } > "$ETC/edge.env.tmp"
  # 0640 root:slag: it may carry SLAG_EDGE_TOKEN.
  chmod 0640 "$ETC/edge.env.tmp"
  if [ $SYSTEMD -eq 1 ]; then chgrp slag "$ETC/edge.env.tmp"; fi
  mv "$ETC/edge.env.tmp" "$ETC/edge.env"
  say "wrote $ETC/edge.env"
else
  say "kept $ETC/edge.env"
  if [ -n "$ORT_PATH" ] && ! grep -q "^ORT_DYLIB_PATH=$ORT_PATH\$" "$ETC/edge.env"; then
    say "note: $ETC/edge.env sets $(grep '^ORT_DYLIB_PATH=' "$ETC/edge.env" || echo 'no ORT_DYLIB_PATH'); the library just installed is $ORT_PATH"
  fi
fi
if [ ! -e "$ETC/token" ]; then
  (umask 077; od -An -tx1 -N32 /dev/urandom | tr -d ' \n' > "$ETC/token.tmp"; echo >> "$ETC/token.tmp")
  if [ $SYSTEMD -eq 1 ]; then chgrp slag "$ETC/token.tmp"; chmod 0640 "$ETC/token.tmp"; fi
  mv "$ETC/token.tmp" "$ETC/token"
  say "wrote a random bearer token to $ETC/token (clients send 'Authorization: Bearer <token>')"
else
  say "kept $ETC/token"
fi

# ---- systemd unit --------------------------------------------------------------------------------
install -d -m 0755 "$UNIT_DIR"
sed -e "s#@PREFIX@#$PREFIX#g" -e "s#/etc/slag/#$ETC/#g" "$here/slag-edge.service" \
  > "$UNIT_DIR/slag-edge.service.tmp"
chmod 0644 "$UNIT_DIR/slag-edge.service.tmp"
mv "$UNIT_DIR/slag-edge.service.tmp" "$UNIT_DIR/slag-edge.service"
say "installed $UNIT_DIR/slag-edge.service"
if [ $SYSTEMD -eq 1 ]; then
  systemctl daemon-reload
  if [ $START -eq 1 ]; then
    systemctl enable slag-edge.service
    systemctl restart slag-edge.service
    say "slag-edge.service enabled and (re)started: journalctl -u slag-edge -f"
  else
    say "start it with: sudo systemctl enable --now slag-edge (after 'slag-edge fetch', see README)"
  fi
fi
"$PREFIX/bin/slag-edge" --version 2>/dev/null ||
  say "note: $PREFIX/bin/slag-edge does not run on this machine ($(uname -m)); it is for aarch64"
