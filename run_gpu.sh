set -x
tar -xJf .device.tar.xz; export LD_LIBRARY_PATH=$PWD/.device/lib
B=.device/bin/bench_plan
ARGS="--phases 10 --phantom-spacing 0.7 --spacing 0.7 --radius 179.2 --mode fast --device cuda --work /tmp/pbb --reuse-phantom"
nvidia-smi -L > $OUT/gpu.txt
$B $ARGS > $OUT/r.json 2>$OUT/r.err
$B $ARGS >> $OUT/r.json 2>>$OUT/r.err
$B $ARGS --phases-at-once 1 >> $OUT/r.json 2>>$OUT/r.err
$B $ARGS >> $OUT/r.json 2>>$OUT/r.err
for t in plan_breathing_test path_safety_cuda_test; do timeout 200 .device/bin/$t --gtest_brief=1 >> $OUT/tests.txt 2>&1; echo "$t rc $?" >> $OUT/tests.txt; done
grep -h wall_s $OUT/r.json | python3 -c "
import sys,json
for l in sys.stdin:
  if l.startswith('{'):
    d=json.loads(l); print(d['wall_s'], d['timings'], d['fast_vs_exact']['points_computed_exactly'])
"
tail -5 $OUT/tests.txt
