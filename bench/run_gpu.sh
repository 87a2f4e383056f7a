#!/usr/bin/env bash
# On the GPU machine, from the repository root, after bench/bundle_gpu.sh ran here: GPU tests,
# the card's sampling rate, the headline case (exact and fast, each value), and the overlay
# renderer's frame time through EGL (no X server needed). Logs go to $OUT.
# ONLY=overlay runs the overlay renderer benchmark alone.
set -uo pipefail
# A bundle carried in two parts (bundle_gpu.sh): the first kept by an earlier call in build-keep/.
if [ ! -f .device.tar.xz ] && [ -f build-keep/.device.part0 ] && [ -f .device.part1 ]; then
  cat build-keep/.device.part0 .device.part1 >.device.tar.xz && rm -f build-keep/.device.part0
fi
if [ -f .device.tar.xz ]; then tar -xJf .device.tar.xz; fi
export LD_LIBRARY_PATH="$PWD/.device/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
out="${OUT:-/tmp/crepuscular-gpu}"
mkdir -p "$out"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$out/gpu.txt"
overlay() {
  echo "== overlay renderer (EGL)"
  if [ ! -x .device/bin/overlay_bench ]; then
    echo "overlay_bench not bundled: run BUNDLE=overlay bash bench/bundle_gpu.sh first"
    return
  fi
  ls /usr/share/glvnd/egl_vendor.d /etc/glvnd/egl_vendor.d 2>/dev/null
  ldconfig -p | grep -E 'libEGL_nvidia|libnvidia-eglcore' | head -3
  # The driver's EGL library without its libglvnd vendor file: name it to libglvnd directly.
  if ! ls /usr/share/glvnd/egl_vendor.d/*nvidia* /etc/glvnd/egl_vendor.d/*nvidia* >/dev/null 2>&1 &&
     ldconfig -p | grep -q libEGL_nvidia.so.0; then
    printf '{"file_format_version":"1.0.0","ICD":{"library_path":"libEGL_nvidia.so.0"}}\n' \
      >"$out/10_nvidia.json"
    export __EGL_VENDOR_LIBRARY_FILENAMES="$out/10_nvidia.json"
  fi
  [ -n "${SKIP_OVERLAY_BENCH:-}" ] ||
    env -u DISPLAY .device/bin/overlay_bench --backend egl --frames "${OVERLAY_FRAMES:-300}" 2>&1 |
    tee "$out/overlay.log"
  if [ -x .device/bin/guide_bench ]; then
    echo "== guidance loop end to end (tracking + overlay + rendering, EGL)"
    # GUIDE_RUNS runs of each configuration; GUIDE_ARGS adds guide_bench options.
    for run in $(seq "${GUIDE_RUNS:-1}"); do
      env -u DISPLAY .device/bin/guide_bench --backend egl --frames "${GUIDE_FRAMES:-150}" \
        ${GUIDE_ARGS:-} 2>&1 | tee -a "$out/guide.jsonl"
    done
  fi
}
# `crepuscular plan` end to end on the headline grid (513^3 at 0.7 mm, phantom at 0.7 mm) with a
# 2 cm tumor segmented at 0.7 mm, all four values, fast then exact (PLAN_MODES overrides).
plan() {
  [ -n "${SKIP_TESTS:-}" ] || echo "== GPU tests"
  [ -n "${SKIP_TESTS:-}" ] || for t in path_safety_cuda_test path_safety_test path_safety_fast_test plan_breathing_test; do
    .device/bin/$t >"$out/$t.log" 2>&1
    echo "$t: exit $?"; tail -3 "$out/$t.log"
  done
  echo "== plan end to end, headline grid"
  # PLAN_VARIANTS: option sets separated by '|', each run in every mode (A/B in one call).
  local variants=("")
  [ -z "${PLAN_VARIANTS:-}" ] || IFS='|' read -ra variants <<<"$PLAN_VARIANTS"
  for m in ${PLAN_MODES:-fast exact}; do
    for v in "${variants[@]}"; do
      .device/bin/bench_plan --phantom-spacing 0.7 --tumor-diameter 20 --tumor-spacing 0.7 \
        --spacing 0.7 --radius 179.2 --mode "$m" --device cuda --work /tmp/plan_bench \
        ${PLAN_ARGS:-} $v 2>&1 |
        tee -a "$out/plan_headline.jsonl"
    done
  done
  df -h /tmp | tail -1 | tee -a "$out/plan_headline.jsonl"
  # PLAN_PHASES=N: the breathing phantom's N phases on the headline grid, planned over the cycle
  # (issue 17's case: fast mode, all four values).
  if [ -n "${PLAN_PHASES:-}" ]; then
    echo "== breathing, $PLAN_PHASES phases, headline grid"
    .device/bin/bench_plan --phases "$PLAN_PHASES" --phantom-spacing 0.7 --spacing 0.7 \
      --radius 179.2 --mode fast --device cuda --work /tmp/plan_bench_breathing \
      ${BREATHING_ARGS:-} 2>&1 |
      tee -a "$out/plan_breathing.jsonl"
  fi
}
if [ "${ONLY:-}" = overlay ]; then
  overlay
  exit
fi
if [ "${ONLY:-}" = plan ]; then
  plan
  exit
fi
echo "== GPU tests"
.device/bin/path_safety_cuda_test 2>&1 | tee "$out/path_safety_cuda_test.log"
echo "== sampling rate"
.device/bin/bench_sampling_rate 2>&1 | tee "$out/sampling_rate.jsonl"
echo "== headline case"
.device/bin/bench_path_safety --case headline --device cuda --each-value --mode "${MODE:-both}" \
  ${BENCH_ARGS:-} 2>&1 | tee "$out/headline.jsonl"
overlay
