#!/usr/bin/env bash
# The test command: set up (idempotent), then every test of the workspace, then the aarch64
# (Jetson) cross build of slag-edge with its tests under qemu and the glibc guard
# (scripts/cross-aarch64.sh; x86_64 Debian 12 hosts). SLAG_SKIP_CROSS=1 skips the cross step
# (quick local runs); CI (.ci/run) always runs it. Arguments go to `cargo test`.
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/setup.sh
cargo test --workspace --locked "$@"
if [ "${SLAG_SKIP_CROSS:-0}" = 1 ]; then
  echo "test: SLAG_SKIP_CROSS=1: aarch64 cross build skipped" >&2
elif [ "$(uname -m)" != x86_64 ]; then
  echo "test: $(uname -m) host: the native build above is the Jetson build; cross step skipped" >&2
else
  bash scripts/cross-aarch64.sh
fi
