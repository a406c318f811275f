#!/usr/bin/env bash
# What the CPU-only session of 2026-11-25 afternoon left for the GPU (docs/design/training.md "Issue
# 18: host cost of a launch" and docs/design/viewer.md "Issue 19"), one device call per STAGE (each well under 10 min):
#   STAGE=cuda      CUDA variants of every test (the array-descriptor bridge on CUDA first: its
#                   launches and generic overloads ran on CPU only), then the launch host cost on
#                   CUDA: experiments/launch_overhead.py --device cuda
#   STAGE=step      the hash-field training step on materials after the bridge change
#                   (scripts/profile_train_step.py, as the "Issue 18" profile), and what watching
#                   costs there (scripts/watch_overhead.py, TensorBoard + idle viewer)
#   STAGE=ttq       issue 18's time to quality on lego (DATA=.gpu/lego; BUDGETS, LABEL, EXTRA)
#   STAGE=variants  short time-to-quality runs of several flag sets (VARIANTS="a;b", BUDGETS)
#   STAGE=tests     the CUDA variants of TESTS (default: test_distortion, test_contraction)
#   STAGE=syncs     where the training step synchronises (scripts/sync_sites.py)
#   STAGE=capture   issue 20: a real capture (DATA=.gpu/beer, NAME, LABEL, BUDGETS, EXTRA) trained
#                   once with snapshots, every val image scored at each budget, spiral frames of
#                   the final state (RUN/render_spiral, FRAMES at SIZE) and one depth frame
#   STAGE=reflect   hash_sdf on materials with the reflection-aware colour head (issue 17's
#                   materials gap): the lapB run of docs/design/surfaces.md plus --color-direction reflect
# Usage on the device (Warp on PYTHONPATH, package installed, data in .gpu/materials):
#   STAGE=cuda bash scripts/gpu_next.sh      (writes under $OUT)
set -u
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
git log -1 --format='commit %H' 2>/dev/null | tee "$OUT/commit.txt"
case "${STAGE:-cuda}" in
  cuda)
    python3 -m pytest tests -q -k "cuda" -p no:cacheprovider 2>&1 | tail -25 | tee "$OUT/pytest_cuda.txt"
    python3 experiments/launch_overhead.py --device cuda --repeats 6 --json "$OUT/launch_cuda.json" 2>&1 | tail -8
    ;;
  step)
    M=${DATA:-.gpu/materials}
    python3 scripts/profile_train_step.py --warm 300 --steps 50 --json "$OUT/step_profile.json" -- \
      train nerf --data "$M" --field hash --device cuda --tf32 --batch 4096 \
      --target-samples 262144 --aabb 1.7 2>&1 | tail -30
    python3 scripts/watch_overhead.py --repeats 3 --json "$OUT/watch_cuda.json" -- --data "$M" \
      --field hash --device cuda --tf32 --batch 4096 --target-samples 262144 --aabb 1.7 \
      --iters 1500 --val-images 0 ${WATCH_EXTRA:-} 2>&1 | tail -6
    ;;
  reflect)
    DATA=${DATA:-.gpu/materials} SECS=300 TAG=reflect GEOMETRY=1 EXTRA="--aabb 1.7 \
      --beta-final 0.005 --beta-anneal-steps 6000 --march-step 0.0029 --max-samples 2048 \
      --color-direction reflect" bash "$(dirname "$0")/gpu_hash_sdf.sh"
    ;;
  ttq)
    # issue 18's figure: lego 400x400, hash field + occupancy grid, one training with snapshots at
    # the budgets, every val image scored at each (scripts/time_to_quality.py), plus eval frame ms
    L=${DATA:-.gpu/lego}
    python3 scripts/time_to_quality.py run /tmp/ttq_lego --budgets ${BUDGETS:-5,15,30,60,120,300} \
      --label "warpnerf ${LABEL:-main}" --chunk 400000 -- train nerf --data "$L" --field hash \
      --device cuda --tf32 --batch 4096 --target-samples 262144 --val-images 0 --quiet \
      ${EXTRA:-} 2>&1 | tail -12 | tee "$OUT/ttq_lego.txt"
    cp /tmp/ttq_lego/ttq.json "$OUT/ttq_lego.json"; cp /tmp/ttq_lego/ttq.png "$OUT/ttq_lego.png"
    cp /tmp/ttq_lego/run/history.json "$OUT/ttq_lego_history.json"
    python3 -m warpnerf.cli eval /tmp/ttq_lego/run --split val --chunk 400000 --max-images 20 \
      --out /tmp/ttq_eval > "$OUT/ttq_eval.json" 2>&1; tail -c 600 "$OUT/ttq_eval.json"
    ;;
  capture)
    D=${DATA:-.gpu/beer}; N=${NAME:-beer}
    python3 scripts/time_to_quality.py run /tmp/cap_$N --budgets ${BUDGETS:-60,120,300} \
      --label "$N ${LABEL:-main}" --chunk 65536 -- train nerf --data "$D" --field hash \
      --device cuda --tf32 --batch 4096 --target-samples 262144 --val-images 0 --quiet \
      --no-tensorboard ${EXTRA:-} 2>&1 | tail -8 | tee "$OUT/cap_$N.txt"
    cp /tmp/cap_$N/ttq.json "$OUT/cap_$N.json"; cp /tmp/cap_$N/run/config.json "$OUT/cap_${N}_config.json"
    python3 -m warpnerf.cli render /tmp/cap_$N/run --frames ${FRAMES:-6} --size ${SIZE:-640x360} \
      2>&1 | tail -2
    # one sheet of the spiral's colour and depth frames (a call returns few files)
    python3 scripts/contact_sheet.py "$OUT/spiral_$N.png" --cols ${FRAMES:-6} --every 1 \
      /tmp/cap_$N/run/render_spiral/rgb_*.png /tmp/cap_$N/run/render_spiral/depth_*.png
    if [ -n "${ROUND:-}" ]; then  # eval frame time with render rounds of ROUND samples a ray
      python3 -m warpnerf.cli eval /tmp/cap_$N/run --split val --round-samples "$ROUND" \
        --out /tmp/cap_${N}_round > "$OUT/cap_${N}_round$ROUND.json" 2>&1
      tail -c 400 "$OUT/cap_${N}_round$ROUND.json"
    fi
    ;;
  variants)
    # short time-to-quality runs of several flag sets (VARIANTS: sets separated by ';'), in order
    L=${DATA:-.gpu/lego}
    i=0
    IFS=';' read -ra sets <<< "${VARIANTS:-}"
    for v in "${sets[@]}"; do
      i=$((i+1))
      rm -rf /tmp/ttq_v$i; python3 scripts/time_to_quality.py run /tmp/ttq_v$i --budgets ${BUDGETS:-5,15,30,60} \
        --label "v$i:$v" --chunk ${CHUNK:-400000} -- train nerf --data "$L" --field hash --device cuda \
        --tf32 --batch 4096 --val-images 0 --quiet --no-tensorboard $v 2>&1 | tail -7 \
        | tee "$OUT/ttq_v${i}${TAG:-}.txt"
      cp /tmp/ttq_v$i/ttq.json "$OUT/ttq_v${i}${TAG:-}.json"
    done
    ;;
  tests)  # the CUDA variants of a few test files (TESTS, default: issue 20's new code)
    python3 -m pytest ${TESTS:-tests/test_distortion.py tests/test_contraction.py} -q -k cuda \
      -p no:cacheprovider 2>&1 | tail -8 | tee "$OUT/pytest_cuda_subset.txt"
    ;;
  syncs)
    python3 scripts/sync_sites.py --json "$OUT/sync_sites.json" -- train nerf --data \
      ${DATA:-builtin} --field hash --device cuda --tf32 --batch 4096 \
      --target-samples 262144 ${EXTRA:-} 2>&1 | tail -25
    ;;
  *) echo "STAGE must be cuda, tests, step, reflect, capture, ttq, variants or syncs"; exit 2 ;;
esac
