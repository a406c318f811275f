#!/usr/bin/env bash
# Issue 44 item 3, the part not yet run: each change of the recipe alone, then all of them, at
# 60 and 300 s, on lego and materials, NeRF hash and hash_sdf (one H200, one run at a time: one
# phase = one 300 s run and its scoring, about 6 minutes; 28 phases, about 3 hours of device time
# over several sessions). Written 2026-12-02 (tree of 2d88866), not run yet. Run from the tree
# root on the device with Warp unpacked in /tmp/site and the data carried in .gpu/data:
#     LIMIT=560 bash experiments/gpu_sessions/issue44_grid.sh SCENE-FIELD-CHANGE
# (BUDGETS=60 WANT=80 LIMIT=120 for a 60 s row alone)
# SCENE: lego | materials; FIELD: nerf | sdf; CHANGE: one of the keys of CHANGES below
# (e.g. `materials-nerf-huber`); `list` prints every phase.
. "$(dirname "$0")/common.sh"  # R, OUT, S, Q, left, pin, step, ttq
F="--quiet --no-tensorboard --val-images 0"
declare -A CHANGES=(
  [base]=""                                         # the command as it is (both with --ema 0.95)
  [random_bg]="--random-background on"              # item 1
  [view_cull]="--view-cull"                         # item 2
  [sparse_adam]="--sparse-adam --mlp-weight-decay 1e-6"  # item 3
  [no_ema]="--ema 0"                                # item 4, removed (NeRF's default has it)
  [ema]="--ema 0.95"                                # item 4, added (hash_sdf's default lacked it before 2026-12-03)
  [huber]="--photometric-loss huber"                # item 5
  [reflect]="--color-direction reflect"             # hash_sdf only: Ref-NeRF's colour input
  [small_hash]="--hash-max-res 512 --hash-log2-size 16"  # materials' capacity (third round)
  [hash256]="--hash-max-res 256 --hash-log2-size 15"    # smaller still (materials 33.52 dB at 60 s, 2026-12-03)
  [hash1024]="--hash-max-res 1024 --hash-log2-size 17"  # between it and the default (33.20 at 60 s)
  [hash128]="--hash-max-res 128 --hash-log2-size 14"    # smaller again (2026-12-03)
  [res256]="--hash-max-res 256"                         # the resolution alone, the default table
  [all]="--random-background on --view-cull --sparse-adam --mlp-weight-decay 1e-6 --ema 0.95 --photometric-loss huber"
)
if [ "$1" = list ]; then
  for s in lego materials; do for f in nerf sdf; do for c in "${!CHANGES[@]}"; do
    # (the defaults: both fields have the weight average since 2026-12-03; reflect: SDF only)
    case $f-$c in nerf-ema|sdf-ema|nerf-reflect) continue ;; esac
    echo "$s-$f-$c"; done; done; done
  exit 0
fi
IFS=- read -r scene field change <<< "$1"
[ -n "${CHANGES[$change]+x}" ] || { echo "unknown phase $1 (try: list)"; exit 2; }
cp -r .gpu/data/* $S/ 2>/dev/null
case $field in
nerf) CMD="train nerf --data $S/$scene --device cuda --iters 40000 $F" ;;
sdf)  CMD="train volsdf --data $S/$scene --field hash_sdf --device cuda --tf32 --batch 4096 --target-samples 262144 $F"
      [ "$scene" = materials ] && CMD="$CMD --aabb 1.7 --fixed-beta --beta 0.01" ;;  # issue 49's
*) echo "unknown field $field"; exit 2 ;;
esac
GEO=""; [ "$field-$scene" = sdf-materials ] && GEO="--geometry materials --mesh-resolution 384"
SPP="1,4"; [ "$field" = sdf ] && SPP=1  # hash_sdf trains one ray a pixel; its 4-ray eval costs minutes
ttq "$1" "${WANT:-400}" --budgets ${BUDGETS:-60,300} --spp $SPP $GEO --label "issue 44 grid: $scene $field ${CHANGES[$change]:-(as it is)}" -- $CMD ${CHANGES[$change]}
cat $OUT/walls.txt; grep -h "^|" $OUT/*.log; cat $OUT/fail.txt 2>/dev/null; true
