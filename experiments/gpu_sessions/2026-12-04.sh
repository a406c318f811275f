#!/usr/bin/env bash
# Written 2026-12-03 (third session of the day, after its device time was spent) for the next
# session's H200, not run yet: what the day's third lease left open (docs/design/surfaces.md
# "Issue 49, tenth round", training.md "Issue 47, sixth round"). Run from the tree root on the
# device with Warp unpacked in /tmp/site and the data carried in .gpu/data:
# LIMIT=... bash THIS PHASE (setup: the earlier driver's, delegated)
# The calls (the tree is about 22 MB and each warp part 41 MB, so a call carries one of the
# parts or the data, never both; `git rev-parse --short HEAD > .commit` first, carried too):
#   A  carry [.gpu/p1]:          mkdir -p /root/stage && cp .gpu/p1/warp.part1 /root/stage/
#   B  carry [.gpu/p2, .commit]: cat /root/stage/warp.part1 .gpu/p2/warp.part2 | (mkdir -p
#      /tmp/site && tar -xJ -C /tmp/site) && export PYTHONPATH=/tmp/site && pip install -q
#      --no-deps --no-build-isolation -e . && LIMIT=200 bash experiments/gpu_sessions/2026-12-04.sh setup
#   C  carry [.gpu/data, .commit]: export PYTHONPATH=/tmp/site; mkdir -p /root/stage &&
#      cp -r .gpu/data/* /root/stage/; LIMIT=575 bash experiments/gpu_sessions/2026-12-04.sh g1
#   then carry [.commit] alone, one phase a call (LIMIT=575), at once after the last returns.
. "$(dirname "$0")/common.sh"  # R, OUT, S, Q, left, pin, step, ttq
F="--quiet --no-tensorboard --val-images 0"
MAT="--data $S/materials --field hash_sdf --device cuda --aabb 1.7"
GEO="--geometry materials --mesh-resolution 384"
B003="--beta 0.01 --beta-final 0.003 --beta-anneal-steps 6000 --march-step 0.0025 --max-samples 4096"
tail_out() { cat $OUT/walls.txt; grep -h "^|" $OUT/*.log; cat $OUT/fail.txt 2>/dev/null; true; }
frames() {  # name run data variants: the run's val frames (5 views) by variant, counters included
  step "frame_$1" 120 python3 scripts/bench_frame.py "$2" --data "$3" --device cuda --images 5 \
    --repeat 2 --variants "$4" --profile 3 --json "$OUT/frame_$1.json"
  python3 - "$OUT/frame_$1.json" <<'PY'
import json, sys
try:
    r = json.load(open(sys.argv[1]))
except OSError:
    sys.exit()
print(r["frame_ms_median"], r["psnr_vs_gt"], r["psnr_vs_rounds_min"])
print(r["samples_per_frame"])
PY
}
case $1 in
g1)  # 47 / 49: lego hash_sdf trained with forward differences (0.72x the step in one lease,
     # 11.56 vs 15.97 ms at step 400): does val stay at 33.13 dB after 300 s? If within 0.1 dB,
     # forward becomes the GPU default. Then its frame in rounds of 16 and 32 samples a live ray
  ttq lego_sdf_forward 330 --budgets 60,300 --spp 1 --label "lego hash_sdf, --sdf-gradient forward" \
    -- train volsdf --data $S/lego --field hash_sdf --device cuda --sdf-gradient forward $F
  frames lego_sdf_forward $Q/lego_sdf_forward/run $S/lego rounds,rounds-16,rounds-32
  tail_out ;;
g2)  # 49: the best materials recipe (beta -> 0.003) with forward differences, scored at 30, 60,
     # 120 and 300 s (item 6's plot: the current recipe's missing points), against the eighth
     # round's 0.0219 / 30.98 dB with central differences
  ttq materials_sdf_beta003_fwd 420 --budgets 30,60,120,300 --spp 1 $GEO \
    --label "materials hash_sdf, beta -> 0.003, forward differences" -- train volsdf $MAT $B003 \
    --sdf-gradient forward $F
  tail_out ;;
g3)  # 49: the floor's height (+0.011 at 0.003, +0.037 at 0.0015, -0.001 beside the spheres):
     # the hypothesis that the shadowless floor stops where carving by the density's front tail
     # stops, so a wider start carves it lower. Start at beta 0.02, same anneal to 0.003
  ttq materials_sdf_beta02_003 360 --budgets 60,300 --spp 1 $GEO \
    --label "materials hash_sdf, beta 0.02 -> 0.003" -- train volsdf $MAT --beta 0.02 \
    --beta-final 0.003 --beta-anneal-steps 6000 --march-step 0.0025 --max-samples 4096 $F
  tail_out ;;
g4)  # 47 / 49: the surface frame's levers on a central-differences run (a 45 s materials run):
     # normals by forward differences at render time (+fwd: 3 more evaluations a coloured sample
     # instead of 6; CPU: 0.63x the frame at -0.017 dB) and rounds that stop marching once a ray
     # is opaque (CPU: 0.71x the samples); the same image within 0.05 dB is the rule
  step g4_train 60 python3 -m warpnerf.cli train volsdf $MAT --fixed-beta --beta 0.01 \
    --max-seconds 45 --iters 100000 --out $Q/g4 $F
  frames g4 $Q/g4 $S/materials rounds,rounds+fwd,rounds-16,rounds-16+fwd,rounds-32+fwd
  tail_out ;;
g4b)  # g4 on the built-in scene at 200x200 (no data to carry: a lease's last minutes, when the
      # warp part fills the call's carry), 30 s of training, 3 views
  step g4b_train 50 python3 -m warpnerf.cli train volsdf --data builtin --builtin-size 200 \
    --field hash_sdf --device cuda --fixed-beta --beta 0.01 --max-seconds 30 --iters 100000 \
    --out $Q/g4b $F
  step frame_g4b 90 python3 scripts/bench_frame.py $Q/g4b --device cuda --images 3 --repeat 2 \
    --variants rounds,rounds+fwd,rounds-16,rounds-16+fwd --json $OUT/frame_g4b.json
  [ -f $OUT/frame_g4b.json ] && python3 -c "import json,sys; r=json.load(open(sys.argv[1])); print(r['frame_ms_median'], r['psnr_vs_gt'], r['psnr_vs_rounds_min'], r['samples_per_frame'])" $OUT/frame_g4b.json
  tail_out ;;
setup|p3|p4|p5|p6|p7|s0|p2)  # the earlier driver's phases (2026-12-03b.sh), unrun or to repeat
  trap - EXIT; OUT=$FINAL exec bash "$(dirname "$0")/2026-12-03b.sh" "$1" ;;
*) echo "unknown phase $1 (g1 g2 g3 g4 g4b setup p2-p7 s0)" >> $OUT/fail.txt; cat $OUT/fail.txt; exit 2 ;;
esac
# Budget (30 device minutes): setup ~1, g1 ~7.5, g2 ~7.5, g3 ~6.5, g4 ~2.5; in that order, then
# issue 44's hash_sdf rows (one change alone at 60 s, ~1.5 min each: `BUDGETS=60 WANT=80
# LIMIT=120 bash experiments/gpu_sessions/issue44_grid.sh {lego,materials}-sdf-{base,random_bg,
# view_cull,sparse_adam,huber,no_ema}`, several to a call), p3 (lego hash_sdf with the anneal +
# frame), p4 (lego NeRF frame profile), p7 (beer, issue 48).
# Carry: .gpu/data with lego and materials (32 MB); beer (8 MB) for p7.
