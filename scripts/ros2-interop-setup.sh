#!/usr/bin/env bash
# The Python side of the ROS 2 interop test (edge/tests/ros2_interop.rs): a venv holding Eclipse
# Cyclone DDS's Python binding (an independent DDS) and rosbags (an independent ROS 2 CDR
# decoder with the Humble message definitions). Idempotent: the venv is cached under
# ~/.cache/slag/ (or $SLAG_CACHE) and reused while its pinned versions are installed.
#
# Prints the venv's python on its last line of stdout. Exit status 0: ready; 2: the install is
# impossible here (no python3 ≥ 3.8 with venv, or PyPI unreachable); anything else: a fault.
set -euo pipefail

CYCLONEDDS_VERSION=11.0.1
ROSBAGS_VERSION=0.11.9
cache="${SLAG_CACHE:-$HOME/.cache/slag}"
venv="$cache/ros2-interop-venv-cyclonedds${CYCLONEDDS_VERSION}-rosbags${ROSBAGS_VERSION}"
py="$venv/bin/python"

if [ -x "$py" ] && "$py" -c 'import cyclonedds, rosbags' 2>/dev/null; then
    echo "$py"
    exit 0
fi

python=""
for cand in python3.12 python3.11 python3.10 python3; do
    if command -v "$cand" >/dev/null 2>&1 \
        && "$cand" -c 'import sys, venv; sys.exit(0 if sys.version_info >= (3, 8) else 1)' 2>/dev/null; then
        python="$cand"
        break
    fi
done
if [ -z "$python" ]; then
    echo "ros2-interop-setup: no python3 (>= 3.8, with the venv module) on PATH" >&2
    exit 2
fi

mkdir -p "$cache"
tmp="$venv.partial.$$"
rm -rf "$tmp"
if ! "$python" -m venv "$tmp" >&2; then
    echo "ros2-interop-setup: $python -m venv failed" >&2
    rm -rf "$tmp"
    exit 2
fi
# Binary wheels only: cyclonedds ships manylinux wheels with the Cyclone DDS C library inside;
# building it from source would need a C toolchain and CMake.
if ! "$tmp/bin/python" -m pip install --quiet --disable-pip-version-check --only-binary=:all: \
    "cyclonedds==$CYCLONEDDS_VERSION" "rosbags==$ROSBAGS_VERSION" >&2; then
    echo "ros2-interop-setup: pip could not install cyclonedds==$CYCLONEDDS_VERSION and" \
        "rosbags==$ROSBAGS_VERSION (offline, or no wheel for this platform)" >&2
    rm -rf "$tmp"
    exit 2
fi
rm -rf "$venv"
mv "$tmp" "$venv"
# A venv's scripts name its folder; the python binary itself does not, so the moved venv works.
"$py" -c 'import cyclonedds, rosbags' >&2
echo "$py"
