#!/usr/bin/env bash
# The GPU driver of the fourth 2026-12-02 session (one H200), beside issue44_grid.sh whose phases
# it follows: materials' NeRF run with the box its opaque pixels ask for (grid phase
# materials-nerf-base, scored at 30/60/120/300 s) is rendered and split by region here; lego
# hash_sdf's frame in the GPU preset's 400,000-ray chunks. Run from the tree root on the device
# with Warp unpacked in /tmp/site and the data carried in .gpu/data: bash THIS PHASE
. "$(dirname "$0")/common.sh"  # R, OUT, S, Q, left, pin, step, ttq
F="--quiet --no-tensorboard --val-images 0"
tail_out() { cat $OUT/walls.txt; grep -h "^|" $OUT/*.log; cat $OUT/fail.txt 2>/dev/null; true; }
case $1 in
setup)
  python3 -c "import warpnerf, warp, torch; print('ok', torch.__version__, warp.__version__, torch.cuda.get_device_name(0))"
  cat "$R/.commit" 2>/dev/null; nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv
  cp -r .gpu/data/* $S/ 2>/dev/null; ls $S ;;
regions)  # after `issue44_grid.sh materials-nerf-base`: its run's val renders, the error by region
  step mat_eval 40 python3 -m warpnerf.cli eval $Q/materials-nerf-base/run --quiet --out $OUT/mat_eval
  step mat_regions 40 python3 experiments/recipe/materials_regions.py $OUT/mat_eval --data $S/materials --json $OUT/mat_regions.json
  cat $Q/materials-nerf-base/run/config.json | python3 -c "import json,sys; print('aabb', json.load(sys.stdin).get('aabb'))"
  cat $OUT/mat_regions.json 2>/dev/null | head -c 3000; tail_out ;;
frame)  # 47/49: lego hash_sdf, 60 s, scored (frame timed) in the preset's 400,000-ray chunks
  ttq sdf_frame 150 --budgets 60 --spp 1 --label "lego hash_sdf (today's command), 60 s" -- train volsdf --data $S/lego --field hash_sdf --device cuda --tf32 --batch 4096 --target-samples 262144 $F
  step sdf_frame_8k 60 python3 -m warpnerf.cli eval $Q/sdf_frame/run --chunk 8192 --quiet --out $Q/sdf_frame/eval_8k
  cp $Q/sdf_frame/eval_8k/metrics.json $OUT/sdf_frame_8k.json 2>/dev/null
  tail_out ;;
esac
