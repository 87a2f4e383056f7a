#!/usr/bin/env bash
# On the GPU machine, from the repository root, after bench/bundle_gpu.sh ran here: GPU tests,
# the card's sampling rate, and the headline case (exact and fast, each value). Logs go to $OUT.
set -uo pipefail
export LD_LIBRARY_PATH="$PWD/.device/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
out="${OUT:-/tmp/crepuscular-gpu}"
mkdir -p "$out"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$out/gpu.txt"
echo "== GPU tests"
.device/bin/path_safety_cuda_test 2>&1 | tee "$out/path_safety_cuda_test.log"
echo "== sampling rate"
.device/bin/bench_sampling_rate 2>&1 | tee "$out/sampling_rate.jsonl"
echo "== headline case"
.device/bin/bench_path_safety --case headline --device cuda --each-value --mode "${MODE:-both}" \
  ${BENCH_ARGS:-} 2>&1 | tee "$out/headline.jsonl"
