#!/usr/bin/env bash
# Idempotent set-up for building and running slag on a fresh Debian/Ubuntu machine (x86_64 or
# aarch64): Mesa lavapipe (Vulkan on the CPU, for wgpu when no GPU is present) and the ONNX Runtime
# shared library from PyPI's `onnxruntime` wheel. Source it (`. scripts/setup.sh`) to get
# ORT_DYLIB_PATH and SLAG_SHARED exported.
set -euo pipefail
SLAG_ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
export SLAG_SHARED=${SLAG_SHARED:-$(cd "$SLAG_ROOT/.." && pwd)/shared}
if [ ! -d "$SLAG_SHARED" ]; then
  echo "setup: no shared/ folder at $SLAG_SHARED (set SLAG_SHARED)" >&2
  exit 1
fi
need=()
dpkg -s mesa-vulkan-drivers >/dev/null 2>&1 || need+=(mesa-vulkan-drivers)
dpkg -s libvulkan1 >/dev/null 2>&1 || need+=(libvulkan1)
if [ ${#need[@]} -gt 0 ]; then
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO=sudo
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
fi
ORT_VERSION=${ORT_VERSION:-1.23.2}
ORT_DIR=${ORT_DIR:-$HOME/.cache/slag/onnxruntime-$ORT_VERSION-$(uname -m)}
if [ ! -e "$ORT_DIR/libonnxruntime.so" ]; then
  bash "$SLAG_SHARED/tools/install-onnxruntime.sh" "$ORT_DIR" "$ORT_VERSION" >/dev/null
fi
export ORT_DYLIB_PATH=$ORT_DIR/libonnxruntime.so
# Mesa's Vulkan loader (wgpu on lavapipe) prints "error: XDG_RUNTIME_DIR is invalid or not set"
# at every start on machines without a login session (CI, containers): give it a private runtime
# folder, as a login session would. Other errors still reach stderr.
if [ -z "${XDG_RUNTIME_DIR:-}" ] || [ ! -d "$XDG_RUNTIME_DIR" ]; then
  export XDG_RUNTIME_DIR=${TMPDIR:-/tmp}/slag-runtime-$(id -u)
  mkdir -p "$XDG_RUNTIME_DIR" && chmod 700 "$XDG_RUNTIME_DIR"
fi
echo "setup: ORT_DYLIB_PATH=$ORT_DYLIB_PATH SLAG_SHARED=$SLAG_SHARED" >&2
