#!/usr/bin/env bash
# Written 2026-12-03 (second session of the day, after its device time was spent) for the next
# session's H200, not run yet: what the day's measurements left open (docs/design/surfaces.md
# "Issue 49, eighth round", training.md "Issue 47, fourth round", nerf.md "Issue 44, eighth
# round"). Run from the tree root on the device with Warp unpacked in /tmp/site and the data
# carried in .gpu/data: LIMIT=... bash THIS PHASE
. "$(dirname "$0")/common.sh"  # R, OUT, S, Q, left, pin, step, ttq
F="--quiet --no-tensorboard --val-images 0"
MAT="--data $S/materials --field hash_sdf --device cuda --aabb 1.7"
tail_out() { cat $OUT/walls.txt; grep -h "^|" $OUT/*.log; cat $OUT/fail.txt 2>/dev/null; true; }
frame() {  # name run data: the run's frame (rounds path and tracer) with a profile of 5 frames
  step "frame_$1" 90 python3 scripts/bench_frame.py "$2" --data "$3" --device cuda --images 0 \
    --repeat 3 --variants rounds,traced --profile 5 --json "$OUT/frame_$1.json"
}
case $1 in
setup)  # the import, the data, the CUDA variants of the tests the session's code touches
  python3 -c "import warpnerf, warp, torch; print('ok', torch.__version__, warp.__version__, torch.cuda.get_device_name(0))"
  cat "$R/.commit" 2>/dev/null; cp -r .gpu/data/* $S/ 2>/dev/null
  l=$(left 5); timeout "$l" python3 -m pytest -o addopts=-ra -q -k cuda -p no:cacheprovider \
    tests/test_hash_sdf.py tests/test_neus_density.py tests/test_graph_step.py \
    > $OUT/cuda_tests.log 2>&1
  echo "pytest rc=$?" >> $OUT/cuda_tests.log; tail -8 $OUT/cuda_tests.log ;;
f0)  # 49 / 47: the surface frame's profile, small enough for a session's last minutes: a 45 s
     # materials hash_sdf run (the GPU preset), then its val frames with and without fp16 MLPs
     # (data: MATDIR, default $S/materials)
  D=${MATDIR:-$S/materials}
  step f0_train 60 python3 -m warpnerf.cli train volsdf --data $D --field hash_sdf --device cuda \
    --aabb 1.7 --fixed-beta --beta 0.01 --max-seconds 45 --iters 100000 --out $Q/f0 $F
  step frame_f0 40 python3 scripts/bench_frame.py $Q/f0 --data $D --device cuda --images 5 \
    --repeat 2 --variants rounds,traced --profile 5 --json $OUT/frame_f0.json
  step frame_f0_half 30 python3 scripts/bench_frame.py $Q/f0 --data $D --device cuda --images 5 \
    --repeat 2 --variants rounds --half --profile 5 --json $OUT/frame_f0_half.json
  python3 - "$OUT" <<'PY'
import json, sys
for n in ("frame_f0", "frame_f0_half"):
    try:
        r = json.load(open(f"{sys.argv[1]}/{n}.json"))
    except OSError:
        continue
    p = r["profile"]
    print(n, r["frame_ms_median"], r["psnr_vs_gt"], "busy", p["device_busy_ms_per_frame"],
          "launches", p["launches_per_frame"], "syncs", p["host_syncs_per_frame"], p["counters"])
    for k, v in list(p["top_ms_per_frame"].items())[:12]:
        print(f"  {v:8.3f}  {k[:90]}")
PY
  tail_out ;;
s0a)  # s0's step A/B alone, short (a session's last minutes): central, then forward
  for g in central forward; do
    step "prof_sdf_$g" 30 python3 scripts/profile_train_step.py --warm 400 --steps 40 \
      --cprofile 0 --json "$OUT/prof_sdf_$g.json" -- train volsdf --data $S/lego \
      --field hash_sdf --device cuda --sdf-gradient $g
    grep -h '"step_ms_median"\|"device_busy\|"samples_per_ray\|"rays_per' "$OUT/prof_sdf_$g.log"
  done
  tail_out ;;
s0)  # 47 / 49: the hash_sdf step with forward differences (4 SDF evaluations a coloured sample
     # instead of 7; predicted: about 3/7 of the step's SDF work, ~9 of 17-20 ms, so 3.5-4 ms
     # less), both orders in one lease, then lego at 300 s with it (33.13 dB with central)
  for g in central forward forward central; do
    step "prof_sdf_$g" 60 python3 scripts/profile_train_step.py --warm 600 --steps 50 \
      --cprofile 0 --json "$OUT/prof_sdf_$g.json" -- train volsdf --data $S/lego \
      --field hash_sdf --device cuda --sdf-gradient $g
    grep -h '"step_ms_median"\|"device_busy' "$OUT/prof_sdf_$g.log"
  done
  ttq lego_sdf_forward 330 --budgets 60,300 --spp 1 --label "lego hash_sdf, --sdf-gradient forward" \
    -- train volsdf --data $S/lego --field hash_sdf --device cuda --sdf-gradient forward $F
  tail_out ;;
p0)  # 49: the floor's +0.010 (both Laplace runs of 2026-12-03): a CPU A/B at 50x50 put it on the
     # opacity loss's push on the object's own rays (surfaces.md "Issue 49, ninth round"):
     # the best recipe (beta 0.01 -> 0.003) with --mask-pixels background
  ttq materials_sdf_beta003_maskbg 360 --budgets 60,300 --spp 1 --geometry materials \
    --mesh-resolution 384 --label "materials hash_sdf, beta -> 0.003, --mask-pixels background" \
    -- train volsdf $MAT --beta 0.01 --beta-final 0.003 --beta-anneal-steps 6000 \
    --max-samples 4096 --mask-pixels background $F
  tail_out ;;
p1)  # 49: the spheres' erosion follows the final beta (0.0216 at 0.01, 0.0095 at 0.003, as the
     # seventh round predicted): 0.0015 predicts 0.005; the march step follows it by default now
     # (5/6 of it: 0.00125, --max-samples 4712)
  ttq materials_sdf_beta0015 360 --budgets 60,300 --spp 1 --geometry materials --mesh-resolution 384 \
    --label "materials hash_sdf, beta 0.01 -> 0.0015 (default step 0.00125)" -- train volsdf $MAT \
    --beta 0.01 --beta-final 0.0015 --beta-anneal-steps 6000 $F
  tail_out ;;
p2)  # 49: the best mesh's recipe (0.0219) with a second seed, and the new diagnostics: the
     # disk's top ring by ring (delivered.disk_top_by_radius) and the depth error by shape with
     # its sign (depth_by_shape): where the floor's +0.010 comes from
  ttq materials_sdf_beta003_seed1 360 --budgets 60,300 --spp 1 --geometry materials \
    --mesh-resolution 384 --label "materials hash_sdf, beta 0.01 -> 0.003, seed 1" -- \
    train volsdf $MAT --beta 0.01 --beta-final 0.003 --beta-anneal-steps 6000 \
    --max-samples 4096 --seed 1 $F
  tail_out ;;
p3)  # 49 / 44: does the anneal keep lego's 33.13 dB (learned beta ends near 0.003 there)?
     # Then the surface frame's profile (target 25 ms; 39.8 ms)
  ttq lego_sdf_beta003 330 --budgets 60,300 --spp 1 --label "lego hash_sdf, beta 0.01 -> 0.003" \
    -- train volsdf --data $S/lego --field hash_sdf --device cuda --beta 0.01 --beta-final 0.003 \
    --beta-anneal-steps 6000 $F
  frame lego_sdf_beta003 $Q/lego_sdf_beta003/run $S/lego
  tail_out ;;
p4)  # 47: lego NeRF's frame with a profile (target 4 ms; the rounds path 10.7 ms, the tracer
     # 16.7 in one chunk): where a frame's time goes, after a 60 s plain run
  ttq lego_nerf_60 100 --budgets 60 --spp 1 --label "lego, the plain command, 60 s" -- \
    train nerf --data $S/lego --device cuda --iters 40000 $F
  frame lego_nerf_60 $Q/lego_nerf_60/run $S/lego
  tail_out ;;
p5)  # 49 / 44: the plain hash_sdf command (GPU preset) on its own 20,000-step schedule, lego
     # (2026-12-03.sh s1, not run there; its archive is s1.tgz)
  trap - EXIT; OUT=$FINAL exec bash "$(dirname "$0")/2026-12-03.sh" s1 ;;
p6)  # 44: the materials winner's second seed, 300 s (33.95 dB with seed 0): 2026-12-03.sh m1
  trap - EXIT; OUT=$FINAL exec bash "$(dirname "$0")/2026-12-03.sh" m1 ;;
p7)  # 48: beer with today's capture defaults (the weight average among them), held-out images
  ttq beer_defaults 340 --budgets 120,300 --spp 1 --label "beer, today's capture defaults" -- \
    train nerf --data $S/beer --device cuda $F
  tail_out ;;
esac
# Budget: setup ~1 min, s0 ~8.5, p1-p3 ~6.5 each (p3 with its frame ~8), p4 ~3.5, p5 ~6, p6 ~6, p7 ~6.5:
# more than one session's 30 minutes; in order of what they settle: p0 (~6.5), s0 (~8.5 min:
# the step A/B ~2.5, lego 300 s ~6), p1, p2, p3, p4, p5, p6, p7; f0 (~2.5 min) where a session has only its
# last minutes.
# Carry: .gpu/data with lego and materials (32 MB); beer (8 MB) for p7.
