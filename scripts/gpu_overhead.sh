#!/usr/bin/env bash
# A/B of the hot paths on the lent GPU: this tree against a base tree, in one session on one machine.
# Base tree: .gpu/base = the base commit's warpnerf/ with kernels/ copied to warpnerf/kernels
#   (git worktree add /tmp/b COMMIT; cp -r /tmp/b/warpnerf .gpu/base/; cp -r /tmp/b/kernels .gpu/base/warpnerf/kernels)
# Data: lego under .gpu/lego (carried). Expects Warp importable and this tree installed. Writes $OUT.
# Measures: training step time (hash field + occupancy grid, ~262k samples a step, median over
# steps 300..ITERS from history.json), REPS runs per version interleaved; the median frame time of
# `eval` (20 val images) of one run rendered by each version. The order within a repetition
# alternates (ORDER=alt, the default: the second run of a pair measured a few % slower on the
# H100); ORDER="base new" or "new base" fixes it.
source "$(dirname "$0")/_gpu_ab.sh"  # OUT, DATA, run_version
ITERS=${ITERS:-1000}
args="train nerf --data $DATA --field hash --batch 4096 --target-samples 262144 --tf32 --iters $ITERS --val-images 0 --device cuda --quiet"
order() {  # the versions' order in repetition $1: ORDER="base new", "new base" or "alt" (default)
  case ${ORDER:-alt} in alt) if [ $(($1 % 2)) = 1 ]; then echo base new; else echo new base; fi ;; *) echo $ORDER ;; esac
}
(B=$PWD/.gpu/base; cd .gpu/base && PYTHONPATH=${PYTHONPATH:-}:$B python3 -c "import warpnerf; print('base code:', warpnerf.__file__)")
python3 -c "import warpnerf; print('new code:', warpnerf.__file__)"
for r in $(seq 1 ${REPS:-2}); do
  for v in $(order $r); do
    rm -rf /tmp/ab_${v}_$r
    run_version $v $args --out /tmp/ab_${v}_$r > /dev/null 2>> "$OUT/log.txt" || echo "train $v $r failed" | tee -a "$OUT/log.txt"
  done
done
for r in $(seq 1 ${EVAL_REPS:-4}); do  # interleaved: the host's speed drifts between runs
  for v in $(order $r); do
    rm -rf /tmp/ev_${v}_$r
    run_version $v eval /tmp/ab_new_1 --max-images 20 --out /tmp/ev_${v}_$r >> "$OUT/log.txt" 2>&1
  done
done
python3 - "$ITERS" "${REPS:-2}" "${EVAL_REPS:-4}" <<'PY' | tee "$OUT/overhead.md"
import json, os, statistics, sys
iters, reps, ereps = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
def step_ms(run):
    """median step ms over steps 300..iters, and the median per 262144 kept samples"""
    h = json.load(open(f"{run}/history.json"))
    s, spr, b = h["seconds"], h["samples_per_ray"], h["batch"]
    d = [1e3 * (s[i] - s[i - 1]) for i in range(300, iters)]
    per = [d[j] * 262144 / max(spr[i] * b[i], 1) for j, i in enumerate(range(300, iters))]
    return statistics.median(d), statistics.median(per), statistics.mean(spr[300:])
def render_ms(ev):
    return json.load(open(f"{ev}/metrics.json"))["render_ms_median"]
print(f"| version | run | median step ms (steps 300..{iters}) | ms per 262144 samples | samples/ray |")
print("|---|---|---|---|---|")
rows = {}
for r in range(1, reps + 1):
    for v in ("base", "new"):
        ms, per, spr = step_ms(f"/tmp/ab_{v}_{r}")
        rows.setdefault(v, []).append(ms)
        rows.setdefault(v + "_per", []).append(per)
        print(f"| {v} | {r} | {ms:.3f} | {per:.3f} | {spr:.1f} |")
for v in ("base", "new"):
    rm = [render_ms(f"/tmp/ev_{v}_{r}") for r in range(1, ereps + 1)]
    rows[v + "_render"] = rm
    shown = " / ".join(f"{x:.1f}" for x in rm)
    print(f"| {v} | eval 20 val images, median frame ms per run: {shown} | | | |")
m = {k: statistics.median(v) for k, v in rows.items()}
for what, k in (("step", ""), ("step per sample", "_per"), ("frame", "_render")):
    q = m["new" + k] / m["base" + k]
    pairs = [a / b for a, b in zip(rows["new" + k], rows["base" + k])]
    sd = statistics.stdev(pairs) / len(pairs) ** 0.5 if len(pairs) > 1 else float("nan")
    print(f"{what}: new / base = {q:.4f} ({100 * (q - 1):+.2f} %) (medians over runs); "
          f"paired ratios {' '.join(f'{x:.3f}' for x in pairs)}, mean {statistics.mean(pairs):.4f} "
          f"+- {sd:.4f} (standard error)")
json.dump(rows, open(os.environ.get("OUT", "/tmp/out") + "/overhead.json", "w"))
PY
