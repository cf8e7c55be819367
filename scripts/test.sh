#!/usr/bin/env bash
# The test command: set up (idempotent), then every test of the workspace, the unused-dependency
# check (cargo machete), then the aarch64
# (Jetson) cross build of slag-edge with its tests under qemu and the glibc guard
# (scripts/cross-aarch64.sh; x86_64 Debian 12 hosts). The web page's browser test needs chromium,
# node and the vendored viewer: scripts/web-setup.sh (SLAG_SKIP_WEB=1 skips it). SLAG_SKIP_CROSS=1 skips the cross step
# (quick local runs); CI (.ci/run) always runs it, and with SLAG_FREE_NATIVE_TARGET=1 removes the
# native build before it (a small disk). Before the tests, scripts/lab/check-links.py checks
# the docs' relative links. Arguments go to `cargo test`.
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/setup.sh
if [ "${SLAG_SKIP_WEB:-0}" = 1 ]; then
  echo "test: SLAG_SKIP_WEB=1: browser test of the web page skipped" >&2
else
  . scripts/web-setup.sh
fi
# --no-fail-fast: every test binary runs even after one fails, and the cross step below runs
# whatever the native result, so one run shows every failure; the exit status is still non-zero.
disk_free() { df -h "${CARGO_TARGET_DIR:-target}" 2>/dev/null | awk 'NR==2 {print $4 " free on " $6}'; }
mkdir -p "${CARGO_TARGET_DIR:-target}"
echo "test: disk before the build: $(disk_free)" >&2
native=0
# The docs' relative links and section anchors (pure Python, about a second): a broken one fails
# the run like a failed test.
python3 scripts/lab/check-links.py || native=$?
cargo test --workspace --locked --no-fail-fast "$@" || native=$?
[ "${SLAG_SKIP_PROBE:-0}" = 1 ] || bash scripts/probe.sh --short --debug || native=$?
echo "test: disk after the native tests: $(disk_free)" >&2
# No dependency declared and unused: cargo-machete (installed once when missing, about two
# minutes) reads every crate's sources against its Cargo.toml.
unused=0
if ! command -v cargo-machete >/dev/null 2>&1; then
  echo "test: installing cargo-machete for the unused-dependency check" >&2
  cargo install --locked cargo-machete || unused=$?
fi
if [ "$unused" -eq 0 ]; then
  cargo machete --skip-target-dir || unused=$?
fi
cross=0
# CI's machine has a small disk: the native build is done with, so its files make room for the
# cross build's (SLAG_FREE_NATIVE_TARGET=1, set by .ci/run; a developer's target stays).
if [ "${SLAG_FREE_NATIVE_TARGET:-0}" = 1 ] && [ "${SLAG_SKIP_CROSS:-0}" != 1 ]; then
  rm -rf "${CARGO_TARGET_DIR:-target}/debug"
  echo "test: native build removed for the cross step: $(disk_free)" >&2
fi
if [ "${SLAG_SKIP_CROSS:-0}" = 1 ]; then
  echo "test: SLAG_SKIP_CROSS=1: aarch64 cross build skipped" >&2
elif [ "$(uname -m)" != x86_64 ]; then
  echo "test: $(uname -m) host: the native build above is the Jetson build; cross step skipped" >&2
else
  bash scripts/cross-aarch64.sh || cross=$?
fi
if [ "$native" -ne 0 ] || [ "$unused" -ne 0 ] || [ "$cross" -ne 0 ]; then
  echo "test: FAILED (native cargo test exit $native, unused-dependency check exit $unused, aarch64 cross step exit $cross)" >&2
  exit 1
fi
echo "test: all passed (native and aarch64 cross step)" >&2
