#!/usr/bin/env bash
# Surface figures on the lent GPU (docs/design/surfaces.md). Usage:
#   gpu_surfaces.sh trace            CUDA tests of the surface code, demos 06/07/08 on cuda
#   gpu_surfaces.sh volsdf_materials BETA...   VolSDF on materials with fixed betas ("learned": learned)
#   gpu_surfaces.sh volsdf_lego      VolSDF on lego (learned beta), eval, spiral renders, mesh
# Expects Warp importable and the package installed; data in $DATA (default .devdata); writes $OUT.
set -u
OUT=${OUT:-/tmp/out}
DATA=${DATA:-.devdata}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
vs="--device cuda --tf32 --batch ${BATCH:-1024} --samples 64 --fine-samples 64 --quiet"
vs="$vs --iters ${ITERS:-4000} --max-seconds ${SECS:-150} --val-every 1000 --val-images 2"
case "$1" in
trace)
  python3 -m pytest -q -p no:cacheprovider tests/test_sphere_trace.py tests/test_neural_sdf.py \
    tests/test_encoding.py tests/test_nerf.py -k cuda 2>&1 | tail -3 | tee -a "$OUT/log.txt"
  python3 demos/06_sphere_trace_torus.py --device cuda --out /tmp/d06 --size 400 | tail -1 | tee -a "$OUT/log.txt"
  python3 demos/07_sphere_trace_scene.py --device cuda --out /tmp/d07 --size 400 | tail -1 | tee -a "$OUT/log.txt"
  python3 demos/08_neural_sdf.py --device cuda --points "$DATA/bunny_pointcloud.npz" --iters 3000 \
    --batch 8192 --resolution 256 --out /tmp/d08 | tail -1 | tee -a "$OUT/log.txt"
  cp /tmp/d06/frame_000.png "$OUT/torus_frame.png"; cp /tmp/d07/frame_000.png "$OUT/scene_frame.png"
  cp /tmp/d08/run/mesh.png "$OUT/bunny_mesh.png"; cp /tmp/d08/run/metrics.json "$OUT/bunny_metrics.json"
  ;;
volsdf_materials)
  shift
  for beta in "$@"; do
    if [ "$beta" = learned ]; then extra=""; else extra="--beta $beta --fixed-beta"; fi
    run=/tmp/vs_mat_$beta
    python3 -m warpnerf.cli train volsdf --data "$DATA/materials" --out $run --aabb 1.7 $vs $extra \
      2>&1 | tail -2 | tee -a "$OUT/log.txt"
    python3 -m warpnerf.cli eval $run --split val 2>&1 | tail -1 | tee -a "$OUT/log.txt"
    python3 scripts/materials_geometry.py $run --json "$OUT/materials_beta_${beta}_geometry.json" \
      2>&1 | tail -1 | tee -a "$OUT/log.txt"
    cp $run/history.json "$OUT/materials_beta_${beta}_history.json"
    cp $run/eval_val/metrics.json "$OUT/materials_beta_${beta}_metrics.json"
    cp $run/eval_val/val_003.png "$OUT/materials_beta_${beta}_val_003.png"
  done
  ;;
volsdf_lego)
  run=/tmp/vs_lego
  python3 -m warpnerf.cli train volsdf --data "$DATA/lego" --out $run $vs 2>&1 | tail -2 | tee -a "$OUT/log.txt"
  python3 -m warpnerf.cli eval $run --split val --max-images ${EVAL_IMAGES:-10} 2>&1 | tail -1 | tee -a "$OUT/log.txt"
  python3 -m warpnerf.cli render $run --frames ${FRAMES:-20} --size 200x200 2>&1 | tail -1 | tee -a "$OUT/log.txt"
  python3 -m warpnerf.cli mesh $run --resolution 256 --out "$OUT/lego_volsdf.ply" 2>&1 | tail -1 | tee -a "$OUT/log.txt"
  cp $run/history.json $run/eval_val/metrics.json "$OUT/" ; cp $run/render_spiral/geometry.gif $run/render_spiral/rgb.gif "$OUT/"
  cp $run/eval_val/val_000.png "$OUT/lego_volsdf_val_000.png"
  ;;
esac
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader >> "$OUT/log.txt"
