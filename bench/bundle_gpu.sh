#!/usr/bin/env bash
# Builds the GPU tests and benchmarks here (nvcc, sm_90) and bundles them with the shared libraries
# they need into .device/, which the GPU machine receives as a carried path (it has no package
# registry). Then run, on the GPU machine: bash bench/run_gpu.sh
set -euo pipefail
cd "$(dirname "$0")/.."
build="${BUILD_DIR:-build-device}"
cmake -S . -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=Release -DCREPUSCULAR_CUDA=ON \
  -DCMAKE_CUDA_ARCHITECTURES=90 >/dev/null
targets=(path_safety_cuda_test path_safety_test path_safety_fast_test bench_path_safety
         bench_sampling_rate)
# BUNDLE=overlay: the overlay renderer benchmark alone (with OpenCV, GLFW, X11 and libglvnd it does
# not fit beside the CUDA programs in the 64 MiB a carried path may hold).
if [ "${BUNDLE:-}" = overlay ]; then targets=(overlay_bench guide_bench); fi
# BUNDLE=plan: the GPU tests and `crepuscular plan` end to end (bench_plan), compressed.
if [ "${BUNDLE:-}" = plan ]; then
  targets=(path_safety_cuda_test path_safety_test path_safety_fast_test plan_breathing_test
           bench_plan)
fi
# BUNDLE=view: the 3D planning view's benchmark and `crepuscular plan` end to end (the headline
# plan it opens), compressed.
if [ "${BUNDLE:-}" = view ]; then targets=(bench_plan bench_view); fi
cmake --build "$build" -j "$(nproc)" --target "${targets[@]}"
rm -rf .device && mkdir -p .device/bin .device/lib
for t in "${targets[@]}"; do
  find "$build" -type f -name "$t" -perm -u+x -exec cp {} .device/bin/ \;
done
# Shared libraries that are not part of every Linux system or the CUDA driver. libglvnd's libEGL and
# libOpenGL travel too; they load the GPU driver's EGL library (libEGL_nvidia) on the GPU machine.
for b in .device/bin/*; do
  ldd "$b" | awk '/=> \// {print $3}'
done | sort -u | grep -vE '/(libc|libm|libdl|libpthread|librt|ld-linux[^/]*|libcuda)\.so' |
  while read -r lib; do cp -L "$lib" .device/lib/; done
# Symbols are not needed there: the bundle stays within what a call may carry.
strip --strip-unneeded .device/bin/* .device/lib/* 2>/dev/null || true
# WITH_PERF=1: Linux perf and its libraries too (bench/ab_gpu.sh's `profile`), from this machine's
# linux-perf package.
if [ -n "${WITH_PERF:-}" ]; then
  command -v perf >/dev/null || { echo "error: WITH_PERF=1 needs perf (apt-get install linux-perf)" >&2; exit 1; }
  perf_binary=$(readlink -f "$(command -v perf)")
  mkdir -p .device/perf/lib && cp "$perf_binary" .device/perf/perf
  ldd "$perf_binary" | awk '/=> \// {print $3}' |
    grep -vE '/(libc|libm|libstdc\+\+|libgcc_s)\.so' | while read -r lib; do cp -L "$lib" .device/perf/lib/; done
fi
du -sh .device
# The overlay programs' libraries exceed the carry limit uncompressed: carry .device.tar.xz and
# unpack it there (run_gpu.sh does).
if [ "${BUNDLE:-}" = overlay ] || [ "${BUNDLE:-}" = plan ] || [ "${BUNDLE:-}" = view ]; then
  # The view's bundle (OpenCV's codecs with their libraries beside CUDA's) fits only at xz's best.
  if [ "${BUNDLE:-}" = view ]; then export XZ_OPT=-9e; fi
  tar -cJf .device.tar.xz .device && rm -rf .device
  du -sh .device.tar.xz
  # Above the 64 MiB a call may carry (the overlay bundle, ~87 MB): two parts, carried by two calls
  # made back to back while the machine is warm. First call: carry .device.part0 and run
  # `mkdir -p build-keep && cp .device.part0 build-keep/`; second: carry .device.part1 and run
  # run_gpu.sh, which joins them.
  rm -f .device.part*
  if [ "$(stat -c %s .device.tar.xz)" -gt $((60 * 1024 * 1024)) ]; then
    split -b $((44 * 1024 * 1024)) -d -a 1 .device.tar.xz .device.part && rm .device.tar.xz
    ls -l .device.part*
  fi
fi
