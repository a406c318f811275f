#!/usr/bin/env bash
# Written 2026-12-03 (after that session's device time was spent) for the next session's H200,
# not run yet: what the 2026-12-03 measurements left open (docs/design/nerf.md "Issue 44, eighth
# round", surfaces.md "Issue 49, sixth round", training.md "Issue 47, fourth round").
# Run from the tree root on the device with Warp unpacked in /tmp/site and the data carried in
# .gpu/data: LIMIT=... bash THIS PHASE
. "$(dirname "$0")/common.sh"  # R, OUT, S, Q, left, pin, step, ttq
F="--quiet --no-tensorboard --val-images 0"
tail_out() { cat $OUT/walls.txt; grep -h "^|" $OUT/*.log; cat $OUT/fail.txt 2>/dev/null; true; }
case $1 in
setup)  # the import, the data, the CUDA variants of the tests the session's code touches
  python3 -c "import warpnerf, warp, torch; print('ok', torch.__version__, warp.__version__, torch.cuda.get_device_name(0))"
  cat "$R/.commit" 2>/dev/null; cp -r .gpu/data/* $S/ 2>/dev/null
  l=$(left 5); timeout "$l" python3 -m pytest -o addopts=-ra -q -k cuda -p no:cacheprovider \
    tests/test_recipe_losses.py tests/test_ema.py tests/test_hash_sdf.py tests/test_sampling.py \
    tests/test_neus_density.py tests/test_graph_step.py \
    > $OUT/cuda_tests.log 2>&1
  echo "pytest rc=$?" >> $OUT/cuda_tests.log; tail -8 $OUT/cuda_tests.log ;;
s1)  # 49: the plain hash_sdf command (the GPU preset: --batch 4096 --target-samples 262144
     # --ema 0.95) on its own 20,000-step schedule, lego, 60 and 300 s (33.13 dB on 100,000)
  ttq lego_sdf_plain 330 --budgets 60,300 --spp 1 --label "the plain hash_sdf command" -- \
    train volsdf --data $S/lego --field hash_sdf --device cuda --iters 20000 $F
  tail_out ;;
s2)  # 49: materials hash_sdf with the average at 300 s (the mesh target 0.016; 0.0237 without)
  ttq materials_sdf_ema 360 --budgets 60,300 --spp 1 --geometry materials --mesh-resolution 384 \
    --label "materials hash_sdf, the GPU preset (ema)" -- train volsdf --data $S/materials \
    --field hash_sdf --device cuda --aabb 1.7 --fixed-beta --beta 0.01 $F
  tail_out ;;
s3)  # 49: the spheres' shrink is the density's tail at the outlines (surfaces.md "Issue 49,
     # seventh round": 0.0237 at beta 0.01, 0.0088 at 0.003): beta annealed to 0.003 with a
     # march step below it (lapB's recipe, issue 17, went to 0.005), materials, mesh at 300 s
  ttq materials_sdf_beta003 360 --budgets 60,300 --spp 1 --geometry materials --mesh-resolution 384 \
    --label "materials hash_sdf, beta 0.01 -> 0.003, march step 0.0025" -- train volsdf \
    --data $S/materials --field hash_sdf --device cuda --aabb 1.7 --beta 0.01 --beta-final 0.003 \
    --beta-anneal-steps 6000 --march-step 0.0025 --max-samples 4096 $F
  tail_out ;;
s4)  # 49: NeuS's unbiased density (--sdf-density neus, built 2026-12-03: outlines at the zero
     # level), materials at fixed beta 0.01, mesh at 300 s (the Laplace runs erode the spheres
     # by 0.020-0.025); the step is slower (the gradient in both passes): steps/s in the JSON
  ttq materials_sdf_neus 360 --budgets 60,300 --spp 1 --geometry materials --mesh-resolution 384 \
    --label "materials hash_sdf, --sdf-density neus" -- train volsdf --data $S/materials \
    --field hash_sdf --device cuda --aabb 1.7 --fixed-beta --beta 0.01 --sdf-density neus $F
  tail_out ;;
m1)  # 44: the materials winner's second seed, 300 s (33.95 dB with seed 0)
  ttq materials_hash256_seed1 330 --budgets 60,300 --spp 1,4 --label "materials hash256 seed 1" \
    -- train nerf --data $S/materials --device cuda --iters 40000 --seed 1 \
    --hash-max-res 256 --hash-log2-size 15 $F
  tail_out ;;
a1)  # 47: the step with and without the occupied-box cut, one lease, both orders
  for m in cut uncut uncut cut; do
    step "prof_$m" 60 python3 experiments/overheads/march_cut_ab.py $m --warm 1500 --steps 50 \
      --cprofile 0 --json $OUT/prof_$m.json -- train nerf --data $S/lego --device cuda
  done
  grep -h '"step_ms_median"\|march_' $OUT/prof_*.log | head -20; tail_out ;;
esac
# Budget: setup ~1 min, s1 ~6, s2 ~6.5, s3 ~6.5, s4 ~6.5, m1 ~6, a1 ~2.5: more than one
# session's 30 minutes; in order of what they settle: s4, s3 (issue 49's mesh target: the
# spheres' erosion), s2, s1, a1, m1.
