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
#
# Safe to source: the caller's shell options (errexit, nounset, pipefail, ...) are the same after
# it as before, and a failure returns non-zero to the caller instead of closing its shell (run as
# `bash scripts/setup.sh`, it exits non-zero). It exports only the variables named above
# (SLAG_SHARED, ORT_DYLIB_PATH, XDG_RUNTIME_DIR, and with a GPU LD_LIBRARY_PATH and VK_DRIVER_FILES).

# `set +o` in a command substitution reports errexit off (bash does not pass -e into it): $- has it.
_slag_setup_opts=$(set +o)
case $- in *e*) _slag_setup_opts+=$'\nset -e' ;; esac
# The body runs without errexit (set here, whatever the caller's), so every step that can fail is
# checked where it runs and returns its own message.
set +e +u -o pipefail

# Fails with a message on stderr: `slag_setup_fail "what went wrong"; return 1`.
slag_setup_fail() { echo "setup: $1" >&2; }

# Installs Mesa's lavapipe and the Vulkan loader when missing (apt; sudo when not root).
slag_setup_vulkan() {
  local need=() sudo=""
  dpkg -s mesa-vulkan-drivers >/dev/null 2>&1 || need+=(mesa-vulkan-drivers)
  dpkg -s libvulkan1 >/dev/null 2>&1 || need+=(libvulkan1)
  # The tests check that OpenSSL reads the signing keys and verifies their signatures.
  dpkg -s openssl >/dev/null 2>&1 || need+=(openssl)
  [ ${#need[@]} -gt 0 ] || return 0
  [ "$(id -u)" -eq 0 ] || sudo=sudo
  $sudo apt-get update -qq \
    && DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null \
    || { slag_setup_fail "apt-get could not install ${need[*]}"; return 1; }
}

# The CUDA library folders of $SLAG_PYTHON's torch, if it is built for CUDA major $1 (empty if not).
slag_torch_cuda_libs() {
  "$SLAG_PYTHON" - "$1" 2>/dev/null <<'PY' || true
import glob, os, sys
import torch
if (torch.version.cuda or "").split(".")[0] == sys.argv[1]:
    site = os.path.dirname(os.path.dirname(torch.__file__))
    print(":".join(sorted({os.path.dirname(p) for p in glob.glob(f"{site}/nvidia/**/lib*.so*", recursive=True)})))
PY
}

# Downloads onnxruntime-gpu==$1 from PyPI into folder $2: its libraries, and the `cuda` + `cudnn`
# extras of the wheel's own metadata (the CUDA runtime wheels it was built against) in
# cuda-requirements.txt.
slag_fetch_ort_gpu() {
  local tmp rc
  tmp=$(mktemp -d) || return 1
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.11 --implementation cp \
    --platform "manylinux_2_28_$(uname -m)" --platform "manylinux_2_27_$(uname -m)" \
    --platform "manylinux_2_17_$(uname -m)" -d "$tmp" "onnxruntime-gpu==$1" \
    && mkdir -p "$2" \
    && python3 - "$tmp" "$2" <<'PY'
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
  rc=$?
  rm -rf "$tmp"
  return $rc
}

# Whether to set up the GPU: --gpu among the arguments, SLAG_GPU=1, or (unless SLAG_GPU=0) an
# NVIDIA driver that answers.
slag_want_gpu() {
  local a
  [ "${SLAG_GPU:-}" = 1 ] && return 0
  for a in "$@"; do [ "$a" = --gpu ] && return 0; done
  [ "${SLAG_GPU:-}" != 0 ] || return 1
  [ -e /proc/driver/nvidia ] || { command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; }
}

# The GPU part: ORT_DYLIB_PATH to ONNX Runtime with the CUDA provider, LD_LIBRARY_PATH to the CUDA
# libraries it needs, VK_DRIVER_FILES to the headless NVIDIA Vulkan driver file.
slag_setup_gpu() {
  local root=$1 ort_gpu_dir cuda_major ortlib cudalibs cudafrom missing cuda_libs_dir icd
  local SLAG_PYTHON=${SLAG_PYTHON:-python3}
  if [ -n "${SLAG_ORT_GPU_DIR:-}" ]; then
    ort_gpu_dir=$SLAG_ORT_GPU_DIR
    cuda_major=${SLAG_CUDA_MAJOR:-13}
  else
    local version=${ORT_GPU_VERSION:-1.31.1}
    ort_gpu_dir=$HOME/.cache/slag/onnxruntime-gpu-$version-$(uname -m)
    if [ ! -e "$ort_gpu_dir/libonnxruntime_providers_cuda.so" ] || [ ! -e "$ort_gpu_dir/cuda-requirements.txt" ]; then
      slag_fetch_ort_gpu "$version" "$ort_gpu_dir" \
        || { slag_setup_fail "could not fetch onnxruntime-gpu $version into $ort_gpu_dir"; return 1; }
    fi
    cuda_major=$(sed -n 's/^nvidia-cuda-runtime[-a-z0-9]*~=\([0-9]*\).*/\1/p' "$ort_gpu_dir/cuda-requirements.txt")
  fi
  ortlib=$ort_gpu_dir/libonnxruntime.so
  [ -e "$ortlib" ] || ortlib=$(ls "$ort_gpu_dir"/libonnxruntime.so.* 2>/dev/null | head -1)
  if [ -z "$ortlib" ] || [ ! -e "$ort_gpu_dir/libonnxruntime_providers_cuda.so" ]; then
    slag_setup_fail "$ort_gpu_dir lacks libonnxruntime.so or libonnxruntime_providers_cuda.so"
    return 1
  fi
  cudalibs=$(slag_torch_cuda_libs "$cuda_major")
  cudafrom=${cudalibs:+torch ($SLAG_PYTHON)}
  # Libraries the CUDA provider still cannot find (the driver's libcuda.so.1 aside), e.g. cuRAND,
  # which some torch wheels do not ship.
  missing=$(LD_LIBRARY_PATH=$ort_gpu_dir${cudalibs:+:$cudalibs} ldd "$ort_gpu_dir/libonnxruntime_providers_cuda.so" 2>/dev/null \
    | awk '/not found/ && $1 != "libcuda.so.1" {print $1}' | paste -sd' ')
  if { [ -z "$cudalibs" ] || [ -n "$missing" ]; } && [ -z "${SLAG_ORT_GPU_DIR:-}" ]; then
    cuda_libs_dir=$HOME/.cache/slag/cuda$cuda_major
    if ! cmp -s "$ort_gpu_dir/cuda-requirements.txt" "$cuda_libs_dir/.requirements.txt"; then
      PIP_ROOT_USER_ACTION=ignore python3 -m pip install -q --disable-pip-version-check \
        --no-warn-script-location --target "$cuda_libs_dir" -r "$ort_gpu_dir/cuda-requirements.txt" \
        && cp "$ort_gpu_dir/cuda-requirements.txt" "$cuda_libs_dir/.requirements.txt" \
        || { slag_setup_fail "pip could not install the CUDA $cuda_major libraries into $cuda_libs_dir"; return 1; }
    fi
    cudalibs=${cudalibs:+$cudalibs:}$(find "$cuda_libs_dir/nvidia" -name 'lib*.so*' -printf '%h\n' | sort -u | paste -sd:)
    cudafrom="${cudafrom:+$cudafrom + }$cuda_libs_dir"
  elif [ -n "$missing" ] || [ -z "$cudalibs" ]; then
    echo "setup: warning: the CUDA provider in $ort_gpu_dir misses ${missing:-the CUDA $cuda_major libraries} (no torch for CUDA $cuda_major in $SLAG_PYTHON has them): add their folders to LD_LIBRARY_PATH" >&2
  fi
  export LD_LIBRARY_PATH=$ort_gpu_dir${cudalibs:+:$cudalibs}${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
  export ORT_DYLIB_PATH=$ortlib
  echo "setup: GPU: ONNX Runtime CUDA provider from $ort_gpu_dir, CUDA $cuda_major libraries from ${cudafrom:-nowhere}" >&2
  # The NVIDIA Vulkan driver file that works without a display (scripts/vulkan-icd.sh says why).
  icd=$(bash "$root/scripts/vulkan-icd.sh" || true)
  if [ -n "$icd" ]; then
    export VK_DRIVER_FILES=$icd
    echo "setup: GPU: Vulkan driver file $VK_DRIVER_FILES" >&2
  fi
}

# The whole set-up, in order; returns non-zero at the first step that fails.
slag_setup() {
  local root ort_version ort_dir
  root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd) || return 1
  export SLAG_SHARED=${SLAG_SHARED:-$(cd "$root/.." && pwd)/shared}
  if [ ! -d "$SLAG_SHARED" ]; then
    slag_setup_fail "no shared/ folder at $SLAG_SHARED (set SLAG_SHARED)"
    return 1
  fi
  slag_setup_vulkan || return 1
  ort_version=${ORT_VERSION:-1.23.2}
  ort_dir=${ORT_DIR:-$HOME/.cache/slag/onnxruntime-$ort_version-$(uname -m)}
  if [ ! -e "$ort_dir/libonnxruntime.so" ]; then
    bash "$SLAG_SHARED/tools/install-onnxruntime.sh" "$ort_dir" "$ort_version" >/dev/null \
      || { slag_setup_fail "could not install ONNX Runtime $ort_version into $ort_dir"; return 1; }
  fi
  export ORT_DYLIB_PATH=$ort_dir/libonnxruntime.so
  # Mesa's Vulkan loader (wgpu on lavapipe) prints "error: XDG_RUNTIME_DIR is invalid or not set"
  # at every start on machines without a login session (CI, containers): give it a private runtime
  # folder, as a login session would. Other errors still reach stderr.
  if [ -z "${XDG_RUNTIME_DIR:-}" ] || [ ! -d "$XDG_RUNTIME_DIR" ]; then
    export XDG_RUNTIME_DIR=${TMPDIR:-/tmp}/slag-runtime-$(id -u)
    mkdir -p "$XDG_RUNTIME_DIR" && chmod 700 "$XDG_RUNTIME_DIR" \
      || { slag_setup_fail "cannot make $XDG_RUNTIME_DIR"; return 1; }
  fi
  if slag_want_gpu "$@"; then
    slag_setup_gpu "$root" || return 1
  fi
  echo "setup: ORT_DYLIB_PATH=$ORT_DYLIB_PATH SLAG_SHARED=$SLAG_SHARED" >&2
}

slag_setup "$@"
_slag_setup_rc=$?
unset -f slag_setup slag_setup_fail slag_setup_vulkan slag_torch_cuda_libs slag_fetch_ort_gpu \
  slag_want_gpu slag_setup_gpu
eval "$_slag_setup_opts"
unset _slag_setup_opts
if [ "$_slag_setup_rc" -ne 0 ]; then
  unset _slag_setup_rc
  return 1 2>/dev/null || exit 1
fi
unset _slag_setup_rc
