#!/usr/bin/env bash
# Written 2026-12-03 (fifth session of the day, after its device time was spent) for the next
# session's H200, not run yet: what 2026-12-05.sh's lease (nerf.md "Issue 44, eleventh round",
# surfaces.md "Issue 49, thirteenth round", training.md "Issue 47, eighth round") left open.
# hash_sdf trains with Huber and forward differences by default, and the rounds path colours
# the samples weighing 1e-3 (or a 100th of their ray's heaviest sample where less) with their
# ray's mean colour for the rest (all since 2026-12-03).
# The calls are 2026-12-05.sh's (A: warp part 1; B: part 2 + `setup`; C: the data + the first
# phase; then one phase a call with [.commit] alone).
. "$(dirname "$0")/common.sh"  # R, OUT, S, Q, left, pin, step, ttq, cuda_setup, tail_out
F="--quiet --no-tensorboard --val-images 0"
frames() {  # name run data variants: 5 val views by variant (bench_frame.py), the summary
  step "frame_$1" 120 python3 scripts/bench_frame.py "$2" --data "$3" --device cuda --images 5 \
    --repeat 2 --variants "$4" --profile 3 --json "$OUT/frame_$1.json"
  python3 -c "import json,sys; r=json.load(open(sys.argv[1])); [print(k, r[k]) for k in ('frame_ms_median', 'psnr_vs_gt', 'psnr_vs_rounds_min', 'samples_per_frame')]" "$OUT/frame_$1.json"
}
case $1 in
setup)  # the CUDA variants of the tests this session's code touches
  cuda_setup tests/test_tracer.py tests/test_sdf_gradient.py tests/test_hash_sdf.py ;;
f1)  # 47 / 49: the frame with the rounds path's new default (colour from 1e-3 or a 100th of
     # the ray's heaviest sample, the rest their ray's mean colour) timed against the old rule (1e-5, black) and the measured black 1e-3,
     # on a 60 s lego hash_sdf run with the defaults (Huber) and a 60 s lego NeRF run; the
     # rule: the same image within 0.05 dB of val; lego hash_sdf target 25 ms (22.1 measured
     # for black at 1e-3, 27.8 for the old rule)
  step f1_sdf 100 python3 -m warpnerf.cli train volsdf --data $S/lego --field hash_sdf \
    --device cuda --max-seconds 60 --iters 100000 --out $Q/f1_sdf $F
  frames lego_sdf $Q/f1_sdf $S/lego rounds,rounds+eps1e-5+black,rounds+black,rounds+eps1e-4
  step f1_nerf 100 python3 -m warpnerf.cli train nerf --data $S/lego --device cuda \
    --max-seconds 60 --iters 40000 --out $Q/f1_nerf $F
  frames lego_nerf $Q/f1_nerf $S/lego rounds,rounds+eps1e-5+black,rounds+black
  tail_out ;;
s1)  # 44: the winner's second seed (Huber on lego hash_sdf: 33.19 / 34.63 dB at 60 / 300 s)
  ttq lego_sdf_huber_seed1 330 --budgets 60,300 --spp 1 --label "lego hash_sdf (Huber), seed 1" \
    -- train volsdf --data $S/lego --field hash_sdf --device cuda --seed 1 $F
  tail_out ;;
c1)  # 44: the combination on lego hash_sdf at 60 s: Huber (now the default) with random
     # backgrounds (+0.30 alone, central differences, MSE), then with view culling as well
  ttq lego_sdf_huber_rbg 90 --budgets 60 --spp 1 --label "lego hash_sdf, Huber + random bg" \
    -- train volsdf --data $S/lego --field hash_sdf --device cuda --random-background on $F
  ttq lego_sdf_huber_rbg_cull 90 --budgets 60 --spp 1 \
    --label "lego hash_sdf, Huber + random bg + view cull" -- train volsdf --data $S/lego \
    --field hash_sdf --device cuda --random-background on --view-cull $F
  tail_out ;;
h4|h3b)  # 2026-12-05.sh's unrun phases (h4: beta 0.05 -> 0.003 on materials, now with Huber)
  trap - EXIT; OUT=$FINAL exec bash "$(dirname "$0")/2026-12-05.sh" "$1" ;;
*) echo "unknown phase $1 (setup f1 s1 c1 h4 h3b)" >> $OUT/fail.txt; cat $OUT/fail.txt; exit 2 ;;
esac
# Budget (30 device minutes): setup ~1, f1 ~5, s1 ~6, h4 ~6.5, c1 ~3.5; then issue 48's driver
# (issue48.sh, about 85 minutes in all: b0 first).
