#!/usr/bin/env bash
# Surfaces on the fast path, on the lent GPU: lego 400x400 with the hash_sdf field (hash-grid SDF,
# VolSDF density, occupancy grid) trained for SECS seconds, evaluated on every val image, meshed.
# Usage: DATA=.gpu/lego SECS=240 [EXTRA="--c2f-every 0"] [TAG=x] bash scripts/gpu_hash_sdf.sh
#        DATA=.gpu/materials SECS=300 EXTRA="--aabb 1.7" TAG=materials GEOMETRY=1 bash ...
# (writes $OUT/surface_$TAG.md, the history, metrics and mesh summary; GEOMETRY=1: the mesh's
# Chamfer distance and the depth error against materials' analytic geometry, materials_geometry.py)
# SNAP=15,30,60,120 also keeps snapshots at those training seconds and evaluates each (all val
# images; geometry too with GEOMETRY=1): scripts/time_to_quality.py -> $OUT/ttq_$TAG.json.
# SPHERE=1: sphere tracing against volume rendering on the final run (surface_renderers.py).
source "$(dirname "$0")/_gpu_ab.sh"  # OUT, DATA
SECS=${SECS:-240}
TAG=${TAG:-lego}
R=/tmp/sdf_$TAG
rm -rf $R ${R}_eval
python3 -m warpnerf.cli train volsdf --data "$DATA" --field hash_sdf --device cuda --tf32 \
  --batch 4096 --target-samples 262144 --iters 100000 --max-seconds "$SECS" --val-images 0 \
  --quiet --out $R ${SNAP:+--snapshots $SNAP,$SECS} ${EXTRA:-} > "$OUT/train_$TAG.json" 2>> "$OUT/log_$TAG.txt" || echo "train failed" | tee -a "$OUT/log_$TAG.txt"
python3 -m warpnerf.cli eval $R --split val --chunk 400000 --out ${R}_eval > "$OUT/eval_$TAG.json" 2>> "$OUT/log_$TAG.txt" || echo "eval failed" | tee -a "$OUT/log_$TAG.txt"
python3 -m warpnerf.cli mesh $R --out "$OUT/mesh_$TAG.ply" --resolution 384 > "$OUT/mesh_$TAG.json" 2>> "$OUT/log_$TAG.txt" || echo "mesh failed" | tee -a "$OUT/log_$TAG.txt"
rm -f "$OUT/mesh_$TAG.ply"  # (large; the summary and screenshot come back)
if [ "${GEOMETRY:-0}" = 1 ]; then
  python3 -m warpnerf.cli eval $R --geometry materials --mesh-resolution 384 --geometry-views 0 > "$OUT/geometry_$TAG.json" 2>> "$OUT/log_$TAG.txt" || echo "geometry failed" | tee -a "$OUT/log_$TAG.txt"
  cat "$OUT/geometry_$TAG.json"; echo
fi
if [ -n "${SNAP:-}" ]; then
  python3 scripts/time_to_quality.py eval $R "$OUT/ttq_$TAG.json" --label "$TAG" --chunk 400000 $( [ "${GEOMETRY:-0}" = 1 ] && echo --geometry materials ) >> "$OUT/log_$TAG.txt" 2>&1 || echo "ttq failed" | tee -a "$OUT/log_$TAG.txt"
  tail -8 "$OUT/log_$TAG.txt"
fi
if [ "${SPHERE:-0}" = 1 ]; then
  python3 scripts/surface_renderers.py $R --json "$OUT/renderers_$TAG.json" >> "$OUT/log_$TAG.txt" 2>&1 || echo "renderers failed" | tee -a "$OUT/log_$TAG.txt"
  cat "$OUT/renderers_$TAG.json"; echo
fi
cp $R/history.json "$OUT/history_$TAG.json"; cp $R/config.json "$OUT/config_$TAG.json"
cp ${R}_eval/metrics.json "$OUT/metrics_$TAG.json" 2>/dev/null
ls ${R}_eval | head -3 >> "$OUT/log_$TAG.txt"
for f in $(ls ${R}_eval/*.png 2>/dev/null | head -2); do cp "$f" "$OUT/${TAG}_$(basename "$f")"; done
python3 - "$TAG" "$SECS" <<'PY' | tee "$OUT/surface_$TAG.md"
import json, statistics, sys
tag, secs = sys.argv[1], float(sys.argv[2])
h = json.load(open(f"/tmp/sdf_{tag}/history.json"))
m = json.load(open(f"/tmp/sdf_{tag}_eval/metrics.json"))
s = h["seconds"]
step = statistics.median(1e3 * (b - a) for a, b in zip(s[300:], s[301:])) if len(s) > 302 else float("nan")
beta = h.get("beta", [None])[-1]
print(f"| run | steps in {secs:g} s | median step ms | final beta | val images | val PSNR | val SSIM | median frame ms |")
print("|---|---|---|---|---|---|---|---|")
print(f"| {tag} | {h['step'][-1]} | {step:.2f} | {beta} | {m['n_images']} | {m['psnr']:.3f} | {m['ssim']:.4f} | {m['render_ms_median']:.1f} |")
for k in ("psnr", "samples_per_ray", "batch", "beta"):
    if k in h and h[k]:
        v = h[k]; print(k, [round(float(v[i]), 4) for i in range(0, len(v), max(1, len(v) // 8))])
PY
