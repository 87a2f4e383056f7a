#!/usr/bin/env bash
# Installs what Crepuscular needs, builds it, and runs the main job on the built-in data:
#   demo/phantom    the phantom abdomen (CT, labels, tumor, vulnerability table)
#   demo/plan       path safety volumes and the area safety model around its tumor
#   demo/slices     axial, coronal and sagittal views through the tumor, and an oblique view
#                   along the largest safe region
#   demo/recording  a synthetic camera recording: patient board and a needle approaching
#   demo/poses.csv  the boards tracked in that recording (T_cam_board, with the error against the
#                   recording's ground truth printed)
# Extra arguments go to `crepuscular demo` (e.g. --mode fast).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install-deps.sh
bash scripts/build.sh
crepuscular=./build/apps/crepuscular
$crepuscular demo --out demo "$@"
rm -rf demo/slices demo/recording demo/poses.csv
$crepuscular slices --plan demo/plan --ct demo/phantom/ct.nii.gz --region 0 \
  --planes axial,coronal,sagittal,oblique --out demo/slices
$crepuscular synth --out demo/recording
$crepuscular track --source recording:demo/recording --out demo/poses.csv
echo "demo: outputs in demo/ (open demo/phantom/ct.nii.gz, demo/plan/path_safety_svv.nii.gz and"
echo "      demo/plan/area_safety.vtk in 3D Slicer; the slice views are PNGs in demo/slices)"
