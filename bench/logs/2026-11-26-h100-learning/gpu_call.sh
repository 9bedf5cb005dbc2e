#!/bin/bash
# One device call (run from the repository root, carry [".whl", ".gl"]): issue 14's GPU learning check, hauwm (each
# run its own 300-step export of the sample data) vs scratch, two seeds each, eager updates, four runs side by side
# on the one GPU (bench/README.md, "Learning check on a GPU"). Run again on the warm machine, it takes each run on
# by another 20k env steps from its checkpoint.
start=$(date +%s)
for f in .gl/*.deb; do dpkg -x $f /; done; ldconfig
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total --format=csv | tee $OUT/gpu.txt
common="--gpu --chunk 20000 --minutes 1 --set compile=off --set eval_every=5000"
for seed in 0 1; do
  timeout 480 python3 bench/bench_learning.py $common --agent hauwm --make-export 300 --seed $seed --logdir runs/hauwm-s$seed > $OUT/hauwm-s$seed.log 2>&1 &
  timeout 480 python3 bench/bench_learning.py $common --agent scratch --seed $seed --logdir runs/scratch-s$seed > $OUT/scratch-s$seed.log 2>&1 &
done
( while sleep 30; do echo "$(( $(date +%s) - start )) s: $(nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader)"; done ) > $OUT/gpu_util.log 2>&1 &
watcher=$!
wait -n; wait -n; wait -n; wait -n
kill $watcher
echo "runs done after $(( $(date +%s) - start )) s"
for run in runs/hauwm-s0 runs/hauwm-s1 runs/scratch-s0 runs/scratch-s1; do
  mkdir -p $OUT/$(basename $run); cp $run/*.csv $run/*.png $run/config.yaml $OUT/$(basename $run)/ 2>/dev/null
done
timeout 60 python3 bench/bench_learning.py --plot runs/hauwm-s0 runs/hauwm-s1 runs/scratch-s0 runs/scratch-s1 --out $OUT/learning_curve.png 2>&1 | tee $OUT/report.log
tail -n 25 $OUT/*-s?.log
echo "call done after $(( $(date +%s) - start )) s"
