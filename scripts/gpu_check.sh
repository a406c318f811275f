#!/usr/bin/env bash
# Runs on the lent GPU machine (see docs/design/kernels.md): CUDA variants of the tests, then the
# compositing benchmark. Expects Warp importable (PYTHONPATH) and the package installed; writes
# under $OUT.
set -u
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm,clocks.mem --format=csv | tee "$OUT/gpu.txt"
python3 -c "import torch, warp; print('torch', torch.__version__, 'warp', warp.__version__)" | tee -a "$OUT/gpu.txt"
git log -1 --format='commit %H' 2>/dev/null | tee -a "$OUT/gpu.txt"
python3 -m pytest tests -q -k "cuda" -p no:cacheprovider ${PYTEST_ARGS:-} 2>&1 | tail -25 | tee "$OUT/pytest_cuda.txt"
python3 -m warpnerf.cli bench composite --device cuda --json "$OUT/bench_cuda.json" 2>&1 | tee "$OUT/bench_cuda.md"
