#!/usr/bin/env bash
# The training recipe's ablation (issue 44) on the lent GPU: one run per row, each trained for the
# same wall-clock budget with the base flags plus the row's own, then evaluated on every val image.
# A row whose step fell back from the CUDA graph to the eager step is marked (it must not).
# Usage (from the repository root, on the device):
#   DATA=.gpu/lego SECS=60 ROWS='base|;bg|--random-background on;ema|--ema 0.95' \
#     bash scripts/gpu_recipe_ablation.sh        (appends to $OUT/ablation.md, logs to $OUT/log.txt)
# BASE: the flags every row shares (default: issue 44's reference, the hash field on CUDA).
set -u
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
DATA=${DATA:-.gpu/lego}
SECS=${SECS:-60}
TAG=${TAG:-$(basename "$DATA")}
BASE=${BASE:---field hash --device cuda --tf32 --batch 4096 --target-samples 524288}
IFS=';' read -ra rows <<< "${ROWS:-base|}"
[ -f "$OUT/ablation.md" ] || {
  echo "| data | row | flags | seconds | steps | median step ms | val images | val PSNR | val SSIM | median frame ms | step |"
  echo "|---|---|---|---|---|---|---|---|---|---|---|"
} > "$OUT/ablation.md"
for row in "${rows[@]}"; do
  name=${row%%|*}
  flags=${row#*|}
  run=/tmp/abl_${TAG}_$name
  rm -rf "$run" "${run}_eval"
  # shellcheck disable=SC2086
  python3 -m warpnerf.cli train nerf --data "$DATA" $BASE --iters 1000000 --max-seconds "$SECS" \
    --val-images 0 --quiet --no-tensorboard $flags --out "$run" > "$run.log" 2>&1 \
    || echo "train $TAG/$name failed" | tee -a "$OUT/log.txt"
  python3 -m warpnerf.cli eval "$run" --split val --chunk 400000 --out "${run}_eval" \
    >> "$run.log" 2>&1 || echo "eval $TAG/$name failed" | tee -a "$OUT/log.txt"
  { echo "== $TAG/$name: $flags"; tail -n 15 "$run.log"; } >> "$OUT/log.txt"
  python3 - "$run" "$TAG" "$name" "$flags" "$SECS" <<'PY' | tee -a "$OUT/ablation.md"
import json, statistics, sys
run, tag, name, flags, secs = sys.argv[1:]
try:
    h = json.load(open(f"{run}/history.json"))
    m = json.load(open(f"{run}_eval/metrics.json"))
except OSError as e:
    print(f"| {tag} | {name} | `{flags}` | {secs} | failed: {e} | | | | | | |")
    raise SystemExit
s = h["seconds"]
step = statistics.median(1e3 * (b - a) for a, b in zip(s[300:], s[301:])) if len(s) > 310 else float("nan")
eager = "eager fallback" if "capture failed" in open(f"{run}.log").read() else "graph"
print(f"| {tag} | {name} | `{flags}` | {secs} | {h['step'][-1]} | {step:.2f} | {m['n_images']} | "
      f"{m['psnr']:.3f} | {m['ssim']:.4f} | {m['render_ms_median']:.1f} | {eager} |")
PY
done
