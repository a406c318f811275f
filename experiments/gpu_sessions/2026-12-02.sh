#!/usr/bin/env bash
# The GPU driver of the 2026-12-02 session (issues 44, 47, 48, 49; one H200), kept as the record
# of how the design notes' figures of that day were measured. Run from the tree root on the device
# with Warp unpacked in /tmp/site and the data carried in .gpu/data: bash THIS PHASE
. "$(dirname "$0")/common.sh"  # R, OUT, S, Q, left, pin, step, ttq
evalkeep() {  # name: eval every val image at the frame's chunk; keep metrics.json
  step "eval_$1" 60 python3 -m warpnerf.cli eval "$Q/$1/run" --chunk 400000 --quiet \
    --out "$Q/$1/eval_val"
  cp "$Q/$1/eval_val/metrics.json" "$OUT/$1.metrics.json" 2>/dev/null
}
F="--quiet --no-tensorboard --val-images 0"
case $1 in
setup)
  python3 -c "import warpnerf, warp, torch; print('ok', torch.__version__, warp.__version__, torch.cuda.get_device_name(0))"
  cat "$R/.commit" 2>/dev/null; nproc; nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv ;;
stage)  # the carried data to the stage (the carried copy is replaced by the next call's tree)
  cp -r .gpu/data/* $S/ && ls $S ;;
r1a)  # 47 (profiles: hash_sdf step, NeRF step fp32/bf16; composite bench), 44 (before)
  cp -r .gpu/data/* $S/ 2>/dev/null; ls $S
  nvidia-smi --query-gpu=name,driver_version --format=csv,noheader > $OUT/gpu.txt
  SDF="train volsdf --data $S/lego --field hash_sdf --device cuda --tf32 --batch 4096 --target-samples 262144"
  step prof_sdf 60 python3 scripts/profile_train_step.py --warm 600 --steps 30 --cprofile 0 \
    --json $OUT/prof_sdf.json -- $SDF
  step prof_fp32 60 python3 scripts/profile_train_step.py --warm 1500 --steps 50 --cprofile 0 \
    --json $OUT/prof_fp32.json -- train nerf --data $S/lego --device cuda
  step prof_bf16 60 python3 scripts/profile_train_step.py --warm 1500 --steps 50 --cprofile 0 \
    --json $OUT/prof_bf16.json -- train nerf --data $S/lego --device cuda --mlp-precision bf16
  step bench_composite 30 python3 -m warpnerf.cli bench composite --device cuda --json $OUT/bench_composite.json
  # issue 44: before (no weight average, the 20,000-step schedule) and after (the plain command),
  # then bf16 (issue 47 item 2) warm, after the fp32 run: the A/B the last session lacked
  ttq lego_before 90 --budgets 60 --label "before: --ema 0 --iters 20000" -- train nerf --data $S/lego --device cuda --ema 0 --iters 20000 $F
  evalkeep lego_before
  cat $OUT/walls.txt; cat $OUT/fail.txt 2>/dev/null; true ;;
r1b)  # 44 (after, crops), 47 (bf16 A/B, frames, CUDA tests)
  ttq lego_plain 90 --budgets 60 --label "the plain command" -- train nerf --data $S/lego --device cuda $F
  evalkeep lego_plain
  ttq lego_bf16 90 --budgets 60 --label "the plain command, --mlp-precision bf16" -- train nerf --data $S/lego --device cuda --mlp-precision bf16 $F
  step frame_plain 40 python3 scripts/bench_frame.py $Q/lego_plain/run --device cuda --data $S/lego --chunk 400000 --repeat 2 --json $OUT/frame_plain.json
  # the worst views' PNGs (gt | prediction | depth) of both, by the plain run's PSNR
  python3 - "$Q" "$OUT" <<'EOF' || true
import json, shutil, sys
q, out = sys.argv[1:]
rows = json.load(open(f"{q}/lego_plain/eval_val/metrics.json"))["per_image"]
worst = sorted(rows, key=lambda r: r["psnr"])[:3]
print("worst", [(r["image"], r["psnr"]) for r in worst])
for r in worst:
    for run in ("lego_before", "lego_plain"):
        i = r["image"]
        try:
            shutil.copy(f"{q}/{run}/eval_val/val_{i:03d}.png", f"{out}/{run}_val_{i:03d}.png")
        except OSError as e:
            print(e)
EOF
  l=$(left 5); [ "$l" -gt 30 ] && timeout "$l" python3 -m pytest -o addopts=-ra -q -k cuda -p no:cacheprovider \
    tests/test_tracer.py tests/test_step_ops.py tests/test_proposal.py tests/test_proposal_sampling.py \
    tests/test_composite.py tests/test_graph_step.py > $OUT/cuda_tests.log 2>&1
  tail -3 $OUT/cuda_tests.log
  cat $OUT/walls.txt; grep -h "^|" $OUT/*.log; cat $OUT/fail.txt 2>/dev/null; true ;;
r2a)  # after the merges: the NeRF step (regression check of the merged march), 49 (materials:
  # where the zero level sits, --level rendered), 47 item 4 (composite), the CUDA tests
  cp -r .gpu/data/* $S/ 2>/dev/null; ls $S
  step prof_fp32 60 python3 scripts/profile_train_step.py --warm 1500 --steps 50 --cprofile 0 \
    --json $OUT/prof_fp32.json -- train nerf --data $S/lego --device cuda
  step cuda_composite 40 python3 -m pytest -o addopts=-ra -q -x -k cuda -p no:cacheprovider tests/test_composite.py tests/test_composite_tiled.py
  SDF="--field hash_sdf --device cuda --tf32 --batch 4096 --target-samples 262144 --aabb 1.7 --fixed-beta --beta 0.01"
  ttq msdf 200 --budgets 120 --geometry materials --mesh-resolution 384 --label "materials hash_sdf, issue 49's command (defaults: mask 0.1, weight cull)" -- train volsdf --data $S/materials $SDF $F
  M=$Q/msdf/run
  step level_abc 60 python3 experiments/surfaces/level_offset.py $M --data $S/materials --parts abc --json $OUT/level_offset_abc.json
  step geo_rendered 50 python3 -m warpnerf.cli eval $M --geometry materials --mesh-resolution 384 --level rendered --quiet --out $Q/msdf/geo_rendered
  cp $Q/msdf/geo_rendered/*.json $OUT/ 2>/dev/null; ls $Q/msdf/geo_rendered >> $OUT/walls.txt 2>&1
  step bench_composite 45 python3 -m warpnerf.cli bench composite --device cuda --rays 1048576 --samples 128 --json $OUT/bench_composite.json
  l=$(left 5); [ "$l" -gt 30 ] && timeout "$l" python3 -m pytest -o addopts=-ra -q -k cuda -p no:cacheprovider \
    tests/test_composite_hard.py tests/test_graph_step.py tests/test_tracer.py tests/test_occupancy.py tests/test_contraction.py \
    tests/test_encoding.py tests/test_step_ops.py tests/test_composite.py tests/test_near_weight.py \
    tests/test_sphere_trace.py tests/test_composite_tiled.py > $OUT/cuda_tests.log 2>&1
  tail -3 $OUT/cuda_tests.log
  cat $OUT/walls.txt; grep -h "^|" $OUT/*.log; cat $OUT/fail.txt 2>/dev/null; true ;;
r2b)  # 49 (the delivered mesh at two more levels), 48 (beer's fog: the default and --near-loss)
  M=$Q/msdf/run
  step level_d 100 python3 experiments/surfaces/level_offset.py $M --data $S/materials --parts d --levels 0.02 0.01 --json $OUT/level_offset_d.json
  l=$(left 5); [ "$l" -gt 150 ] && OUT=$OUT DATA=$S/beer SECS=${BEER_SECS:-90} FRAMES=8 ROWS="base|;near|--near-loss 0.1" \
    timeout "$l" taskset -c 0-15 python3 scripts/gpu.py fog > $OUT/fog.log 2>&1
  cat $OUT/fog.md 2>/dev/null
  cat $OUT/walls.txt; cat $OUT/fail.txt 2>/dev/null; true ;;
esac
