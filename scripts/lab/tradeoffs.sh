#!/usr/bin/env bash
# The speed/accuracy trade study, reproducible by one command:
#   bash scripts/lab/tradeoffs.sh [--quick] [more slag-bench tradeoffs arguments]
# builds slag-bench (release; SLAG_BENCH_PROFILE=dev uses the dev build), runs
# `slag-bench tradeoffs` on ../shared/scenes/snowmiku (or the embedded mini scene with --quick),
# writes docs/results/tradeoffs.{md,csv}, then plots docs/results/tradeoffs.png with matplotlib from a venv
# (~/.cache/slag/venv-plot, created on first use). Encode runs are cached under
# target/slag-bench/ (pass --fresh to redo them, --cached-only to tabulate a run cut short).
set -euo pipefail
cd "$(dirname "$0")/../.."
export ORT_DYLIB_PATH="${ORT_DYLIB_PATH:-/opt/ort/libonnxruntime.so}"
if [ ! -f "$ORT_DYLIB_PATH" ] && [ -f scripts/setup.sh ]; then
    # shellcheck disable=SC1091
    source scripts/setup.sh
fi
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"
OUT="${SLAG_TRADEOFFS_OUT:-docs/results}"
PROFILE="${SLAG_BENCH_PROFILE:-release}"
if [ "$PROFILE" = release ]; then
    cargo build --release --workspace --bin slag-bench
    BIN="${CARGO_TARGET_DIR:-target}/release/slag-bench"
else
    cargo build --workspace --bin slag-bench
    BIN="${CARGO_TARGET_DIR:-target}/debug/slag-bench"
fi
SCENE_ARGS=()
case " $* " in
    *" --scene-dir "*) ;;
    *" --quick "*) SCENE_ARGS=(--scene-dir data/snowmiku-mini) ;;
    *) SCENE_ARGS=(--scene-dir ../shared/scenes/snowmiku) ;;
esac
"$BIN" tradeoffs "${SCENE_ARGS[@]}" --out "$OUT" "$@"

VENV="$HOME/.cache/slag/venv-plot"
if [ ! -x "$VENV/bin/python3" ] || ! "$VENV/bin/python3" -c 'import matplotlib' 2>/dev/null; then
    python3 -m venv "$VENV"
    "$VENV/bin/pip" install --quiet matplotlib
fi
"$VENV/bin/python3" scripts/lab/plot_tradeoffs.py "$OUT/tradeoffs.csv" "$OUT/tradeoffs.png"
echo "wrote $OUT/tradeoffs.md, $OUT/tradeoffs.csv, $OUT/tradeoffs.png"
