#!/usr/bin/env bash
# The GPU driver of the 2026-11-28 session (issues 44, 47, 48, 49), kept as the record of how
# docs/design/{nerf,surfaces,rendering}.md measured; run from the tree root on the device with
# warp on PYTHONPATH=/tmp/site and the data copied to /root/stage: bash THIS PHASE
set -u
R=$(pwd)
ln -sfn "$R/kernels" "$R/warpnerf/kernels"
export PYTHONPATH=/tmp/site:$R PYTHONUNBUFFERED=1
FINAL=${OUT:-/tmp/out}; OUT=/root/res/$1; rm -rf $OUT; mkdir -p "$OUT" "$FINAL"
trap 'tar czf $FINAL/$1.tgz -C /root/res $1 2>/dev/null' EXIT
S=/root/stage; Q=/root/q; mkdir -p $S $Q
pin() { local g=$1; shift; OMP_NUM_THREADS=8 MKL_NUM_THREADS=8 CUDA_VISIBLE_DEVICES=$g taskset -c $((16*g))-$((16*g+15)) "$@"; }
ttq() {  # gpu name ttq-args...
  local g=$1 name=$2; shift 2
  rm -rf $Q/$name; mkdir -p $Q/$name
  local t0=$(date +%s)
  local left=$(( ${DEADLINE:-99999999999} - $(date +%s) )); [ $left -lt 20 ] && { echo "$name skipped (no time)" >> $OUT/fail.txt; return; }
  pin $g timeout $left python3 scripts/time_to_quality.py run $Q/$name "$@" > $OUT/$name.log 2>&1 || echo "$name failed" >> $OUT/fail.txt
  echo "$name wall $(( $(date +%s) - t0 )) s" >> $OUT/walls.txt
  cp $Q/$name/ttq.json $OUT/$name.ttq.json 2>/dev/null
}
F="--quiet --no-tensorboard --val-images 0"
SDF="--field hash_sdf --device cuda --tf32 --batch 4096 --target-samples 262144 --aabb 1.7 --fixed-beta --beta 0.01"
case $1 in
setup)
  python3 -c "import warpnerf, warp, plyfile, torch; print('ok', torch.cuda.device_count(), torch.cuda.get_device_name(0))"
  git -C "$R" log -1 --format=%h 2>/dev/null || cat "$R/.commit" 2>/dev/null
  nproc; nvidia-smi --query-gpu=name,memory.total --format=csv ;;
stage)  # copy carried data to the stage
  for d in .gpu/lego .gpu/materials .gpu/fern .gpu/beer; do [ -d $d ] && cp -r $d $S/; done; ls $S ;;
b1a)  # issue 44 (lego schedule) and 49 item 4 (materials hash_sdf variants)
  DEADLINE=$(( $(date +%s) + ${LIMIT:-570} ))
  ( ttq 0 lego_it40k --budgets 15,30,60,120,300 --label "plain + --iters 40000" -- train nerf --data $S/lego --device cuda --iters 40000 $F
    ttq 0 msdf_c2f --budgets 60,120 --geometry materials --mesh-resolution 384 --label "materials hash_sdf default + --c2f-every 500" -- train volsdf --data $S/materials $SDF --c2f-every 500 $F ) > $OUT/g0.txt 2>&1 &
  ( ttq 1 lego_it100k --budgets 15,30,60,120,300 --label "plain + --iters 100000" -- train nerf --data $S/lego --device cuda --iters 100000 $F
    ttq 1 msdf_anneal --budgets 60,120 --geometry materials --mesh-resolution 384 --label "materials hash_sdf, beta 0.05 -> 0.005 over 10000 steps" -- train volsdf --data $S/materials ${SDF/--fixed-beta --beta 0.01/--beta 0.05 --beta-final 0.005 --beta-anneal-steps 10000} $F ) > $OUT/g1.txt 2>&1 &
  wait; cat $OUT/walls.txt; grep -h "^|" $OUT/*.log; cat $OUT/fail.txt 2>/dev/null; true ;;
b1b)  # issue 44 (materials regularisation) and 49 (materials hash_sdf defaults, 300 s)
  DEADLINE=$(( $(date +%s) + ${LIMIT:-570} ))
  ( ttq 0 mnerf_base --budgets 30,60,120 --label "materials NeRF, gpu recipe" -- train nerf --data $S/materials --device cuda $F
    ttq 0 mnerf_res512 --budgets 30,60,120 --label "materials NeRF, --hash-max-res 512" -- train nerf --data $S/materials --device cuda --hash-max-res 512 $F
    ttq 0 mnerf_t16 --budgets 30,60,120 --label "materials NeRF, --hash-log2-size 16" -- train nerf --data $S/materials --device cuda --hash-log2-size 16 $F
    ttq 0 mnerf_r512t16 --budgets 30,60,120 --label "materials NeRF, max res 512 + log2 size 16" -- train nerf --data $S/materials --device cuda --hash-max-res 512 --hash-log2-size 16 $F ) > $OUT/g0.txt 2>&1 &
  ( ttq 1 msdf_default --budgets 60,120,300 --geometry materials --mesh-resolution 384 --label "materials hash_sdf, defaults (mask 0.1, weight cull)" -- train volsdf --data $S/materials $SDF $F
    ttq 1 msdf_logistic --budgets 60 --geometry materials --mesh-resolution 384 --label "materials hash_sdf, NeuS logistic density (s = 100)" -- train volsdf --data $S/materials $SDF --sdf-density logistic $F ) > $OUT/g1.txt 2>&1 &
  wait; cat $OUT/walls.txt; grep -h "^|" $OUT/*.log; cat $OUT/fail.txt 2>/dev/null; true ;;
b2)  # issue 47 (the tracer's frames; CUDA tests of the new kernels) and 49 item 4 (logistic + c2f, 270 s)
  DEADLINE=$(( $(date +%s) + ${LIMIT:-440} ))
  ( ttq 1 msdf_logc2f --budgets 120,270 --geometry materials --mesh-resolution 384 --label "materials hash_sdf, logistic density + --c2f-every 500" -- train volsdf --data $S/materials $SDF --sdf-density logistic --c2f-every 500 $F
    left=$(( DEADLINE - $(date +%s) - 5 )); [ $left -gt 20 ] && pin 1 timeout $left python3 -m warpnerf.cli mesh $Q/msdf_logc2f/run --out $Q/msdf_mesh.ply --no-screenshot > $OUT/mesh.log 2>&1 && gzip -c $Q/msdf_mesh.ply > $OUT/msdf_mesh.ply.gz ) > $OUT/g1.txt 2>&1 &
  ( t0=$(date +%s)
    ttq 0 lego60 --budgets 60 --label "plain command (fp32 MLPs), step fusions of issue 47" -- train nerf --data $S/lego --device cuda $F
    pin 0 timeout 120 python3 scripts/bench_frame.py $Q/lego60/run --device cuda --data $S/lego --repeat 2 --json $OUT/frame_default.json > $OUT/frame.log 2>&1
    pin 0 timeout 45 python3 scripts/bench_frame.py $Q/lego60/run --device cuda --data $S/lego --repeat 1 --images 20 --variants traced --min-steps 4 --max-steps 32 --json $OUT/frame_4_32.json >> $OUT/frame.log 2>&1
    pin 0 timeout 45 python3 scripts/bench_frame.py $Q/lego60/run --device cuda --data $S/lego --repeat 1 --images 20 --variants traced,traced-all --min-steps 16 --max-steps 256 --json $OUT/frame_16_256.json >> $OUT/frame.log 2>&1
    echo "frames wall $(( $(date +%s) - t0 )) s" >> $OUT/walls.txt
    ttq 0 lego60_bf16 --budgets 60 --label "plain command, --mlp-precision bf16" -- train nerf --data $S/lego --device cuda --mlp-precision bf16 $F
    left=$(( DEADLINE - $(date +%s) - 10 ))
    [ $left -gt 30 ] && CUDA_VISIBLE_DEVICES=0 timeout $left python3 -m pytest -o addopts=-ra -x -q tests/test_tracer.py tests/test_step_ops.py tests/test_proposal.py > $OUT/cuda_tests.log 2>&1
    tail -3 $OUT/cuda_tests.log ) > $OUT/g0.txt 2>&1 &
  ( ttq 2 beer_grid --budgets 120,240 --label "beer, the capture defaults (occupancy grid)" -- train nerf --data $S/beer --device cuda $F ) > $OUT/g2.txt 2>&1 &
  ( ttq 3 beer_proposal --budgets 120,240 --label "beer, --sampler proposal" -- train nerf --data $S/beer --device cuda --sampler proposal $F ) > $OUT/g3.txt 2>&1 &
  wait; cat $OUT/walls.txt $OUT/g0.txt; grep -h '"median\|ms\|psnr' $OUT/frame.log | head -40; grep -h "^|" $OUT/*.log; cat $OUT/fail.txt 2>/dev/null; true ;;
esac
