#!/usr/bin/env bash
# A/B of the hot paths on the lent GPU: this tree against a base tree, in one session on one machine.
# Base tree: .gpu/base = the base commit's warpnerf/ with kernels/ copied to warpnerf/kernels
#   (git worktree add /tmp/b COMMIT; cp -r /tmp/b/warpnerf .gpu/base/; cp -r /tmp/b/kernels .gpu/base/warpnerf/kernels)
# Data: lego under .gpu/lego (carried). Expects Warp importable and this tree installed. Writes $OUT.
# Measures: training step time (hash field + occupancy grid, ~262k samples a step, median over
# steps 300..ITERS from history.json), twice per version interleaved; the median frame time of
# `eval` (20 val images) of one run rendered by each version.
set -u
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
DATA=$PWD/${DATA:-.gpu/lego}
ITERS=${ITERS:-1000}
args="train nerf --data $DATA --field hash --batch 4096 --target-samples 262144 --tf32 --iters $ITERS --val-images 0 --device cuda --quiet"
run_version() {  # version, argv...
  if [ "$1" = base ]; then shift; (cd .gpu/base && python3 -m warpnerf.cli "$@"); else shift; python3 -m warpnerf.cli "$@"; fi
}
(cd .gpu/base && python3 -c "import warpnerf; print('base code:', warpnerf.__file__)")
python3 -c "import warpnerf; print('new code:', warpnerf.__file__)"
for r in 1 2; do
  for v in base new; do
    rm -rf /tmp/ab_${v}_$r
    run_version $v $args --out /tmp/ab_${v}_$r > /dev/null 2>> "$OUT/log.txt" || echo "train $v $r failed" | tee -a "$OUT/log.txt"
  done
done
for v in base new; do
  for r in 1 2; do
    rm -rf /tmp/ev_${v}_$r
    run_version $v eval /tmp/ab_new_1 --max-images 20 --out /tmp/ev_${v}_$r >> "$OUT/log.txt" 2>&1
  done
done
python3 - "$ITERS" <<'PY' | tee "$OUT/overhead.md"
import json, statistics, sys
iters = int(sys.argv[1])
def step_ms(run):
    h = json.load(open(f"{run}/history.json"))
    s = h["seconds"]
    d = [1e3 * (b - a) for a, b in zip(s[299:], s[300:iters])]
    return statistics.median(d), len(d), statistics.mean(h.get("samples_per_ray", [0])[300:])
def render_ms(ev):
    return json.load(open(f"{ev}/metrics.json"))["render_ms_median"]
print("| version | run | median step ms (steps 300..%d) | samples/ray |" % iters)
print("|---|---|---|---|")
rows = {}
for v in ("base", "new"):
    for r in (1, 2):
        ms, n, spr = step_ms(f"/tmp/ab_{v}_{r}")
        rows.setdefault(v, []).append(ms)
        print(f"| {v} | {r} | {ms:.3f} | {spr:.1f} |")
for v in ("base", "new"):
    rm = [render_ms(f"/tmp/ev_{v}_{r}") for r in (1, 2)]
    rows[v + "_render"] = rm
    print(f"| {v} | eval 20 val images | median frame {rm[0]:.2f} / {rm[1]:.2f} ms | |")
b, n = statistics.mean(rows["base"]), statistics.mean(rows["new"])
br, nr = statistics.mean(rows["base_render"]), statistics.mean(rows["new_render"])
print(f"\nstep: new / base = {n / b:.4f} ({100 * (n / b - 1):+.2f} %); "
      f"frame: new / base = {nr / br:.4f} ({100 * (nr / br - 1):+.2f} %)")
json.dump(rows, open(__import__("os").environ.get("OUT", "/tmp/out") + "/overhead.json", "w"))
PY
