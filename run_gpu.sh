tar -xJf .device.tar.xz; export LD_LIBRARY_PATH=$PWD/.device/lib
B=.device/bin/bench_plan
ARGS="--phases 10 --phantom-spacing 0.7 --spacing 0.7 --radius 179.2 --mode fast --device cuda --work /tmp/pbb --reuse-phantom"
HEAD="--phantom-spacing 0.7 --tumor-diameter 20 --tumor-spacing 0.7 --spacing 0.7 --radius 179.2 --mode fast --device cuda --work /tmp/pb --reuse-phantom"
nvidia-smi -L > $OUT/gpu.txt
run() { echo "== $*" >> $OUT/r.err; SECONDS=0; $B "$@" >> $OUT/r.json 2>>$OUT/r.err; echo "rc $? ${SECONDS}s" >> $OUT/r.err; }
run $ARGS
run $ARGS
run $HEAD
run $HEAD
run $HEAD
run $ARGS --phases-at-once 1 --read-all-first
run $ARGS
for t in plan_breathing_test path_safety_cuda_test; do timeout 100 .device/bin/$t --gtest_brief=1 >> $OUT/tests.txt 2>&1; echo "$t rc $?" >> $OUT/tests.txt; done
python3 - <<'PY'
import json,os
for l in open(os.environ['OUT']+'/r.json'):
  if l.startswith('{'):
    d=json.loads(l); f=d['fast_vs_exact']; print(d.get('phases'), d.get('phases_at_once'), d.get('read_all_first'), round(d['wall_s'],2), {k:round(v,2) for k,v in d['timings'].items() if isinstance(v,float)}, f['points_computed_exactly'], [f[v]['class_agreement'] for v in ('svv','isbv','ivbv','bvv')])
PY
grep -E "PASSED|FAILED|rc " $OUT/tests.txt; grep "rc " $OUT/r.err
