#!/usr/bin/env bash
# The GPU driver of the second 2026-12-02 session (issue 44: rays through random points of their
# pixels and supersampled scoring; issue 49: lego hash_sdf re-measured; one H200), kept as the
# record of how the design notes' figures of that session were measured. Run from the tree root
# on the device with Warp unpacked in /tmp/site and the data carried in .gpu/data: bash THIS PHASE
. "$(dirname "$0")/common.sh"  # R, OUT, S, Q, left, pin, step, ttq
F="--quiet --no-tensorboard --val-images 0"
LEGO="train nerf --data $S/lego --device cuda --iters 40000 $F"  # the plain command (40,000 steps)
case $1 in
setup)
  python3 -c "import warpnerf, warp, torch; print('ok', torch.__version__, warp.__version__, torch.cuda.get_device_name(0))"
  cat "$R/.commit" 2>/dev/null; nproc; nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv ;;
g1)  # 44: the plain command, scored at the pixels' centres and with 4 rays a pixel
  cp -r .gpu/data/* $S/ 2>/dev/null; ls $S
  nvidia-smi --query-gpu=name,driver_version --format=csv,noheader > $OUT/gpu.txt
  ttq lego_plain 400 --budgets 60,300 --spp 1,4 --label "the plain command" -- $LEGO
  cat $OUT/walls.txt; grep -h "^|" $OUT/*.log; cat $OUT/fail.txt 2>/dev/null; true ;;
g2)  # 44: the same with --pixel-jitter
  ttq lego_jitter 400 --budgets 60,300 --spp 1,4 --label "the plain command, --pixel-jitter" -- $LEGO --pixel-jitter
  cat $OUT/walls.txt; grep -h "^|" $OUT/*.log; cat $OUT/fail.txt 2>/dev/null; true ;;
g5)  # 44: the plain command with --train-spp 4 (each pixel the mean of its 2x2 sub-rays), setup first
  cp -r .gpu/data/* $S/ 2>/dev/null; ls $S
  nvidia-smi --query-gpu=name,driver_version --format=csv,noheader > $OUT/gpu.txt
  ttq lego_tspp4 400 --budgets 60,300 --spp 1,4 --label "the plain command, --train-spp 4" -- $LEGO --train-spp 4
  cat $OUT/walls.txt; grep -h "^|" $OUT/*.log; cat $OUT/fail.txt 2>/dev/null; true ;;
g6)  # 44: materials 60 s, plain and --train-spp 4, each scored with 1 and 4 rays a pixel (run as
  # one inline command at the end of the session, with the same flags)
  M="train nerf --data $S/materials --device cuda --iters 40000 $F"
  ttq mat_base 90 --budgets 60 --spp 1,4 --label "materials base" -- $M
  ttq mat_tspp4 90 --budgets 60 --spp 1,4 --label "materials tspp4" -- $M --train-spp 4
  cat $OUT/walls.txt; grep -h "^|" $OUT/*.log; cat $OUT/fail.txt 2>/dev/null; true ;;
g2b)  # 44: the g1/g2 runs' snapshots scored with 2, 8 and 16 rays a pixel (run inline likewise)
  for s in 2 8 16; do pin python3 scripts/time_to_quality.py eval $Q/lego_plain/run $OUT/plain_spp$s.json --spp $s --label "plain spp $s"; done
  pin python3 scripts/time_to_quality.py eval $Q/lego_jitter/run $OUT/jitter_spp16.json --spp 16 --label "jitter spp 16" ;;
# not run this session (no device time left): g3 (materials with the smaller grid, +-jitter), g4
g3)  # 44: materials (NeRF hash, the smaller grid of the third round), with and without --pixel-jitter
  M="train nerf --data $S/materials --device cuda --iters 40000 --hash-max-res 512 --hash-log2-size 16 $F"
  ttq mat_base 160 --budgets 120 --spp 1,4 --label "materials, r512 t16" -- $M
  ttq mat_jitter 160 --budgets 120 --spp 1,4 --label "materials, r512 t16, --pixel-jitter" -- $M --pixel-jitter
  cat $OUT/walls.txt; grep -h "^|" $OUT/*.log; cat $OUT/fail.txt 2>/dev/null; true ;;
g4)  # 49: lego hash_sdf (train volsdf's defaults on a GPU), 300 s; its step and frame
  SDF="train volsdf --data $S/lego --field hash_sdf --device cuda --tf32 --batch 4096 --target-samples 262144 $F"
  ttq lego_sdf 380 --budgets 60,300 --label "lego hash_sdf" -- $SDF ${SDF_EXTRA:-}
  step frame_sdf 40 python3 scripts/bench_frame.py $Q/lego_sdf/run --device cuda --data $S/lego --chunk 400000 --repeat 2 --json $OUT/frame_sdf.json
  cat $OUT/walls.txt; grep -h "^|" $OUT/*.log; cat $OUT/fail.txt 2>/dev/null; true ;;
esac
