#!/usr/bin/env bash
# Cross-build `slag-edge` for the Jetson Orin (aarch64-unknown-linux-gnu, JetPack 6 = Ubuntu 22.04,
# glibc 2.35) on an x86_64 Debian 12 (bookworm) machine, from Debian's and PyPI's registries only
# (no Docker, no rustup target download), then check the result:
#   1. installs (idempotently, only what is missing) Debian's Rust 1.96 (`rustc-web`, `cargo-web`) with
#      the arm64 standard library (`libstd-rust-web-dev:arm64`), the aarch64 GCC/G++ cross compilers
#      (ring's C/asm, onig's C, tokenizers' C++), the arm64 C/C++ runtime (for running under qemu)
#      and qemu-user >= 8 (bookworm's qemu 7.2 was seen to segfault inside ONNX Runtime's arm64
#      start-up, so the bookworm-backports qemu 10 is used; the source is added when apt lacks it);
#   2. fetches the arm64 ONNX Runtime library (PyPI `onnxruntime` manylinux aarch64 wheel) into
#      ~/.cache/slag/onnxruntime-VERSION-aarch64 (the name scripts/setup.sh uses on an aarch64 host);
#   3. builds and runs the edge crate's tests under qemu-user (ORT_DYLIB_PATH = the arm64 library),
#      release profile;
#   4. builds the binary that ships with the `jetson` profile (release with whole-program LTO and
#      one codegen unit: a smaller binary, see docs/results/edge-binary.md), runs
#      `slag-edge --version` / `--help` under qemu;
#   5. glibc guard: fails when the binary (or the arm64 ORT library) needs a GLIBC_ symbol newer
#      than 2.35 (JetPack 6).
# The rustup toolchain stays the user's default for native builds: this script calls Debian's
# /usr/bin/cargo and /usr/bin/rustc explicitly and builds into its own target dir.
#
#   bash scripts/cross-aarch64.sh            # everything above
#   SLAG_CROSS_NO_TEST=1 bash scripts/cross-aarch64.sh   # build + guard only (no test run)
#   eval "$(bash scripts/cross-aarch64.sh --env)"        # the cross environment, for other cargo runs
# Environment: SLAG_CROSS_TARGET_DIR (default target/aarch64), SLAG_CROSS_PROFILE (the binary's
# profile: jetson|release|dev, default jetson; the tests run in release, or in dev with dev),
# SLAG_GLIBC_MAX (default 2.35), ORT_VERSION (default 1.23.2), SLAG_SHARED.
# Output: target/aarch64/aarch64-unknown-linux-gnu/jetson/slag-edge (see jetson/README.md).
set -euo pipefail
SLAG_ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$SLAG_ROOT"
TARGET=aarch64-unknown-linux-gnu
GLIBC_MAX=${SLAG_GLIBC_MAX:-2.35}
PROFILE=${SLAG_CROSS_PROFILE:-jetson}
ORT_VERSION=${ORT_VERSION:-1.23.2}
export SLAG_SHARED=${SLAG_SHARED:-$(cd "$SLAG_ROOT/.." && pwd)/shared}
say() { echo "cross-aarch64: $*" >&2; }
die() { echo "cross-aarch64: ERROR: $*" >&2; exit 1; }
t0=$(date +%s)

# ---- the cross environment (also printed by --env) ---------------------------------------------
CARGO=/usr/bin/cargo
export RUSTC=/usr/bin/rustc RUSTDOC=/usr/bin/rustdoc
ORT_DIR=${ORT_DIR_AARCH64:-$HOME/.cache/slag/onnxruntime-$ORT_VERSION-aarch64}
export CARGO_TARGET_DIR=${SLAG_CROSS_TARGET_DIR:-$SLAG_ROOT/target/aarch64}
export CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_LINKER=aarch64-linux-gnu-gcc
export CC_aarch64_unknown_linux_gnu=aarch64-linux-gnu-gcc
export CXX_aarch64_unknown_linux_gnu=aarch64-linux-gnu-g++
export AR_aarch64_unknown_linux_gnu=aarch64-linux-gnu-ar
# `-L /`: the arm64 loader and libraries of the multiarch packages (libc6:arm64, libstdc++6:arm64)
# live under /lib/aarch64-linux-gnu. (`-L /usr/aarch64-linux-gnu` makes threaded binaries hang in
# pthread_create.)
QEMU="qemu-aarch64-static -L /"
# Test binaries run through a wrapper that stops one running past its time limit and runs it once
# more (qemu-user can deadlock a forked child before its exec; see the wrapper's header).
export SLAG_QEMU=$QEMU
export CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_RUNNER=$SLAG_ROOT/scripts/qemu-test-runner.sh
# A test under qemu-user cannot exec an aarch64 program itself (the host kernel has no binfmt_misc
# entry here: the child fails with status 127). Tests that spawn the binary
# (env!("CARGO_BIN_EXE_slag-edge"), current_exe()) must prefix this runner when it is set.
export SLAG_TEST_RUNNER=$QEMU
# Property tests run emulated (several times slower): fewer cases than natively, unless set.
export PROPTEST_CASES=${PROPTEST_CASES:-64}
export ORT_DYLIB_PATH=$ORT_DIR/libonnxruntime.so
if [ "${1:-}" = --env ]; then
  # For running other cargo commands by hand: eval "$(bash scripts/cross-aarch64.sh --env)"
  for v in RUSTC RUSTDOC CARGO_TARGET_DIR CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_LINKER \
    CC_aarch64_unknown_linux_gnu CXX_aarch64_unknown_linux_gnu AR_aarch64_unknown_linux_gnu \
    CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_RUNNER SLAG_QEMU SLAG_TEST_RUNNER ORT_DYLIB_PATH SLAG_SHARED; do
    printf 'export %s=%q\n' "$v" "${!v}"
  done
  echo "# then: /usr/bin/cargo test --release -p slag-edge --target $TARGET"
  echo "#   or: /usr/bin/cargo build --profile jetson -p slag-edge --target $TARGET --bin slag-edge"
  exit 0
fi

# ---- 1. packages --------------------------------------------------------------------------------
[ "$(dpkg --print-architecture 2>/dev/null)" = amd64 ] ||
  die "this script cross-builds from an x86_64 Debian 12 host (dpkg architecture amd64)"
SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO=sudo
apt_updated=0
apt_update() { [ $apt_updated -eq 1 ] || { $SUDO apt-get update -qq; apt_updated=1; }; }
apt_install() {
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "$@" >/dev/null
}
if ! dpkg --print-foreign-architectures | grep -qx arm64; then
  say "adding the arm64 dpkg architecture"
  $SUDO dpkg --add-architecture arm64
  apt_updated=0
fi
need=()
# libc6-dev-arm64-cross (the linker's sysroot, /usr/aarch64-linux-gnu) is only a Recommends of
# gcc-aarch64-linux-gnu, hence named; the multiarch libc6/libgcc-s1/libstdc++6:arm64 serve qemu.
for p in rustc-web cargo-web libstd-rust-web-dev:arm64 gcc-aarch64-linux-gnu g++-aarch64-linux-gnu \
  binutils-aarch64-linux-gnu libc6-dev-arm64-cross libc6:arm64 libgcc-s1:arm64 libstdc++6:arm64; do
  dpkg -s "$p" >/dev/null 2>&1 || need+=("$p")
done
if [ ${#need[@]} -gt 0 ]; then
  say "installing ${need[*]}"
  apt_update
  apt_install "${need[@]}"
fi
qemu_major() {
  command -v qemu-aarch64-static >/dev/null || { echo 0; return; }
  qemu-aarch64-static --version | sed -n 's/.*version \([0-9]*\)\..*/\1/p' | head -n1
}
if [ "$(qemu_major)" -lt 8 ]; then
  codename=$(. /etc/os-release && echo "${VERSION_CODENAME:-}")
  if [ "$codename" = bookworm ]; then
    if ! apt-cache policy qemu-user-static 2>/dev/null | grep -q bookworm-backports; then
      say "adding the bookworm-backports apt source (for qemu-user 10)"
      printf '%s\n' 'Types: deb' 'URIs: http://deb.debian.org/debian' 'Suites: bookworm-backports' \
        'Components: main' 'Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg' |
        $SUDO tee /etc/apt/sources.list.d/bookworm-backports.sources >/dev/null
      apt_updated=0
    fi
    apt_update
    say "installing qemu-user-static from bookworm-backports"
    apt_install -t bookworm-backports qemu-user-static
  else
    apt_update
    apt_install qemu-user-static
  fi
  [ "$(qemu_major)" -ge 8 ] ||
    die "qemu-aarch64-static $(qemu_major).x is too old (< 8 segfaults in ONNX Runtime's start-up)"
fi
"$RUSTC" --print sysroot >/dev/null
[ -d "$("$RUSTC" --print sysroot)/lib/rustlib/$TARGET/lib" ] ||
  die "Debian's rustc has no $TARGET standard library (package libstd-rust-web-dev:arm64)"
say "$("$RUSTC" -V) / $("$CARGO" -V) / $(qemu-aarch64-static --version | head -n1)"

# ---- 2. arm64 ONNX Runtime ----------------------------------------------------------------------
if [ ! -e "$ORT_DIR/libonnxruntime.so" ]; then
  [ -f "$SLAG_SHARED/tools/install-onnxruntime.sh" ] ||
    die "no $SLAG_SHARED/tools/install-onnxruntime.sh (set SLAG_SHARED)"
  say "fetching ONNX Runtime $ORT_VERSION (PyPI manylinux aarch64 wheel) into $ORT_DIR"
  bash "$SLAG_SHARED/tools/install-onnxruntime.sh" "$ORT_DIR" "$ORT_VERSION" aarch64 >/dev/null
fi
ORT_LIB=$(readlink -f "$ORT_DIR/libonnxruntime.so")

# ---- 3./4. tests under qemu, build, run ---------------------------------------------------------
# The tests run in the release profile: the `jetson` profile's whole-program LTO would link every
# test binary that way too (many minutes each on 2 cores), and LTO changes no behaviour.
case "$PROFILE" in
  jetson) test_prof=(--release); prof=(--profile jetson); outdir=jetson ;;
  release) test_prof=(--release); prof=(--release); outdir=release ;;
  dev) test_prof=(); prof=(); outdir=debug ;;
  *) die "SLAG_CROSS_PROFILE=$PROFILE: expected jetson, release or dev" ;;
esac
cargo_x() { "$CARGO" "$@" --locked -p slag-edge --target "$TARGET"; }
if [ "${SLAG_CROSS_NO_TEST:-0}" != 1 ]; then
  say "building and running the edge tests under qemu (ORT_DYLIB_PATH=$ORT_DYLIB_PATH)"
  cargo_x test "${test_prof[@]}"
fi
# The plain build after the tests: `cargo test` unifies the dev-dependencies' features (proptest's
# rand, ...) and leaves its own build of the binary at the output path; this one is what ships.
say "building slag-edge ($PROFILE profile) for $TARGET"
tb=$(date +%s)
cargo_x build "${prof[@]}" --bin slag-edge
say "slag-edge ($PROFILE profile) built in $(( $(date +%s) - tb )) s"
BIN=$CARGO_TARGET_DIR/$TARGET/$outdir/slag-edge
file_out=$(file -b "$BIN" 2>/dev/null || true)
say "binary: $BIN ($(du -h "$BIN" | cut -f1)) $file_out"
$QEMU "$BIN" --version
$QEMU "$BIN" --help >/dev/null || die "slag-edge --help failed under qemu"

# ---- 5. glibc guard -----------------------------------------------------------------------------
newest() { aarch64-linux-gnu-objdump -T "$1" | grep -o 'GLIBC_[0-9][0-9.]*' | sed 's/GLIBC_//' |
  sort -uV | tail -n1; }
check_glibc() {
  local f=$1 v
  v=$(newest "$f")
  [ -n "$v" ] || die "no GLIBC_ symbol versions found in $f (objdump failed?)"
  if [ "$(printf '%s\n%s\n' "$v" "$GLIBC_MAX" | sort -V | tail -n1)" != "$GLIBC_MAX" ]; then
    echo "cross-aarch64: ERROR: $f needs glibc $v, newer than $GLIBC_MAX (SLAG_GLIBC_MAX; 2.35 = JetPack 6 / Ubuntu 22.04)." >&2
    echo "  symbols needing more than $GLIBC_MAX:" >&2
    aarch64-linux-gnu-objdump -T "$f" | grep 'GLIBC_' | awk -v max="$GLIBC_MAX" '{
      for (i = 1; i <= NF; i++) if ($i ~ /GLIBC_/) { v = $i; gsub(/[()]|GLIBC_/, "", v); print v, $NF } }' |
      sort -V | while read -r ver sym; do
        [ "$(printf '%s\n%s\n' "$ver" "$GLIBC_MAX" | sort -V | tail -n1)" = "$GLIBC_MAX" ] ||
          echo "    $sym@GLIBC_$ver" >&2
      done
    echo "  Link against an older glibc (see jetson/README.md, 'glibc')." >&2
    exit 1
  fi
  say "glibc guard: $(basename "$f"): newest GLIBC_ symbol version $v (limit $GLIBC_MAX): ok"
}
check_glibc "$BIN"
check_glibc "$ORT_LIB"
say "done in $(( $(date +%s) - t0 )) s"
