#!/usr/bin/env bash
# Installs what Crepuscular needs, builds it, and runs every test suite with CTest.
# GPU tests skip themselves where no CUDA device is found. Then fuzzes the readers (clang build).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install-deps.sh
bash scripts/build.sh
jobs=$(nproc 2>/dev/null || echo 2)
ctest --test-dir build --output-on-failure -j "$jobs" "$@"
# Every reader of outside data under libFuzzer, a bounded and reproducible run (tests/fuzz).
bash scripts/fuzz.sh --ci
