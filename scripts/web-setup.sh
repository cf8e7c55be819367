#!/usr/bin/env bash
# Idempotent set-up for the browser test of the web page (tests/tests/web_viewer.rs): Debian's
# chromium, nodejs and npm, then the vendored viewer + playwright-core (scripts/web-vendor.sh).
# Sourced by scripts/test.sh, which then exports SLAG_WEB_E2E=1 (a missing piece fails the test).
# SLAG_SKIP_WEB=1 skips it (the test then reports SKIPPED).
set -euo pipefail
_web_root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
_need=()
command -v chromium >/dev/null 2>&1 || _need+=(chromium)
command -v node >/dev/null 2>&1 || _need+=(nodejs)
command -v npm >/dev/null 2>&1 || _need+=(npm)
if [ ${#_need[@]} -gt 0 ]; then
  _sudo=""; [ "$(id -u)" -eq 0 ] || _sudo=sudo
  $_sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $_sudo apt-get install -y -qq --no-install-recommends "${_need[@]}" >/dev/null
fi
bash "$_web_root/scripts/web-vendor.sh" >&2
export SLAG_WEB_E2E=1
