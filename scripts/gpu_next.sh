#!/usr/bin/env bash
# What the CPU-only session of 2026-11-25 afternoon left for the GPU (docs/PERFORMANCE.md "Issue
# 18: host cost of a launch" and "Issue 19"), one device call per STAGE (each well under 10 min):
#   STAGE=cuda      CUDA variants of every test (the array-descriptor bridge on CUDA first: its
#                   launches and generic overloads ran on CPU only), then the launch host cost on
#                   CUDA: scripts/launch_overhead.py --device cuda
#   STAGE=step      the hash-field training step on materials after the bridge change
#                   (scripts/profile_train_step.py, as the "Issue 18" profile), and what watching
#                   costs there (scripts/watch_overhead.py, TensorBoard + idle viewer)
#   STAGE=reflect   hash_sdf on materials with the reflection-aware colour head (issue 17's
#                   materials gap): the lapB run of PERFORMANCE.md plus --color-direction reflect
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
    python3 scripts/launch_overhead.py --device cuda --repeats 6 --json "$OUT/launch_cuda.json" 2>&1 | tail -8
    ;;
  step)
    M=${DATA:-.gpu/materials}
    python3 scripts/profile_train_step.py --warm 300 --steps 50 --json "$OUT/step_profile.json" -- \
      train nerf --data "$M" --field hash --device cuda --tf32 --batch 4096 \
      --target-samples 262144 --aabb 1.7 2>&1 | tail -30
    python3 scripts/watch_overhead.py --repeats 3 --json "$OUT/watch_cuda.json" -- --data "$M" \
      --field hash --device cuda --tf32 --batch 4096 --target-samples 262144 --aabb 1.7 \
      --iters 1500 --val-images 0 2>&1 | tail -6
    ;;
  reflect)
    DATA=${DATA:-.gpu/materials} SECS=300 TAG=reflect GEOMETRY=1 EXTRA="--aabb 1.7 \
      --beta-final 0.005 --beta-anneal-steps 6000 --march-step 0.0029 --max-samples 2048 \
      --color-direction reflect" bash "$(dirname "$0")/gpu_hash_sdf.sh"
    ;;
  *) echo "STAGE must be cuda, step or reflect"; exit 2 ;;
esac
