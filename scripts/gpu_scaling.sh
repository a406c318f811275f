#!/usr/bin/env bash
# Issue 21 on a two-GPU device machine (nvidia-h200-x2 / nvidia-h100-x2), one call per STAGE:
#   STAGE=one   the machine (GPUs, links), Warp's kernels compiled once (a short lego run, a short
#               beer run with its contraction, one scoring), where a step's time goes on one GPU
#               and on two (scripts/dp_profile.py), then lego: 1 GPU against 2 at the same total
#               batch and at twice the batch (scripts/dp_scaling.py)
#   STAGE=two   beer the same way, and lego 1 GPU at the doubled batch
# Data under $DATA_ROOT (lego/ and beer/); results under $OUT (one archive, results.tar.gz, and
# the summaries). Usage on the device, Warp on PYTHONPATH and the package installed:
#   STAGE=one DATA_ROOT=/root/data bash scripts/gpu_scaling.sh
set -u
OUT=${OUT:-/tmp/out}
D=${DATA_ROOT:-/root/data}
R=/tmp/scaling
mkdir -p "$OUT" "$R"
export PYTHONUNBUFFERED=1 NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1
COMMON="--field hash --device cuda --tf32 --batch 4096"
# (the device copy's git metadata may not be this tree's: pass WARPNERF_COMMIT=<the tree's commit>)
echo "commit ${WARPNERF_COMMIT:-$(git log -1 --format=%H 2>/dev/null)}" | tee "$R/commit.txt"
export WARPNERF_COMMIT=${WARPNERF_COMMIT:-}
case "${STAGE:-one}" in
  one)
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$R/gpus.txt"
    nvidia-smi topo -m 2>&1 | tee -a "$R/gpus.txt"
    python3 -c 'import torch, warp; print(torch.__version__, torch.cuda.device_count(), warp.__version__, torch.cuda.nccl.version())' | tee -a "$R/gpus.txt"
    t0=$(date +%s)
    python3 -m warpnerf.cli train nerf --data "$D/lego" $COMMON --target-samples 262144 \
      --iters 40 --val-images 0 --quiet --no-tensorboard --out /tmp/warm_lego 2>&1 | tail -2
    python3 -m warpnerf.cli eval /tmp/warm_lego --split val --max-images 1 --out /tmp/warm_eval \
      2>&1 | tail -c 300
    python3 -m warpnerf.cli train nerf --data "$D/beer" $COMMON --target-samples 262144 \
      --iters 40 --val-images 0 --quiet --no-tensorboard --out /tmp/warm_beer 2>&1 | tail -2
    echo "warm-up (Warp compilation, cold cache): $(( $(date +%s) - t0 )) s" | tee "$R/warmup.txt"
    for n in 1 2; do
      timeout 150 python3 -m torch.distributed.run --standalone --nproc-per-node=$n \
        scripts/dp_profile.py --warm 200 --steps 100 --json "$R/profile_lego_${n}gpu.json" -- \
        train nerf --data "$D/lego" $COMMON --target-samples 262144 2>&1 | tail -22
    done
    python3 scripts/dp_scaling.py run "$R" --name lego --budgets 15,30,60 --chunk 400000 \
      --eval-parallel 2 --configs 1x262144,2x262144,2x524288 -- --data "$D/lego" $COMMON
    ;;
  two)
    python3 scripts/dp_scaling.py run "$R" --name beer --budgets 15,30,60 --chunk 131072 \
      --eval-parallel 2 --configs 1x262144,2x262144,2x524288 -- --data "$D/beer" $COMMON
    python3 scripts/dp_scaling.py run "$R" --name lego1 --budgets 15,30,60 --chunk 400000 \
      --eval-parallel 2 --configs 1x524288 -- --data "$D/lego" $COMMON
    ;;
  *) echo "STAGE must be one or two"; exit 2 ;;
esac
cp "$R"/scaling_*.json "$R"/scaling_*.png "$OUT/" 2>/dev/null
(cd "$R" && tar -czf "$OUT/results_${STAGE:-one}.tar.gz" --exclude='*.pt' --exclude='render_*' \
  --exclude='*.png' . 2>/dev/null)
ls -la "$OUT"
