#!/usr/bin/env bash
# Idempotent set-up for the browser test of the web page (tests/tests/web_viewer.rs): Debian's
# chromium, nodejs and npm, then the vendored viewer + playwright-core (scripts/web-vendor.sh).
# Sourced by scripts/test.sh, which then exports SLAG_WEB_E2E=1 (a missing piece fails the test).
# SLAG_SKIP_WEB=1 skips it (the test then reports SKIPPED).
#
# Safe to source, as scripts/setup.sh: the caller's shell options are the same after it as before,
# and a failure returns non-zero with a message instead of closing the caller's shell (run as
# `bash scripts/web-setup.sh`, it exits non-zero). It exports only SLAG_WEB_E2E.

# `set +o` in a command substitution reports errexit off (bash does not pass -e into it): $- has it.
_slag_web_opts=$(set +o)
case $- in *e*) _slag_web_opts+=$'\nset -e' ;; esac
set +e +u -o pipefail

# Installs what is missing of chromium, nodejs and npm (apt; sudo when not root), vendors the
# viewer, then exports SLAG_WEB_E2E=1.
slag_web_setup() {
  local root need=() sudo=""
  root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd) || return 1
  command -v chromium >/dev/null 2>&1 || need+=(chromium)
  command -v node >/dev/null 2>&1 || need+=(nodejs)
  command -v npm >/dev/null 2>&1 || need+=(npm)
  if [ ${#need[@]} -gt 0 ]; then
    [ "$(id -u)" -eq 0 ] || sudo=sudo
    $sudo apt-get update -qq \
      || { echo "web-setup: apt-get update failed" >&2; return 1; }
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends \
      "${need[@]}" >/dev/null \
      || { echo "web-setup: apt-get could not install ${need[*]}" >&2; return 1; }
  fi
  bash "$root/scripts/web-vendor.sh" >&2 \
    || { echo "web-setup: scripts/web-vendor.sh failed (see above)" >&2; return 1; }
  export SLAG_WEB_E2E=1
}

slag_web_setup
_slag_web_rc=$?
unset -f slag_web_setup
eval "$_slag_web_opts"
unset _slag_web_opts
if [ "$_slag_web_rc" -ne 0 ]; then
  unset _slag_web_rc
  return 1 2>/dev/null || exit 1
fi
unset _slag_web_rc
