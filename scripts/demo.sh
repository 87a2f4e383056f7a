#!/usr/bin/env bash
# Installs what Crepuscular needs, builds it, and runs the demo on the built-in phantom.
# Outputs land in demo/ (phantom volumes and the plan; open them in 3D Slicer).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install-deps.sh
bash scripts/build.sh
./build/apps/crepuscular demo --out demo "$@"
