#!/usr/bin/env bash
# Builds compared on one GPU machine, run after run, so that the machine's own speed (which varies
# from one instance to the next by more than most changes gain) weighs on each alike.
#
# Here: BUNDLE=plan bash bench/bundle_gpu.sh, then copy the builds to compare into the bundle
# beside bench_plan (e.g. .device/bin/bench_plan_prev) and pack it again as .device.tar.xz.
# On the GPU machine, carrying .device.tar.xz:
#   RUNS='run prev bench_plan_prev br; run new bench_plan br trace; run new2 bench_plan br' \
#   TESTS='plan_breathing_test' PROFILE='' bash bench/ab_gpu.sh
# run LABEL PROGRAM CASE [trace]: CASE br is the breathing case (10 phases of the 513^3 grid,
# 2 cm tumor, fast mode), hl the headline (one phase); the first run of a case also makes its
# phantom. An environment prefix applies to one run (OMP_NUM_THREADS=8 run ...), ARGS among them
# (more bench_plan options).
# profile LABEL [bench_plan options]: one breathing run under `perf record` (perf and its
# libraries in .device/perf/: WITH_PERF=1 BUNDLE=plan bash bench/bundle_gpu.sh), its functions by
# core time in perf_LABEL.txt.
# Results in $OUT: runs.txt (one JSON line per run, summed by bench/runs_summary.py),
# progress.txt, trace_LABEL.txt (bench/timeline.py), vm.txt (/proc/vmstat before and after each
# run), machine.txt, and each test's log. A device call brings back at most 8 files: the last run's
# own output (last.json) is removed at the end, and a call with many tests or traces leaves out
# the rest (files_left_out).
set -u
out="${OUT:-/tmp/crepuscular-ab}"
mkdir -p "$out"
if [ -f .device.tar.xz ]; then tar -xJf .device.tar.xz; fi
export LD_LIBRARY_PATH="$PWD/.device/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
bin=.device/bin
start=$(date +%s)
{
  nproc
  nvidia-smi --query-gpu=name,clocks.max.sm,memory.total --format=csv
  cat /sys/kernel/mm/transparent_hugepage/enabled /sys/kernel/mm/transparent_hugepage/defrag
  free -g
} >"$out/machine.txt" 2>&1
vmstat_now() {
  grep -E '^(thp_fault_alloc|thp_fault_fallback|compact_stall|compact_fail|pgfault) ' /proc/vmstat |
    awk '{printf "%s=%s ", $1, $2}'
}
headline="--phantom-spacing 0.7 --tumor-diameter 20 --tumor-spacing 0.7 --spacing 0.7 --radius 179.2
  --mode fast --device cuda --work /tmp/ab_headline --reuse-phantom"
breathing="--phases 10 --phantom-spacing 0.7 --spacing 0.7 --radius 179.2 --mode fast --device cuda
  --work /tmp/ab_breathing --reuse-phantom --phase-tumor-diameter 20 --tumor-spacing 0.7"
run() {
  local label=$1 program=$2 case=$3 trace=${4:-} args
  if [ "$case" = br ]; then args=$breathing; else args=$headline; fi
  args="$args ${ARGS:-}"  # more bench_plan options for one run: ARGS='--check-voxels 20000' run ...
  echo "$label before $(vmstat_now)" >>"$out/vm.txt"
  # shellcheck disable=SC2086
  if [ -n "$trace" ]; then
    CREPUSCULAR_TRACE="$out/trace_$label.txt" "$bin/$program" $args >"$out/last.json" 2>>"$out/stderr.txt"
  else
    "$bin/$program" $args >"$out/last.json" 2>>"$out/stderr.txt"
  fi
  echo "$label $(tail -1 "$out/last.json")" >>"$out/runs.txt"
  echo "$label after $(vmstat_now)" >>"$out/vm.txt"
  echo "$label $(($(date +%s) - start)) s" >>"$out/progress.txt"
}
profile() {
  local label=$1
  shift
  # shellcheck disable=SC2086
  LD_LIBRARY_PATH="$LD_LIBRARY_PATH:$PWD/.device/perf/lib" .device/perf/perf record -F 1999 \
    -o "/tmp/perf_$label.data" -- "$bin/bench_plan" $breathing "$@" >"$out/profile_$label.json" \
    2>"$out/profile_$label.err"
  LD_LIBRARY_PATH="$LD_LIBRARY_PATH:$PWD/.device/perf/lib" .device/perf/perf report \
    -i "/tmp/perf_$label.data" --no-children --sort dso,sym --stdio 2>&1 | head -250 \
    >"$out/perf_$label.txt"
  echo "profile $label $(($(date +%s) - start)) s" >>"$out/progress.txt"
}
eval "${RUNS:-}"
eval "${PROFILE:-}"
for t in ${TESTS:-}; do
  "$bin/$t" >"$out/$t.log" 2>&1
  echo "$t exit $? $(tail -1 "$out/$t.log")" >>"$out/progress.txt"
done
rm -f "$out/last.json"  # its line is in runs.txt
