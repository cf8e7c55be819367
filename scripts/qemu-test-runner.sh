#!/usr/bin/env bash
# The cargo runner for the aarch64 test binaries under qemu-user (set by scripts/cross-aarch64.sh):
# runs one test binary under qemu with a time limit and, when it runs past the limit, once more.
#
# Why: qemu-user can deadlock the forked child of a multi-threaded program before the child execs
# (seen in edge/tests/crash_points.rs: the child sat in futex waits for 25 minutes, holding the
# test's store lock, so the next test could not open the store either). The limit ends the whole
# process group: the test binary and every qemu child it started. A hang of the code under test
# hangs both tries, and the step fails with the second try's status.
#
#   scripts/qemu-test-runner.sh TEST_BINARY [ARGS...]
# Environment: SLAG_QEMU_TEST_LIMIT_S (seconds per try, default 420: the slowest edge test binary
# takes about 185 s under qemu on a 2-core machine), SLAG_QEMU (default `qemu-aarch64-static -L /`).
set -uo pipefail
limit=${SLAG_QEMU_TEST_LIMIT_S:-420}
read -r -a qemu <<< "${SLAG_QEMU:-qemu-aarch64-static -L /}"
rc=0
for try in 1 2; do
  # -s KILL: a deadlocked qemu process may never act on a TERM.
  timeout -s KILL "$limit" "${qemu[@]}" "$@"
  rc=$?
  [ "$rc" -eq 124 ] || [ "$rc" -eq 137 ] || exit "$rc"
  echo "qemu-test-runner: $(basename "$1") ran past ${limit} s and was stopped (try $try of 2)" >&2
done
exit "$rc"
