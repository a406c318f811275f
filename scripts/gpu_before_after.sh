#!/usr/bin/env bash
# Time to quality before/after a change, on the lent GPU: lego 400x400, hash field + occupancy
# grid, trained for the same wall-clock budget by this tree ("new") and a base tree ("base"),
# each then evaluated on every val image by its own code. Base tree as in gpu_overhead.sh
# (.gpu/base = the base commit's warpnerf/ with kernels/ copied to warpnerf/kernels).
# Usage: DATA=.gpu/lego SECS=120 bash scripts/gpu_before_after.sh   (writes $OUT/before_after.md)
source "$(dirname "$0")/_gpu_ab.sh"  # OUT, DATA, run_version
SECS=${SECS:-120}
args="train nerf --data $DATA --field hash --device cuda --tf32 --batch 4096 --target-samples 262144 --iters 100000 --max-seconds $SECS --val-images 0 --quiet --no-tensorboard"
for v in ${ORDER:-base new}; do
  rm -rf /tmp/ba_$v
  run_version $v $args --out /tmp/ba_$v > "$OUT/train_$v.json" 2>> "$OUT/log.txt" || echo "train $v failed" | tee -a "$OUT/log.txt"
  run_version $v eval /tmp/ba_$v --split val --chunk 400000 --out /tmp/ba_${v}_eval > /dev/null 2>> "$OUT/log.txt" || echo "eval $v failed" | tee -a "$OUT/log.txt"
done
python3 - "$SECS" <<'PY' | tee "$OUT/before_after.md"
import json, statistics, sys
secs = float(sys.argv[1])
print(f"| version | steps in {secs:g} s | median step ms | val images | val PSNR | val SSIM | median frame ms |")
print("|---|---|---|---|---|---|---|")
res = {}
for v in ("base", "new"):
    h = json.load(open(f"/tmp/ba_{v}/history.json"))
    m = json.load(open(f"/tmp/ba_{v}_eval/metrics.json"))
    s = h["seconds"]
    step = statistics.median(1e3 * (b - a) for a, b in zip(s[300:], s[301:]))
    res[v] = m["psnr"]
    print(f"| {v} | {h['step'][-1]} | {step:.2f} | {m['n_images']} | {m['psnr']:.3f} | {m['ssim']:.4f} | {m['render_ms_median']:.1f} |")
print(f"new - base: {res['new'] - res['base']:+.3f} dB")
PY
