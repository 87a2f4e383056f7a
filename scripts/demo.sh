#!/usr/bin/env bash
# Installs what Crepuscular needs, builds it, and runs the main job on the built-in data
# (`crepuscular demo`, about 1-2 minutes on 2 cores), writing demo/:
#   demo/report.md      the plan's numbers and the needle's safety along the recording
#   demo/overlay.mp4    the guidance overlay on the synthetic recording (headless rendering)
#   demo/snapshots      the overlay when the needle is on the safe path and on the vessel
#   demo/slices         axial, coronal, sagittal and oblique views through the largest safe region
#   demo/plan           path safety volumes, their classes and the area safety model (open in 3D Slicer)
#   demo/3d             the 3D planning view from four sides
#   demo/phantom        the phantom abdomen (CT, labels, tumor, vulnerability table)
#   demo/recording      the synthetic camera recording, with ground truth
#   demo/setup          camera, registration and needle calibration files of the recording
# Extra arguments go to `crepuscular demo` (e.g. --mode fast).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install-deps.sh
# The demo needs the command only, not the tests and benchmarks.
CREPUSCULAR_BUILD_TARGET=crepuscular bash scripts/build.sh
./build/apps/crepuscular demo --out demo "$@"
echo "demo: outputs in demo/ (start with demo/report.md, demo/3d/ and demo/overlay.mp4; look at"
echo "      the plan with ./build/apps/crepuscular view --plan demo/plan, or open"
echo "      demo/phantom/ct.nii.gz with demo/plan/path_safety_svv_classes.seg.nrrd in 3D Slicer)"
