#!/usr/bin/env bash
# Fuzzes every reader of outside data (tests/fuzz/targets.hpp) with libFuzzer.
#
#   scripts/fuzz.sh                  each target for 10 s
#   scripts/fuzz.sh --ci             what the test command runs: each target from the same seed,
#                                    at most 4000 inputs or 6 s (a finding there is reproducible)
#   scripts/fuzz.sh --seconds 600    longer runs
#   scripts/fuzz.sh --seconds 60 nifti camera_yaml     only these targets
#
# Builds with clang, AddressSanitizer and UndefinedBehaviorSanitizer into build-fuzz/. Each target
# starts from tests/fuzz/corpus/<target>/ and its past findings; new inputs go to
# build-fuzz/corpus/<target>/ (the repository's corpus is never written). A crash, another
# exception than crepuscular::Error, a hang (over 10 s) or more than 2 GB stops the run: the input
# is saved as build-fuzz/findings/<target>/crash-* and the script fails. Fix the reader, then copy
# the input to tests/fuzz/findings/<target>/: fuzz_corpus_test replays it from then on.
set -euo pipefail
cd "$(dirname "$0")/.."

seconds=10
limits=()
targets=()
while [ $# -gt 0 ]; do
  case "$1" in
    --seconds) seconds="$2"; shift 2 ;;
    --ci) seconds=6; limits=(-seed=1 -runs=4000); shift ;;
    -h|--help) sed -n '2,14p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *) targets+=("$1"); shift ;;
  esac
done

jobs=$(nproc 2>/dev/null || echo 2)
launcher=()
if command -v ccache >/dev/null 2>&1; then launcher=(-DCMAKE_CXX_COMPILER_LAUNCHER=ccache); fi
CC=clang CXX=clang++ cmake -S . -B build-fuzz -G Ninja -DCMAKE_BUILD_TYPE=Debug \
  -DCREPUSCULAR_FUZZ=ON -DCREPUSCULAR_CUDA=OFF -DCREPUSCULAR_GUI=OFF "${launcher[@]}" >/dev/null
cmake --build build-fuzz -j "$jobs" --target fuzz

if [ ${#targets[@]} -eq 0 ]; then
  for dir in tests/fuzz/corpus/*/; do targets+=("$(basename "$dir")"); done
fi

export LSAN_OPTIONS="suppressions=$PWD/tests/fuzz/lsan.supp:print_suppressions=0"
# One thread in ITK and OpenMP: the coverage an input reaches then does not depend on thread
# timing, so libFuzzer explores the same inputs from the same seed on every machine and a --ci
# run here predicts the test command's.
export ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS=1 OMP_NUM_THREADS=1
# Each fuzzing process makes a scratch folder for its inputs and removes it at exit; one that
# crashes or times out cannot, so the folders go in the build tree, emptied here, not in /tmp.
export TMPDIR="$PWD/build-fuzz/tmp"
rm -rf "$TMPDIR" && mkdir -p "$TMPDIR"
failed=()
for t in "${targets[@]}"; do
  program="build-fuzz/tests/fuzz/fuzz_$t"
  if [ ! -x "$program" ]; then
    echo "fuzz: no program for corpus folder tests/fuzz/corpus/$t (add it to tests/fuzz/CMakeLists.txt)" >&2
    failed+=("$t"); continue
  fi
  mkdir -p "build-fuzz/corpus/$t" "build-fuzz/findings/$t"
  seeds=("tests/fuzz/corpus/$t")
  [ -d "tests/fuzz/findings/$t" ] && seeds+=("tests/fuzz/findings/$t")
  log="build-fuzz/findings/$t/last-run.log"
  # --ci starts from the repository's corpus alone, so that its inputs are the same every time.
  if [ ${#limits[@]} -gt 0 ]; then rm -rf "build-fuzz/corpus/$t"; mkdir -p "build-fuzz/corpus/$t"; fi
  if "$program" "${limits[@]}" -max_total_time="$seconds" -timeout=10 -rss_limit_mb=2048 -malloc_limit_mb=2048 \
       -artifact_prefix="build-fuzz/findings/$t/" -print_final_stats=1 \
       "build-fuzz/corpus/$t" "${seeds[@]}" >"$log" 2>&1; then
    runs=$(grep -o 'stat::number_of_executed_units: *[0-9]*' "$log" | grep -o '[0-9]*$' || echo "?")
    echo "fuzz $t: $runs inputs, no finding"
  else
    echo "fuzz $t: FINDING, see $log and build-fuzz/findings/$t/" >&2
    # The reason and what the reader printed just before it (the readers' libraries print
    # "** ERROR" lines of their own for every refused input, so those alone say nothing).
    grep -B 12 -m 1 -E '==[0-9]+== ?ERROR|fuzz .*escaped|runtime error' "$log" >&2 || tail -n 20 "$log" >&2
    grep -m 1 'SUMMARY' "$log" >&2 || true
    failed+=("$t")
  fi
done

if [ ${#failed[@]} -gt 0 ]; then
  echo "fuzz: findings in ${failed[*]}" >&2
  exit 1
fi
echo "fuzz: ${#targets[@]} targets, no finding"
