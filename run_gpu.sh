tar -xJf .device.tar.xz; export LD_LIBRARY_PATH=$PWD/.device/lib
B=.device/bin/bench_plan
ARGS="--phases 10 --phantom-spacing 0.7 --spacing 0.7 --radius 179.2 --mode fast --device cuda --work /tmp/pbb --reuse-phantom"
nvidia-smi -L > $OUT/gpu.txt
for extra in "" "" "--read-all-first" "--phases-at-once 1 --read-all-first" ""; do
  echo "== $extra" >> $OUT/r.err
  $B $ARGS $extra >> $OUT/r.json 2>>$OUT/r.err
done
for t in plan_breathing_test path_safety_cuda_test; do timeout 200 .device/bin/$t --gtest_brief=1 >> $OUT/tests.txt 2>&1; echo "$t rc $?" >> $OUT/tests.txt; done
python3 - <<'PY'
import json,os
for l in open(os.environ['OUT']+'/r.json'):
  if l.startswith('{'):
    d=json.loads(l); print(d['phases_at_once'], d['read_all_first'], round(d['wall_s'],2), {k:round(v,2) for k,v in d['timings'].items()}, d['fast_vs_exact']['points_computed_exactly'])
PY
grep -E "PASSED|FAILED|rc " $OUT/tests.txt
