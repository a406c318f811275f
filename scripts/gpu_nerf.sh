#!/usr/bin/env bash
# NeRF figures on the lent GPU (see docs/design/nerf.md).
# Usage: gpu_nerf.sh materials|lego_seed|lego_full|lego_hash|lego_grid|lego_grid_more|sweep|capture
# (lego_grid: hash field + occupancy grid for SECS seconds, then eval on all val images;
#  lego_grid_more: resume that run for SECS more seconds and eval again; sweep: speed vs error)
# Expects Warp importable and the package installed; data under .devdata/ (carried); writes $OUT.
set -u
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
common="--device cuda --tf32 --layers 8 --width 256 --pos-freqs 10 --dir-freqs 4 --batch 4096 --quiet"
case "$1" in
materials)
  for vd in view-dependence no-view-dependence; do
    python3 -m warpnerf.cli train nerf --data .devdata/materials --out /tmp/mat_$vd --$vd $common \
      --samples 128 --iters 20000 --max-seconds ${SECS:-190} --val-every 1000 --val-images 2 \
      2>&1 | tail -4 | tee -a "$OUT/log.txt"
    python3 -m warpnerf.cli eval /tmp/mat_$vd --split val 2>&1 | tail -1 | tee -a "$OUT/log.txt"
    cp /tmp/mat_$vd/history.json "$OUT/materials_${vd}_history.json"
    cp /tmp/mat_$vd/eval_val/metrics.json "$OUT/materials_${vd}_metrics.json"
  done
  cp /tmp/mat_view-dependence/eval_val/val_003.png "$OUT/materials_vd_val_003.png"
  cp /tmp/mat_no-view-dependence/eval_val/val_003.png "$OUT/materials_novd_val_003.png"
  ;;
lego_seed|lego_full|lego_hash)
  if [ "$1" = lego_seed ]; then extra="--downscale 3 --samples 128"; else extra="--samples 64 --coarse-fine --fine-samples 128"; fi
  if [ "$1" = lego_hash ]; then
    common="--device cuda --tf32 --field hash --grid-res 0 --batch ${BATCH:-4096} --quiet"
    extra="--samples ${COARSE:-64} --coarse-fine --fine-samples ${FINE:-128}"
  fi
  python3 -m warpnerf.cli train nerf --data .devdata/lego --out /tmp/$1 $common $extra \
    --iters ${ITERS:-30000} --max-seconds ${SECS:-420} --val-every 1000 --val-images 2 2>&1 | tail -6 | tee -a "$OUT/log.txt"
  python3 -m warpnerf.cli eval /tmp/$1 --split val --max-images ${EVAL_IMAGES:-25} 2>&1 | tail -1 | tee -a "$OUT/log.txt"
  cp /tmp/$1/history.json "$OUT/$1_history.json"
  cp /tmp/$1/eval_val/metrics.json "$OUT/$1_metrics.json"
  cp /tmp/$1/eval_val/val_000.png "$OUT/$1_val_000.png"
  cp /tmp/$1/config.json "$OUT/$1_config.json"
  ;;
lego_grid|lego_grid_more)
  run=/tmp/lego_grid
  if [ "$1" = lego_grid ]; then
    python3 -m warpnerf.cli train nerf --data ${DATA:-.devdata/lego} --out $run --device cuda \
      --tf32 --field hash --batch 4096 --target-samples ${TARGET:-262144} ${EXTRA:-} \
      --iters ${ITERS:-20000} --max-seconds ${SECS:-120} --val-every 2000 --val-images 2 --quiet \
      2>&1 | tail -4 | tee -a "$OUT/log.txt"
  else
    python3 -m warpnerf.cli train nerf --out $run --resume --iters ${ITERS:-20000} \
      --max-seconds ${SECS:-180} --quiet 2>&1 | tail -3 | tee -a "$OUT/log.txt"
  fi
  python3 -m warpnerf.cli eval $run --split val --chunk 400000 --max-images ${EVAL_IMAGES:-25} ${EVAL_EXTRA:-} \
    2>&1 | tail -1 | tee -a "$OUT/log.txt"
  cp $run/history.json "$OUT/$1_history.json"
  cp $run/eval_val/metrics.json "$OUT/$1_metrics.json"
  cp $run/eval_val/val_000.png "$OUT/$1_val_000.png"
  cp $run/config.json "$OUT/$1_config.json"
  ;;
capture)
  # A real capture (COLMAP/LLFF, DATA=folder, NAME=label): hash field + grid, trained in stages
  # of STAGES seconds (cumulative), each followed by eval on the held-out images (every 8th).
  run=/tmp/${NAME:-capture}
  first=1
  for secs in ${STAGES:-60 60 180}; do
    if [ $first = 1 ]; then
      python3 -m warpnerf.cli train nerf --data $DATA --out $run --device cuda --tf32 --field hash \
        --batch 4096 --target-samples ${TARGET:-262144} ${EXTRA:-} --iters 100000 \
        --max-seconds $secs --val-every 100000 --val-images 0 --quiet 2>&1 | tail -3 | tee -a "$OUT/log.txt"
      first=0
    else
      python3 -m warpnerf.cli train nerf --out $run --resume --iters 100000 --max-seconds $secs \
        --quiet 2>&1 | tail -3 | tee -a "$OUT/log.txt"
    fi
    # CHUNK: rays per rendering chunk (the field sees at most 2^23 samples per call anyway)
    python3 -m warpnerf.cli eval $run --split val --chunk ${CHUNK:-400000} 2>&1 | tail -1 | tee -a "$OUT/log.txt"
    step=$(python3 -c "import json; print(json.load(open('$run/history.json'))['step'][-1])")
    cp $run/eval_val/metrics.json "$OUT/${NAME:-capture}_metrics_$step.json"
  done
  cp $run/history.json $run/config.json "$OUT/" 2>/dev/null
  mv "$OUT/history.json" "$OUT/${NAME:-capture}_history.json"; mv "$OUT/config.json" "$OUT/${NAME:-capture}_config.json"
  cp $run/eval_val/val_000.png "$OUT/${NAME:-capture}_val_000.png"
  ;;
sweep)
  python3 scripts/speed_vs_error.py sweep /tmp/lego_grid "$OUT/speed_vs_error.json" --images ${EVAL_IMAGES:-5} \
    2>&1 | tee -a "$OUT/log.txt"
  ;;
esac
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader >> "$OUT/log.txt"
