#!/usr/bin/env bash
# Picks the NVIDIA Vulkan driver file (ICD) for a headless machine and prints the path to put in
# VK_DRIVER_FILES; prints nothing (exit 0) when there is no NVIDIA driver to pick.
#
# Why: the NVIDIA driver's own ICD (`nvidia_icd.json`) names `libGLX_nvidia.so.0`. On headless
# and container GPU hosts (no X server, the driver's libraries mounted under /usr/local/nvidia)
# that library fails `vkCreateInstance`, so wgpu sees no GPU and slag would fall back to Mesa's
# CPU driver or stop. The same driver's `libEGL_nvidia.so.0` holds the same Vulkan entry points
# and needs no display: an ICD file naming it works there, and where GLX works too.
#
# The rule, in order:
#   1. VK_DRIVER_FILES (or the older VK_ICD_FILENAMES) already set: print it, change nothing.
#   2. No NVIDIA ICD file in the ICD folders: print nothing.
#   3. An NVIDIA ICD file that already names libEGL_nvidia: print it.
#   4. libEGL_nvidia.so.0 found (beside the ICD's library, in /usr/local/nvidia/lib64, or a
#      system library folder): write an ICD file naming it by absolute path, with the
#      api_version of the driver's own file, to $SLAG_ICD_DIR (default ~/.cache/slag), print it.
#   5. Otherwise print the driver's own ICD file.
#
#   VK_DRIVER_FILES=$(bash scripts/vulkan-icd.sh) && export VK_DRIVER_FILES
#
# SLAG_ICD_ROOT=DIR looks for every folder under DIR instead of / (how the tests fake a host).
set -euo pipefail
if [ -n "${VK_DRIVER_FILES:-}" ]; then echo "$VK_DRIVER_FILES"; exit 0; fi
if [ -n "${VK_ICD_FILENAMES:-}" ]; then echo "$VK_ICD_FILENAMES"; exit 0; fi
root=${SLAG_ICD_ROOT:-}
icd_dirs=(/usr/local/nvidia/share/vulkan/icd.d /etc/vulkan/icd.d /usr/share/vulkan/icd.d
          /usr/local/share/vulkan/icd.d)
lib_dirs=(/usr/local/nvidia/lib64 /usr/local/nvidia/lib /usr/lib/x86_64-linux-gnu
          /usr/lib/aarch64-linux-gnu /usr/lib64 /usr/lib /usr/lib/aarch64-linux-gnu/tegra)
# The library_path and api_version fields of an ICD file (one JSON object; no jq on a bare host).
field() { sed -n "s/.*\"$1\"[[:space:]]*:[[:space:]]*\"\([^\"]*\)\".*/\1/p" "$2" | head -1; }
own=""
for d in "${icd_dirs[@]}"; do
  for f in "$root$d"/*.json; do
    [ -f "$f" ] || continue
    lib=$(field library_path "$f")
    case "$lib" in
      *EGL_nvidia*) echo "$f"; exit 0 ;;
      *nvidia*) [ -n "$own" ] || own=$f ;;
    esac
  done
done
[ -n "$own" ] || exit 0
lib=$(field library_path "$own")
api=$(field api_version "$own"); api=${api:-1.3.0}
candidates=()
case "$lib" in /*) candidates+=("$(dirname "$lib")") ;; esac
candidates+=("${lib_dirs[@]}")
for d in "${candidates[@]}"; do
  egl=$root$d/libEGL_nvidia.so.0
  if [ -e "$egl" ]; then
    out_dir=${SLAG_ICD_DIR:-$HOME/.cache/slag}
    mkdir -p "$out_dir"
    out=$out_dir/nvidia_icd_egl.json
    printf '{"file_format_version":"1.0.1","ICD":{"library_path":"%s","api_version":"%s"}}\n' \
      "$d/libEGL_nvidia.so.0" "$api" > "$out.partial"
    mv "$out.partial" "$out"
    echo "$out"
    exit 0
  fi
done
echo "$own"
