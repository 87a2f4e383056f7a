#!/usr/bin/env bash
# Installs every Debian package Crepuscular needs to build, test and run. Idempotent and
# non-interactive: packages already present are not fetched again.
set -euo pipefail

packages=(
  build-essential cmake ninja-build pkg-config git ca-certificates
  clang libclang-rt-dev libomp-dev  # the fuzz build (scripts/fuzz.sh): libFuzzer, sanitizers
  libinsighttoolkit5-dev libeigen3-dev zlib1g-dev
  libcli11-dev libspdlog-dev libfmt-dev nlohmann-json3-dev
  libgtest-dev libgmock-dev
  libopencv-dev libapriltag-dev libceres-dev libjpeg-dev
  libglfw3-dev libglm-dev libgl-dev libegl-dev libv4l-dev
  xvfb xauth libgl1-mesa-dri libegl-mesa0
  libopenigtlink-dev openigtlink-examples  # OpenIGTLink; tests build two of its examples
  python3-nibabel python3-numpy python3-jsonschema
  python3-vtk9  # tests: area_safety.vtk read back by VTK's own reader
)

# A machine whose /etc/alternatives is gone has dangling links for BLAS, LAPACK (which Ceres and
# OpenCV load) and the compilers, while dpkg still lists every package as installed: let
# update-alternatives make the links again from dpkg's own records.
if [ -d /var/lib/dpkg/alternatives ] && [ ! -d /etc/alternatives ] && [ "$(id -u)" -eq 0 ]; then
  echo "install-deps: /etc/alternatives is missing; recreating the links dpkg records"
  mkdir -p /etc/alternatives
  for name in /var/lib/dpkg/alternatives/*; do
    update-alternatives --auto "$(basename "$name")" >/dev/null 2>&1 || true
  done
fi

missing=()
for p in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done

if [ ${#missing[@]} -eq 0 ]; then
  echo "install-deps: all ${#packages[@]} packages present"
  exit 0
fi

SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
echo "install-deps: installing ${#missing[@]} packages: ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
echo "install-deps: done"
