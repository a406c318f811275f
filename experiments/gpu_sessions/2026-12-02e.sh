#!/usr/bin/env bash
# Written 2026-12-02 (fourth session, after its device time was spent) for the next session's
# H200, not run yet: the CUDA tests of the march's occupied-box cut, its GPU
# timings (issue 47: the step's march was 1.57 ms of 8.67), the plain lego command against its
# earlier steps/s and PSNR, and issue 44's materials capacity rows (issue44_grid.sh's keys).
# Run from the tree root on the device with Warp unpacked in /tmp/site and the data carried in
# .gpu/data: LIMIT=... bash THIS PHASE
. "$(dirname "$0")/common.sh"  # R, OUT, S, Q, left, pin, step, ttq
F="--quiet --no-tensorboard --val-images 0"
tail_out() { cat $OUT/walls.txt; grep -h "^|" $OUT/*.log; cat $OUT/fail.txt 2>/dev/null; true; }
case $1 in
setup)  # the import, then the CUDA variants of the tests this session's code touches
  python3 -c "import warpnerf, warp, torch; print('ok', torch.__version__, warp.__version__, torch.cuda.get_device_name(0))"
  cat "$R/.commit" 2>/dev/null; cp -r .gpu/data/* $S/ 2>/dev/null
  l=$(left 5); timeout "$l" python3 -m pytest -o addopts=-ra -q -k cuda -p no:cacheprovider \
    tests/test_march_work.py tests/test_occupancy.py tests/test_contraction.py tests/test_tracer.py \
    tests/test_graph_step.py tests/test_view_cull.py tests/test_sampling.py tests/test_importance.py > $OUT/cuda_tests.log 2>&1
  echo "pytest rc=$?" >> $OUT/cuda_tests.log; tail -8 $OUT/cuda_tests.log ;;
b1)  # 47: the march cut and uncut on the GPU; the step's profile
  step bench_march 90 python3 -m warpnerf.cli bench march --device cuda --json $OUT/bench_march.json
  step prof_step 90 python3 scripts/profile_train_step.py --warm 1500 --steps 50 --cprofile 0 \
    --json $OUT/prof_step.json -- train nerf --data $S/lego --device cuda
  tail_out ;;
t1)  # 44/47: the plain command, 60 s (steps/s against 103-109, 37.35-37.70 dB with 4 rays)
  ttq lego_plain 110 --budgets 60 --spp 1,4 --label "the plain command, march cut to the occupied box" -- train nerf --data $S/lego --device cuda --iters 40000 $F
  tail_out ;;
esac
# then issue 44's materials capacity rows, one 60 s run each (about 80 s):
#   for c in hash256 hash1024; do BUDGETS=60 WANT=80 LIMIT=110 bash issue44_grid.sh materials-nerf-$c; done
#   BUDGETS=60 WANT=80 LIMIT=110 bash issue44_grid.sh lego-nerf-small_hash   (does lego lose at 512?)
