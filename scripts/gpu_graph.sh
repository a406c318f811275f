#!/usr/bin/env bash
# Issue 33 on the lent GPU: the training step with static shapes captured in CUDA graphs
# (--cuda-graph auto) against the eager step (--cuda-graph off), lego 400x400, hash field +
# occupancy grid, 2^19 samples a step. Run from the repository root there, Warp on PYTHONPATH.
#   STAGES="tests profile speed ttq" DATA=/root/stage/lego bash scripts/gpu_graph.sh
# Writes $OUT/*.json, *.txt; prints a short summary last.
set -u
OUT=${OUT:-/tmp/gpu_graph_out}; mkdir -p "$OUT"
DATA=${DATA:-/root/stage/lego}
SECS=${SECS:-30}
common="train nerf --data $DATA --field hash --device cuda --tf32 --batch 4096 --target-samples 524288"
sdf="train volsdf --data $DATA --field hash_sdf --device cuda --tf32 --batch 4096 --target-samples 262144"
export PYTHONUNBUFFERED=1
for stage in ${STAGES:-tests profile speed}; do
  echo "=== $stage $(date -u +%H:%M:%S)"
  case $stage in
  tests)
    python3 -m pytest tests/test_graph_step.py tests/test_sync_budget.py tests/test_encoding.py \
      -q -x -k cuda \
      > "$OUT/tests.txt" 2>&1; tail -15 "$OUT/tests.txt" ;;
  bench)
    python3 -m warpnerf.cli bench encoding --device cuda --json "$OUT/bench_encoding.json" \
      > "$OUT/bench_encoding.txt" 2>&1; tail -8 "$OUT/bench_encoding.txt" ;;
  base)  # today's main before this issue (.gpu/base: its warpnerf/ with kernels/ inside), same run
    rm -rf /tmp/sp_base
    (B=$PWD/.gpu/base; cd .gpu/base && PYTHONPATH=${PYTHONPATH:-}:$B python3 -m warpnerf.cli \
      $common --iters 1000000 --max-seconds $SECS --val-images 0 --quiet --no-tensorboard \
      --out /tmp/sp_base > "$OUT/speed_base.txt" 2>&1 && PYTHONPATH=${PYTHONPATH:-}:$B \
      python3 -m warpnerf.cli eval /tmp/sp_base --split val --chunk 400000 \
      --out /tmp/sp_base_eval > /dev/null 2>> "$OUT/speed_base.txt") || tail -5 "$OUT/speed_base.txt" ;;
  sdfprofile)  # the surface field's step (hash_sdf on lego, 2^18 samples)
    for g in ${GRAPHS:-off auto}; do
      python3 scripts/profile_train_step.py --warm 600 --steps 30 --cprofile 0 \
        --json "$OUT/prof_sdf_$g.json" -- $sdf --cuda-graph $g > "$OUT/prof_sdf_$g.txt" 2>&1 \
        || tail -20 "$OUT/prof_sdf_$g.txt"
      python3 -c "
import json; r = json.load(open('$OUT/prof_sdf_$g.json'))
print('hash_sdf $g', {k: r.get(k) for k in ('step_ms_median', 'device_busy_ms_per_step', 'host_syncs_per_step', 'launches_issued_per_step', 'rays_per_step', 'graphs_captured')})
print(list(r['top_device_ops_ms_per_step'].items())[:6])"
    done ;;
  sdfspeed)  # hash_sdf trained SECS seconds each way, then every val image
    for g in ${GRAPHS:-off auto}; do
      rm -rf /tmp/sdf_$g
      python3 -m warpnerf.cli $sdf --cuda-graph $g --iters 1000000 --max-seconds $SECS \
        --val-images 0 --quiet --no-tensorboard --out /tmp/sdf_$g > "$OUT/sdf_$g.txt" 2>&1 \
        || tail -20 "$OUT/sdf_$g.txt"
      python3 -m warpnerf.cli eval /tmp/sdf_$g --split val --chunk 400000 \
        --out /tmp/sdf_${g}_eval > /dev/null 2>> "$OUT/sdf_$g.txt" || tail -5 "$OUT/sdf_$g.txt"
    done
    python3 - "$OUT" <<'PY'
import json, statistics, sys
rows = {}
for g in ("off", "auto"):
    try:
        h = json.load(open(f"/tmp/sdf_{g}/history.json"))
        m = json.load(open(f"/tmp/sdf_{g}_eval/metrics.json"))
    except OSError:
        continue
    s, n = h["seconds"], len(h["seconds"])
    half = [1e3 * (b - a) for a, b in zip(s[n // 2:], s[n // 2 + 1:])]
    rows[g] = dict(steps=h["step"][-1], seconds=s[-1], median_step_ms_second_half=statistics.median(half),
                   rays_last=h["batch"][-1], dropped_total=sum(h.get("dropped_samples", [])),
                   val_psnr=m.get("psnr"), val_ssim=m.get("ssim"), frame_ms_median=m.get("render_ms_median"),
                   n_images=m.get("n_images"), beta_last=h["beta"][-1])
json.dump(rows, open(f"{sys.argv[1]}/sdf_speed.json", "w"), indent=1)
print(json.dumps(rows, indent=1))
PY
    ;;
  alltests)
    python3 -m pytest tests -q -k cuda -p no:cacheprovider > "$OUT/alltests.txt" 2>&1
    tail -15 "$OUT/alltests.txt" ;;
  profile)
    for g in ${GRAPHS:-off auto}; do
      python3 scripts/profile_train_step.py --warm ${WARM:-1500} --steps 50 --cprofile 0 \
        --json "$OUT/prof_$g.json" -- $common --cuda-graph $g > "$OUT/prof_$g.txt" 2>&1 \
        || tail -20 "$OUT/prof_$g.txt"
    done ;;
  speed)
    for g in ${GRAPHS:-off auto}; do
      rm -rf /tmp/sp_$g
      python3 -m warpnerf.cli $common --cuda-graph $g --iters 1000000 --max-seconds $SECS \
        --val-images 0 --quiet --no-tensorboard --out /tmp/sp_$g > "$OUT/speed_$g.txt" 2>&1 \
        || tail -20 "$OUT/speed_$g.txt"
      python3 -m warpnerf.cli eval /tmp/sp_$g --split val --chunk 400000 --out /tmp/sp_${g}_eval \
        > /dev/null 2>> "$OUT/speed_$g.txt" || tail -5 "$OUT/speed_$g.txt"
    done
    python3 - "$OUT" <<'PY'
import json, statistics, sys
out = sys.argv[1]
rows = {}
for g in ("base", "off", "auto"):
    try:
        h = json.load(open(f"/tmp/sp_{g}/history.json"))
    except OSError:
        continue
    s, n = h["seconds"], len(h["seconds"])
    half = [1e3 * (b - a) for a, b in zip(s[n // 2:], s[n // 2 + 1:])]
    m = {}
    try:
        m = json.load(open(f"/tmp/sp_{g}_eval/metrics.json"))
    except OSError:
        pass
    rows[g] = dict(steps=h["step"][-1], seconds=s[-1], first_step_s=s[0],
                   median_step_ms_second_half=statistics.median(half),
                   steps_per_s_second_half=1e3 / statistics.median(half),
                   rays_last=h["batch"][-1], samples_per_ray_last=h["samples_per_ray"][-1],
                   dropped_total=sum(h.get("dropped_samples", [])),
                   steps_with_drops=sum(1 for d in h.get("dropped_samples", []) if d),
                   val_psnr=m.get("psnr"), val_ssim=m.get("ssim"),
                   frame_ms_median=m.get("render_ms_median"), n_images=m.get("n_images"))
json.dump(rows, open(f"{out}/speed.json", "w"), indent=1)
print(json.dumps(rows, indent=1))
PY
    ;;
  ttq)
    rm -rf /tmp/ttq
    python3 scripts/time_to_quality.py run /tmp/ttq --budgets ${BUDGETS:-15,60} --chunk 400000 \
      -- $common --val-images 0 --quiet --no-tensorboard > "$OUT/ttq.txt" 2>&1
    tail -12 "$OUT/ttq.txt"; cp /tmp/ttq/ttq.json "$OUT/ttq.json" 2>/dev/null
    cp /tmp/ttq/run/history.json "$OUT/ttq_history.json" 2>/dev/null ;;
  esac
done
echo "=== summary $(date -u +%H:%M:%S)"
for g in off auto; do
  [ -f "$OUT/prof_$g.json" ] && python3 -c "
import json; r = json.load(open('$OUT/prof_$g.json'))
print('$g', {k: r.get(k) for k in ('step_ms_median', 'device_busy_ms_per_step', 'host_syncs_per_step', 'kernel_launches_per_step', 'launches_issued_per_step', 'rays_per_step', 'samples_per_ray', 'dropped_samples_last_50', 'graphs_captured')})"
done
