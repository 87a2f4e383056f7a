tar -xJf .device.tar.xz; export LD_LIBRARY_PATH=$PWD/.device/lib
A="--phantom-spacing 0.7 --tumor-diameter 20 --tumor-spacing 0.7 --spacing 0.7 --radius 179.2 --mode fast --device cuda --work /tmp/plan_bench"
for r in 1 2; do
for v in "X=1" "CREP_CHECK_SEQ=1"; do
  echo "== $v" >> $OUT/ab.txt
  env $v .device/bin/bench_plan $A 2>/dev/null | grep '^{' | python3 -c "
import json,sys
d=json.loads(sys.stdin.read()); t=d['timings']; p=t['path_safety_phases']
fv=d['fast_vs_exact']
print('total %.3f ps %.3f kern %.3f ad %.3f up %.3f chk %.3f write %.3f area %.3f rp %.3f cls %s' % (t['total_s'], t['path_safety_s'], p['gpu_kernels'], p['adaptive_sampling'], p.get('self_check_upload',0), p['self_check'], t['write_s'], t['area_safety_s'], t['read_and_preprocess_s'], [fv[v]['class_agreement'] for v in ['svv','isbv','ivbv','bvv']]))" >> $OUT/ab.txt
done; done
cat $OUT/ab.txt
