#!/usr/bin/env bash
# The GPU driver of the third 2026-12-02 session (issue 44: the CUDA tests of --train-spp and
# --pixel-jitter, a second seed of the plain command, materials' renders for the per-sphere error;
# issues 44 and 49: lego hash_sdf at 300 s with and without --train-spp 4; one H200), kept as the
# record of how the design notes' figures of that session were measured. Run from the tree root
# on the device with Warp unpacked in /tmp/site and the data carried in .gpu/data: bash THIS PHASE
. "$(dirname "$0")/common.sh"  # R, OUT, S, Q, left, pin, step, ttq
F="--quiet --no-tensorboard --val-images 0"
LEGO="train nerf --data $S/lego --device cuda --iters 40000 $F"  # the plain command (40,000 steps)
SDF="train volsdf --data $S/lego --field hash_sdf --device cuda --tf32 --batch 4096 --target-samples 262144 $F"
tail_out() { cat $OUT/walls.txt; grep -h "^|" $OUT/*.log; cat $OUT/fail.txt 2>/dev/null; true; }
case $1 in
setup)  # the import, then the CUDA variants of the tests this round's code touches
  python3 -c "import warpnerf, warp, torch; print('ok', torch.__version__, warp.__version__, torch.cuda.get_device_name(0))"
  cat "$R/.commit" 2>/dev/null; nproc; nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv
  l=$(left 5); timeout "$l" python3 -m pytest -o addopts=-ra -q -k cuda -p no:cacheprovider tests/test_train_spp.py \
    tests/test_pixel_jitter.py tests/test_step_loss.py tests/test_graph_step.py tests/test_composite.py \
    tests/test_composite_tiled.py > $OUT/cuda_tests.log 2>&1; echo "pytest rc=$?" >> $OUT/cuda_tests.log
  tail -15 $OUT/cuda_tests.log; tail_out ;;
h1)  # 44: the plain command (--train-spp 4 by default), second seed; materials 60 s and its renders
  cp -r .gpu/data/* $S/ 2>/dev/null; ls $S
  nvidia-smi --query-gpu=name,driver_version --format=csv,noheader > $OUT/gpu.txt
  ttq lego_seed1 400 --budgets 60,300 --spp 1,4 --label "the plain command, --seed 1" -- $LEGO --seed 1
  ttq mat 90 --budgets 60 --spp 1,4 --label "materials, the plain command" -- train nerf --data $S/materials --device cuda --iters 40000 $F
  step mat_eval 30 python3 -m warpnerf.cli eval $Q/mat/run --spp 4 --quiet --out $OUT/mat_eval
  tail_out ;;
h3)  # 44/49: lego hash_sdf with --train-spp 4, 300 s
  ttq sdf_tspp4 380 --budgets 60,300 --spp 1,4 --label "lego hash_sdf, --train-spp 4" -- $SDF --train-spp 4
  tail_out ;;
h2)  # 44/49: lego hash_sdf as it is today (one ray a pixel), 300 s
  ttq sdf_base 360 --budgets 60,300 --spp 1 --label "lego hash_sdf (today's command)" -- $SDF
  tail_out ;;
# written for the next session, not run in this one (no device time left): n1 (44: materials
# 300 s with the box its opaque pixels now ask for, 1.669, and its regions), n2 (47/49: the
# hash_sdf frame in the GPU preset's 400,000-ray chunks, from the h2 run's folder if still there)
n1)
  cp -r .gpu/data/* $S/ 2>/dev/null
  ttq mat_box 380 --budgets 60,300 --spp 1,4 --label "materials, the plain command (box 1.669)" -- train nerf --data $S/materials --device cuda --iters 40000 $F
  step mat_box_eval 30 python3 -m warpnerf.cli eval $Q/mat_box/run --quiet --out $OUT/mat_box_eval
  step mat_box_regions 30 python3 experiments/recipe/materials_regions.py $OUT/mat_box_eval --data $S/materials --json $OUT/mat_box_regions.json
  # what may act on the floaters past the rim and the glass: the recipe's options, 60 s each
  for x in "--random-background on" "--view-cull" "--hash-max-res 512 --hash-log2-size 16"; do
    n=mat_$(echo "$x" | tr -dc 'a-z0-9' | cut -c1-24)
    ttq $n 100 --budgets 60 --spp 1,4 --label "materials (box 1.669) $x" -- train nerf --data $S/materials --device cuda --iters 40000 $F $x
  done
  tail_out ;;
n2)
  step sdf_frame 90 python3 -m warpnerf.cli eval $Q/sdf_base/run --chunk 400000 --quiet --out $Q/sdf_base/eval_chunk
  cp $Q/sdf_base/eval_chunk/metrics.json $OUT/sdf_frame_chunk400k.json 2>/dev/null
  tail_out ;;
esac
