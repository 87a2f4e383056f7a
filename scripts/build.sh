#!/usr/bin/env bash
# Configures and builds Crepuscular (Release) into build/. Extra arguments go to CMake.
# CREPUSCULAR_BUILD_TARGET=NAME builds that target (and what it needs) only; unset: everything.
set -euo pipefail
cd "$(dirname "$0")/.."
jobs=$(nproc 2>/dev/null || echo 2)
launcher=()
# ccache, where installed, makes rebuilds after a switch of branch or folder cheap.
if command -v ccache >/dev/null 2>&1; then launcher=(-DCMAKE_CXX_COMPILER_LAUNCHER=ccache); fi
cmake -S . -B build -G Ninja -DCMAKE_BUILD_TYPE=Release "${launcher[@]}" "$@" >/dev/null
target=()
if [ -n "${CREPUSCULAR_BUILD_TARGET:-}" ]; then target=(--target "$CREPUSCULAR_BUILD_TARGET"); fi
cmake --build build -j "$jobs" "${target[@]}"
