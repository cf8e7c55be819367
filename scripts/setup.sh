#!/usr/bin/env bash
# Idempotent set-up for building and running slag on a fresh Debian/Ubuntu machine (x86_64 or
# aarch64): Mesa lavapipe (Vulkan on the CPU, for wgpu when no GPU is present) and the ONNX Runtime
# shared library from PyPI's `onnxruntime` wheel. Source it (`. scripts/setup.sh`) to get
# ORT_DYLIB_PATH and SLAG_SHARED exported.
#
# GPU: when an NVIDIA driver is present (nvidia-smi works or /proc/driver/nvidia exists), or with
# SLAG_GPU=1 or `. scripts/setup.sh --gpu` (SLAG_GPU=0 turns it off), ORT_DYLIB_PATH points instead
# to ONNX Runtime with its CUDA execution provider, from PyPI's `onnxruntime-gpu` wheel
# (ORT_GPU_VERSION, default 1.31.1, built for CUDA 13; 1.23.2-1.26.0 are CUDA 12 builds), in
# ~/.cache/slag/onnxruntime-gpu-VERSION-ARCH, and LD_LIBRARY_PATH gets the CUDA runtime libraries it
# needs: torch's nvidia/*/lib folders when $SLAG_PYTHON (default python3) has a torch built for the
# same CUDA major version, else the wheels of onnxruntime-gpu's own `cuda` and `cudnn` extras,
# pip-installed into ~/.cache/slag/cudaMAJOR. SLAG_ORT_GPU_DIR=DIR uses an already assembled folder
# (libonnxruntime.so[.VERSION] + libonnxruntime_providers_{cuda,shared}.so, e.g. /root/og from
# ../shared/tools/ort-gpu-chunks.sh on a machine without network) and only adds the CUDA libraries
# of torch. VK_DRIVER_FILES names the NVIDIA Vulkan driver file that works without a display
# (scripts/vulkan-icd.sh). Without a GPU nothing here changes (CI's path).
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

slag_gpu=0
for _a in "$@"; do [ "$_a" = --gpu ] && slag_gpu=1; done
if [ "${SLAG_GPU:-}" = 1 ]; then
  slag_gpu=1
elif [ "${SLAG_GPU:-}" != 0 ] && [ "$slag_gpu" = 0 ]; then
  if [ -e /proc/driver/nvidia ] || { command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; }; then
    slag_gpu=1
  fi
fi
if [ "$slag_gpu" = 1 ]; then
  SLAG_PYTHON=${SLAG_PYTHON:-python3}
  # The CUDA library folders of $SLAG_PYTHON's torch, if it is built for CUDA major $1.
  slag_torch_cuda_libs() {
    "$SLAG_PYTHON" - "$1" 2>/dev/null <<'PY' || true
import glob, os, sys
import torch
if (torch.version.cuda or "").split(".")[0] == sys.argv[1]:
    site = os.path.dirname(os.path.dirname(torch.__file__))
    print(":".join(sorted({os.path.dirname(p) for p in glob.glob(f"{site}/nvidia/**/lib*.so*", recursive=True)})))
PY
  }
  if [ -n "${SLAG_ORT_GPU_DIR:-}" ]; then
    ORT_GPU_DIR=$SLAG_ORT_GPU_DIR
    cuda_major=${SLAG_CUDA_MAJOR:-13}
  else
    ORT_GPU_VERSION=${ORT_GPU_VERSION:-1.31.1}
    ORT_GPU_DIR=$HOME/.cache/slag/onnxruntime-gpu-$ORT_GPU_VERSION-$(uname -m)
    if [ ! -e "$ORT_GPU_DIR/libonnxruntime_providers_cuda.so" ] || [ ! -e "$ORT_GPU_DIR/cuda-requirements.txt" ]; then
      _tmp=$(mktemp -d)
      python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.11 --implementation cp \
        --platform "manylinux_2_28_$(uname -m)" --platform "manylinux_2_27_$(uname -m)" \
        --platform "manylinux_2_17_$(uname -m)" -d "$_tmp" "onnxruntime-gpu==$ORT_GPU_VERSION"
      mkdir -p "$ORT_GPU_DIR"
      # The libraries, and the `cuda` + `cudnn` extras of the wheel's own metadata (the CUDA
      # runtime wheels it was built against) in cuda-requirements.txt.
      python3 - "$_tmp" "$ORT_GPU_DIR" <<'PY'
import glob, os, re, shutil, sys, zipfile
tmp, dest = sys.argv[1:3]
whl = glob.glob(os.path.join(tmp, "onnxruntime_gpu-*.whl"))[0]
with zipfile.ZipFile(whl) as z:
    for n in z.namelist():
        b = os.path.basename(n)
        if "/capi/" in n and (b.startswith("libonnxruntime.so") or b in (
                "libonnxruntime_providers_cuda.so", "libonnxruntime_providers_shared.so")):
            out = os.path.join(dest, b)
            with z.open(n) as s, open(out + ".tmp", "wb") as d:
                shutil.copyfileobj(s, d)
            os.chmod(out + ".tmp", 0o755)
            os.replace(out + ".tmp", out)
        if n.endswith(".dist-info/METADATA"):
            meta = z.read(n).decode()
reqs = [m.group(1).strip() for m in re.finditer(
    r"^Requires-Dist: ([^;]+); extra == \"(?:cuda|cudnn)\"", meta, re.M)]
lib = sorted(glob.glob(os.path.join(dest, "libonnxruntime.so.*")))[0]
link = os.path.join(dest, "libonnxruntime.so")
if os.path.lexists(link):
    os.remove(link)
os.symlink(os.path.basename(lib), link)
open(os.path.join(dest, "cuda-requirements.txt"), "w").write("\n".join(reqs) + "\n")
PY
      rm -rf "$_tmp"
    fi
    cuda_major=$(sed -n 's/^nvidia-cuda-runtime[-a-z0-9]*~=\([0-9]*\).*/\1/p' "$ORT_GPU_DIR/cuda-requirements.txt")
  fi
  _ortlib=$ORT_GPU_DIR/libonnxruntime.so
  [ -e "$_ortlib" ] || _ortlib=$(ls "$ORT_GPU_DIR"/libonnxruntime.so.* 2>/dev/null | head -1)
  if [ -z "$_ortlib" ] || [ ! -e "$ORT_GPU_DIR/libonnxruntime_providers_cuda.so" ]; then
    echo "setup: $ORT_GPU_DIR lacks libonnxruntime.so or libonnxruntime_providers_cuda.so" >&2
    return 1 2>/dev/null || exit 1
  fi
  _cudalibs=$(slag_torch_cuda_libs "$cuda_major")
  _cudafrom=${_cudalibs:+torch ($SLAG_PYTHON)}
  # Libraries the CUDA provider still cannot find (the driver's libcuda.so.1 aside), e.g. cuRAND,
  # which some torch wheels do not ship.
  _missing=$(LD_LIBRARY_PATH=$ORT_GPU_DIR${_cudalibs:+:$_cudalibs} ldd "$ORT_GPU_DIR/libonnxruntime_providers_cuda.so" 2>/dev/null \
    | awk '/not found/ && $1 != "libcuda.so.1" {print $1}' | paste -sd' ')
  if { [ -z "$_cudalibs" ] || [ -n "$_missing" ]; } && [ -z "${SLAG_ORT_GPU_DIR:-}" ]; then
    CUDA_LIBS_DIR=$HOME/.cache/slag/cuda$cuda_major
    if ! cmp -s "$ORT_GPU_DIR/cuda-requirements.txt" "$CUDA_LIBS_DIR/.requirements.txt"; then
      PIP_ROOT_USER_ACTION=ignore python3 -m pip install -q --disable-pip-version-check \
        --no-warn-script-location --target "$CUDA_LIBS_DIR" -r "$ORT_GPU_DIR/cuda-requirements.txt"
      cp "$ORT_GPU_DIR/cuda-requirements.txt" "$CUDA_LIBS_DIR/.requirements.txt"
    fi
    _cudalibs=${_cudalibs:+$_cudalibs:}$(find "$CUDA_LIBS_DIR/nvidia" -name 'lib*.so*' -printf '%h\n' | sort -u | paste -sd:)
    _cudafrom="${_cudafrom:+$_cudafrom + }$CUDA_LIBS_DIR"
  elif [ -n "$_missing" ] || [ -z "$_cudalibs" ]; then
    echo "setup: warning: the CUDA provider in $ORT_GPU_DIR misses ${_missing:-the CUDA $cuda_major libraries} (no torch for CUDA $cuda_major in $SLAG_PYTHON has them): add their folders to LD_LIBRARY_PATH" >&2
  fi
  export LD_LIBRARY_PATH=$ORT_GPU_DIR${_cudalibs:+:$_cudalibs}${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
  export ORT_DYLIB_PATH=$_ortlib
  echo "setup: GPU: ONNX Runtime CUDA provider from $ORT_GPU_DIR, CUDA $cuda_major libraries from ${_cudafrom:-nowhere}" >&2
  # The NVIDIA Vulkan driver file that works without a display (scripts/vulkan-icd.sh says why).
  _icd=$(bash "$SLAG_ROOT/scripts/vulkan-icd.sh" || true)
  if [ -n "$_icd" ]; then
    export VK_DRIVER_FILES=$_icd
    echo "setup: GPU: Vulkan driver file $VK_DRIVER_FILES" >&2
  fi
  unset -f slag_torch_cuda_libs
fi
echo "setup: ORT_DYLIB_PATH=$ORT_DYLIB_PATH SLAG_SHARED=$SLAG_SHARED" >&2
