#!/usr/bin/env python3
"""The one runner for the lent GPU machine: every phase it can run is a line of PHASES below (a
name, what it measures, the shell commands it runs), so the figures' commands live in one place.

    python3 scripts/gpu.py PHASE [PHASE ...]   run the phases in order (one device call each
                                               should stay under its 10-minute limit)
    python3 scripts/gpu.py --list              the phases, one line each, with the old harness each replaces
    python3 scripts/gpu.py --print PHASE       the bash script a phase runs, without running it

Run it from the repository root on the device (Warp importable, the package installed). Settings
come from environment variables, as in the harnesses this replaces: OUT (results, default
/tmp/out), DATA (a scene folder), SECS, ITERS, BUDGETS, EXTRA, ... (each phase's commands show
its defaults, `--print`). A/B phases (overhead, before_after, graph_base) run a base tree from
.gpu/base: the base commit's warpnerf/ with kernels/ copied to warpnerf/kernels
(git worktree add /tmp/b COMMIT; cp -r /tmp/b/warpnerf .gpu/base/; cp -r /tmp/b/kernels
.gpu/base/warpnerf/kernels). The tables the phases print are made by the SUMMARIES functions
below (``--summary NAME ARGS``, called by the phases themselves).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve()

# What every phase starts with: OUT, unbuffered output, and run_version (this tree, "new", or the
# base tree in .gpu/base, "base"), $GPU to call this file's summaries.
PRELUDE = f"""set -u
OUT=${{OUT:-/tmp/out}}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
GPU="python3 {HERE}"
run_version() {{  # version, argv...: python3 -m warpnerf.cli argv with this tree or the base tree
  if [ "$1" = base ]; then shift; (B=$PWD/.gpu/base; cd .gpu/base && PYTHONPATH=${{PYTHONPATH:-}}:$B python3 -m warpnerf.cli "$@"); else shift; python3 -m warpnerf.cli "$@"; fi
}}
gpu_line() {{ nvidia-smi --query-gpu=name,driver_version --format=csv,noheader >> "$OUT/log.txt"; }}
"""

# ---------------------------------------------------------------------------------------------
# The phases: name -> (old harness it replaces, what it measures, bash commands).
# ---------------------------------------------------------------------------------------------

_NERF = (
    "--device cuda --tf32 --layers 8 --width 256 --pos-freqs 10 --dir-freqs 4 --batch 4096 --quiet"
)
_VOLSDF = ('vs="--device cuda --tf32 --batch ${BATCH:-1024} --samples 64 --fine-samples 64 --quiet '
           '--iters ${ITERS:-4000} --max-seconds ${SECS:-150} --val-every 1000 --val-images 2"\n'
           'DATA=${DATA:-.devdata}\n')  # fmt: skip
_GRAPH = """DATA=${DATA:-/root/stage/lego}
SECS=${SECS:-30}
common="train nerf --data $DATA --field hash --device cuda --tf32 --batch 4096 --target-samples 524288"
sdf="train volsdf --data $DATA --field hash_sdf --device cuda --tf32 --batch 4096 --target-samples 262144"
"""
_AB = "DATA=$PWD/${DATA:-.gpu/lego}\n"  # (the A/B phases' data, relative to the repository root)
_SCALING = """D=${DATA_ROOT:-/root/data}
R=/tmp/scaling
mkdir -p "$R"
export NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1
COMMON="--field hash --device cuda --tf32 --batch 4096"
# (the device copy's git metadata may not be this tree's: pass WARPNERF_COMMIT=<the tree's commit>)
echo "commit ${WARPNERF_COMMIT:-$(git log -1 --format=%H 2>/dev/null)}" | tee "$R/commit.txt"
export WARPNERF_COMMIT=${WARPNERF_COMMIT:-}
"""
_SCALING_END = """cp "$R"/scaling_*.json "$R"/scaling_*.png "$OUT/" 2>/dev/null
(cd "$R" && tar -czf "$OUT/results_$STAGE.tar.gz" --exclude='*.pt' --exclude='render_*' \\
  --exclude='*.png' . 2>/dev/null)
ls -la "$OUT"
"""


def _nerf_lego(name: str) -> str:
    """gpu_nerf.sh lego_seed|lego_full|lego_hash: an MLP or hash NeRF on lego, then eval."""
    if name == "lego_seed":
        common, extra = _NERF, "--downscale 3 --samples 128"
    elif name == "lego_full":
        common, extra = _NERF, "--samples 64 --coarse-fine --fine-samples 128"
    else:
        common = "--device cuda --tf32 --field hash --grid-res 0 --batch ${BATCH:-4096} --quiet"
        extra = "--samples ${COARSE:-64} --coarse-fine --fine-samples ${FINE:-128}"
    return f"""python3 -m warpnerf.cli train nerf --data .devdata/lego --out /tmp/{name} {common} {extra} \\
  --iters ${{ITERS:-30000}} --max-seconds ${{SECS:-420}} --val-every 1000 --val-images 2 2>&1 | tail -6 | tee -a "$OUT/log.txt"
python3 -m warpnerf.cli eval /tmp/{name} --split val --max-images ${{EVAL_IMAGES:-25}} 2>&1 | tail -1 | tee -a "$OUT/log.txt"
cp /tmp/{name}/history.json "$OUT/{name}_history.json"
cp /tmp/{name}/eval_val/metrics.json "$OUT/{name}_metrics.json"
cp /tmp/{name}/eval_val/val_000.png "$OUT/{name}_val_000.png"
cp /tmp/{name}/config.json "$OUT/{name}_config.json"
gpu_line
"""


def _lego_grid(name: str) -> str:
    """gpu_nerf.sh lego_grid|lego_grid_more: hash field + grid (or resume it), then eval."""
    if name == "lego_grid":
        train = """python3 -m warpnerf.cli train nerf --data ${DATA:-.devdata/lego} --out $run --device cuda \\
  --tf32 --field hash --batch 4096 --target-samples ${TARGET:-262144} ${EXTRA:-} \\
  --iters ${ITERS:-20000} --max-seconds ${SECS:-120} --val-every 2000 --val-images 2 --quiet \\
  2>&1 | tail -4 | tee -a "$OUT/log.txt\""""
    else:
        train = """python3 -m warpnerf.cli train nerf --out $run --resume --iters ${ITERS:-20000} \\
  --max-seconds ${SECS:-180} --quiet 2>&1 | tail -3 | tee -a "$OUT/log.txt\""""
    return f"""run=/tmp/lego_grid
{train}
python3 -m warpnerf.cli eval $run --split val --chunk 400000 --max-images ${{EVAL_IMAGES:-25}} ${{EVAL_EXTRA:-}} \\
  2>&1 | tail -1 | tee -a "$OUT/log.txt"
cp $run/history.json "$OUT/{name}_history.json"
cp $run/eval_val/metrics.json "$OUT/{name}_metrics.json"
cp $run/eval_val/val_000.png "$OUT/{name}_val_000.png"
cp $run/config.json "$OUT/{name}_config.json"
gpu_line
"""


def _graph_ab(kind: str, stage: str) -> str:
    """gpu_graph.sh speed|sdfspeed: trained SECS each way (GRAPHS: --cuda-graph values), scored."""
    cmd, run = ("$common", "sp") if kind == "nerf" else ("$sdf", "sdf")
    return (
        _GRAPH
        + f"""for g in ${{GRAPHS:-off auto}}; do
  rm -rf /tmp/{run}_$g
  python3 -m warpnerf.cli {cmd} --cuda-graph $g --iters 1000000 --max-seconds $SECS \\
    --val-images 0 --quiet --no-tensorboard --out /tmp/{run}_$g > "$OUT/{run}_$g.txt" 2>&1 \\
    || tail -20 "$OUT/{run}_$g.txt"
  python3 -m warpnerf.cli eval /tmp/{run}_$g --split val --chunk 400000 --out /tmp/{run}_${{g}}_eval \\
    > /dev/null 2>> "$OUT/{run}_$g.txt" || tail -5 "$OUT/{run}_$g.txt"
done
$GPU --summary {stage} "$OUT"
"""
    )


def _graph_profile(kind: str) -> str:
    """gpu_graph.sh profile|sdfprofile: the step profiled each way (GRAPHS)."""
    if kind == "nerf":
        return (
            _GRAPH
            + """for g in ${GRAPHS:-off auto}; do
  python3 scripts/profile_train_step.py --warm ${WARM:-1500} --steps 50 --cprofile 0 \\
    --json "$OUT/prof_$g.json" -- $common --cuda-graph $g > "$OUT/prof_$g.txt" 2>&1 \\
    || tail -20 "$OUT/prof_$g.txt"
done
"""
        )
    return (
        _GRAPH
        + """for g in ${GRAPHS:-off auto}; do
  python3 scripts/profile_train_step.py --warm 600 --steps 30 --cprofile 0 \\
    --json "$OUT/prof_sdf_$g.json" -- $sdf --cuda-graph $g > "$OUT/prof_sdf_$g.txt" 2>&1 \\
    || tail -20 "$OUT/prof_sdf_$g.txt"
  $GPU --summary graph_profile "$OUT/prof_sdf_$g.json" "hash_sdf $g"
done
"""
    )


def _row_runs(table, prefix, *, data, secs, rows, header, train, then, settings="") -> str:
    """A phase that trains one NeRF per row of ROWS ('name|flags;...', default ``rows``) and
    appends a line per row to $OUT/TABLE.md (``header`` its first line, written once). DATA
    (default ``data``), SECS (default ``secs``) and TAG (DATA's folder name) are set, then
    ``settings`` (bash: more of them). Each row trains on DATA with ``train`` and the row's flags
    for SECS into /tmp/PREFIX_TAG_NAME (log in ``$run.log``), then runs ``then`` (bash, with $run,
    $name and $flags set), which scores the run and prints the row's line."""
    rule = "|" + "---|" * header.count(" | ") + "---|"
    return f"""
DATA=${{DATA:-{data}}}
SECS=${{SECS:-{secs}}}
TAG=${{TAG:-$(basename "$DATA")}}
{settings}IFS=';' read -ra rows <<< "${{ROWS:-{rows}}}"
[ -f "$OUT/{table}.md" ] || {{
  echo "{header}"
  echo "{rule}"
}} > "$OUT/{table}.md"
for row in "${{rows[@]}}"; do
  name=${{row%%|*}}
  flags=${{row#*|}}
  run=/tmp/{prefix}_${{TAG}}_$name
  rm -rf "$run" "${{run}}_eval"
  # shellcheck disable=SC2086
  python3 -m warpnerf.cli train nerf --data "$DATA" {train} --max-seconds "$SECS" \\
    --val-images 0 --quiet --no-tensorboard $flags --out "$run" > "$run.log" 2>&1 \\
    || echo "train $TAG/$name failed" | tee -a "$OUT/log.txt"
{then}done
"""


PHASES: dict[str, tuple[str, str, str]] = {
    # -- checks ---------------------------------------------------------------------------------
    "check": (
        "gpu_check.sh",
        "the CUDA tests and the compositing benchmark",
        """
nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm,clocks.mem --format=csv | tee "$OUT/gpu.txt"
python3 -c "import torch, warp; print('torch', torch.__version__, 'warp', warp.__version__)" | tee -a "$OUT/gpu.txt"
git log -1 --format='commit %H' 2>/dev/null | tee -a "$OUT/gpu.txt"
python3 -m pytest -o addopts=-ra tests -q -k "cuda" -p no:cacheprovider ${PYTEST_ARGS:-} 2>&1 | tail -25 | tee "$OUT/pytest_cuda.txt"
python3 -m warpnerf.cli bench composite --device cuda --json "$OUT/bench_cuda.json" 2>&1 | tee "$OUT/bench_cuda.md"
""",
    ),
    "cuda_tests": (
        "gpu_graph.sh alltests; gpu_next.sh STAGE=cuda (with launch)",
        "the CUDA variants of every test",
        """
git log -1 --format='commit %H' 2>/dev/null | tee "$OUT/commit.txt"
python3 -m pytest -o addopts=-ra tests -q -k cuda -p no:cacheprovider > "$OUT/alltests.txt" 2>&1
tail -25 "$OUT/alltests.txt"
""",
    ),
    "tests": (
        "gpu_next.sh STAGE=tests",
        "the CUDA variants of TESTS (default: test_distortion, test_contraction)",
        """
python3 -m pytest -o addopts=-ra ${TESTS:-tests/test_distortion.py tests/test_contraction.py} -q -k cuda \\
  -p no:cacheprovider 2>&1 | tail -8 | tee "$OUT/pytest_cuda_subset.txt"
""",
    ),
    "launch": (
        "gpu_next.sh STAGE=cuda (with cuda_tests)",
        "the host cost of a launch on CUDA (experiments/launch_overhead.py)",
        """
python3 experiments/launch_overhead.py --device cuda --repeats 6 --json "$OUT/launch_cuda.json" 2>&1 | tail -8
""",
    ),
    # -- speed and profiles ---------------------------------------------------------------------
    "step": (
        "gpu_next.sh STAGE=step",
        "the hash-field step on materials profiled "
        "(profile_train_step.py) and what watching costs (experiments/overheads/watch_overhead.py)",
        """
M=${DATA:-.gpu/materials}
python3 scripts/profile_train_step.py --warm 300 --steps 50 --json "$OUT/step_profile.json" -- \\
  train nerf --data "$M" --field hash --device cuda --tf32 --batch 4096 \\
  --target-samples 262144 --aabb 1.7 2>&1 | tail -30
python3 experiments/overheads/watch_overhead.py --repeats 3 --json "$OUT/watch_cuda.json" -- --data "$M" \\
  --field hash --device cuda --tf32 --batch 4096 --target-samples 262144 --aabb 1.7 \\
  --iters 1500 --val-images 0 ${WATCH_EXTRA:-} 2>&1 | tail -6
""",
    ),
    "syncs": (
        "gpu_next.sh STAGE=syncs",
        "where the training step synchronises (sync_sites.py)",
        """
python3 scripts/sync_sites.py --json "$OUT/sync_sites.json" -- train nerf --data \\
  ${DATA:-builtin} --field hash --device cuda --tf32 --batch 4096 \\
  --target-samples 262144 ${EXTRA:-} 2>&1 | tail -25
""",
    ),
    "graph_tests": (
        "gpu_graph.sh STAGES=tests",
        "the CUDA-graph step's tests on CUDA",
        _GRAPH
        + """
python3 -m pytest -o addopts=-ra tests/test_graph_step.py tests/test_sync_budget.py tests/test_encoding.py \\
  -q -x -k cuda > "$OUT/tests.txt" 2>&1; tail -15 "$OUT/tests.txt"
""",
    ),
    "graph_bench": (
        "gpu_graph.sh STAGES=bench",
        "the encoding benchmark",
        _GRAPH
        + """
python3 -m warpnerf.cli bench encoding --device cuda --json "$OUT/bench_encoding.json" \\
  > "$OUT/bench_encoding.txt" 2>&1; tail -8 "$OUT/bench_encoding.txt"
""",
    ),
    "graph_base": (
        "gpu_graph.sh STAGES=base",
        "the base tree (.gpu/base) trained SECS and scored, for graph_speed's table",
        _GRAPH
        + """
rm -rf /tmp/sp_base
(run_version base $common --iters 1000000 --max-seconds $SECS --val-images 0 --quiet --no-tensorboard \\
  --out /tmp/sp_base > "$OUT/speed_base.txt" 2>&1 && run_version base eval /tmp/sp_base --split val \\
  --chunk 400000 --out /tmp/sp_base_eval > /dev/null 2>> "$OUT/speed_base.txt") || tail -5 "$OUT/speed_base.txt"
""",
    ),
    "graph_profile": (
        "gpu_graph.sh STAGES=profile",
        "the NeRF step with and without CUDA graphs (profile_train_step.py; GRAPHS)",
        _graph_profile("nerf"),
    ),
    "graph_speed": (
        "gpu_graph.sh STAGES=speed",
        "NeRF trained SECS with and without CUDA graphs, every val image scored (speed.json)",
        _graph_ab("nerf", "graph_speed"),
    ),
    "graph_sdfprofile": (
        "gpu_graph.sh STAGES=sdfprofile",
        "the hash_sdf step with and without CUDA graphs",
        _graph_profile("sdf"),
    ),
    "graph_sdfspeed": (
        "gpu_graph.sh STAGES=sdfspeed",
        "hash_sdf trained SECS with and without CUDA graphs, scored (sdf_speed.json)",
        _graph_ab("sdf", "graph_sdfspeed"),
    ),
    "graph_ttq": (
        "gpu_graph.sh STAGES=ttq",
        "time to quality of the CUDA-graph step (BUDGETS, default 15,60)",
        _GRAPH
        + """
rm -rf /tmp/ttq
python3 scripts/time_to_quality.py run /tmp/ttq --budgets ${BUDGETS:-15,60} --chunk 400000 \\
  -- $common --val-images 0 --quiet --no-tensorboard > "$OUT/ttq.txt" 2>&1
tail -12 "$OUT/ttq.txt"; cp /tmp/ttq/ttq.json "$OUT/ttq.json" 2>/dev/null
cp /tmp/ttq/run/history.json "$OUT/ttq_history.json" 2>/dev/null
""",
    ),
    "graph_summary": (
        "gpu_graph.sh (its closing summary)",
        "the graph_profile JSONs, one line each",
        """
for g in off auto; do
  if [ -f "$OUT/prof_$g.json" ]; then $GPU --summary graph_profile "$OUT/prof_$g.json" "$g"; fi
done
""",
    ),
    "overhead": (
        "gpu_overhead.sh",
        "A/B of the hot paths against .gpu/base: step time (REPS "
        "interleaved runs of ITERS steps) and eval frame time (EVAL_REPS); ORDER",
        _AB
        + """
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
$GPU --summary overhead "$ITERS" "${REPS:-2}" "${EVAL_REPS:-4}" "$OUT" | tee "$OUT/overhead.md"
""",
    ),
    "before_after": (
        "gpu_before_after.sh",
        "time to quality of this tree against .gpu/base, SECS "
        "of training each (ORDER), every val image scored",
        _AB
        + """
SECS=${SECS:-120}
args="train nerf --data $DATA --field hash --device cuda --tf32 --batch 4096 --target-samples 262144 --iters 100000 --max-seconds $SECS --val-images 0 --quiet --no-tensorboard"
for v in ${ORDER:-base new}; do
  rm -rf /tmp/ba_$v
  run_version $v $args --out /tmp/ba_$v > "$OUT/train_$v.json" 2>> "$OUT/log.txt" || echo "train $v failed" | tee -a "$OUT/log.txt"
  run_version $v eval /tmp/ba_$v --split val --chunk 400000 --out /tmp/ba_${v}_eval > /dev/null 2>> "$OUT/log.txt" || echo "eval $v failed" | tee -a "$OUT/log.txt"
done
$GPU --summary before_after "$SECS" | tee "$OUT/before_after.md"
""",
    ),
    "scaling_one": (
        "gpu_scaling.sh STAGE=one",
        "two GPUs: the machine, warm-up, dp_profile.py on "
        "1 and 2 GPUs, lego 1 GPU against 2 (dp_scaling.py; DATA_ROOT)",
        _SCALING
        + """
STAGE=one
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$R/gpus.txt"
nvidia-smi topo -m 2>&1 | tee -a "$R/gpus.txt"
python3 -c 'import torch, warp; print(torch.__version__, torch.cuda.device_count(), warp.__version__, torch.cuda.nccl.version())' | tee -a "$R/gpus.txt"
t0=$(date +%s)
python3 -m warpnerf.cli train nerf --data "$D/lego" $COMMON --target-samples 262144 \\
  --iters 40 --val-images 0 --quiet --no-tensorboard --out /tmp/warm_lego 2>&1 | tail -2
python3 -m warpnerf.cli eval /tmp/warm_lego --split val --max-images 1 --out /tmp/warm_eval \\
  2>&1 | tail -c 300
python3 -m warpnerf.cli train nerf --data "$D/beer" $COMMON --target-samples 262144 \\
  --iters 40 --val-images 0 --quiet --no-tensorboard --out /tmp/warm_beer 2>&1 | tail -2
echo "warm-up (Warp compilation, cold cache): $(( $(date +%s) - t0 )) s" | tee "$R/warmup.txt"
for n in 1 2; do
  timeout 150 python3 -m torch.distributed.run --standalone --nproc-per-node=$n \\
    scripts/dp_profile.py --warm 200 --steps 100 --json "$R/profile_lego_${n}gpu.json" -- \\
    train nerf --data "$D/lego" $COMMON --target-samples 262144 2>&1 | tail -22
done
python3 scripts/dp_scaling.py run "$R" --name lego --budgets 15,30,60 --chunk 400000 \\
  --eval-parallel 2 --configs 1x262144,2x262144,2x524288 -- --data "$D/lego" $COMMON
"""
        + _SCALING_END,
    ),
    "scaling_two": (
        "gpu_scaling.sh STAGE=two",
        "two GPUs: beer 1 GPU against 2, lego 1 GPU at the doubled batch",
        _SCALING
        + """
STAGE=two
python3 scripts/dp_scaling.py run "$R" --name beer --budgets 15,30,60 --chunk 131072 \\
  --eval-parallel 2 --configs 1x262144,2x262144,2x524288 -- --data "$D/beer" $COMMON
python3 scripts/dp_scaling.py run "$R" --name lego1 --budgets 15,30,60 --chunk 400000 \\
  --eval-parallel 2 --configs 1x524288 -- --data "$D/lego" $COMMON
"""
        + _SCALING_END,
    ),
    # -- quality --------------------------------------------------------------------------------
    "ttq": (
        "gpu_next.sh STAGE=ttq",
        "time to quality on lego (BUDGETS, LABEL, EXTRA), plus eval frame time",
        """
git log -1 --format='commit %H' 2>/dev/null | tee "$OUT/commit.txt"
L=${DATA:-.gpu/lego}
python3 scripts/time_to_quality.py run /tmp/ttq_lego --budgets ${BUDGETS:-5,15,30,60,120,300} \\
  --label "warpnerf ${LABEL:-main}" --chunk 400000 -- train nerf --data "$L" --field hash \\
  --device cuda --tf32 --batch 4096 --target-samples 262144 --val-images 0 --quiet \\
  ${EXTRA:-} 2>&1 | tail -12 | tee "$OUT/ttq_lego.txt"
cp /tmp/ttq_lego/ttq.json "$OUT/ttq_lego.json"; cp /tmp/ttq_lego/ttq.png "$OUT/ttq_lego.png"
cp /tmp/ttq_lego/run/history.json "$OUT/ttq_lego_history.json"
python3 -m warpnerf.cli eval /tmp/ttq_lego/run --split val --chunk 400000 --max-images 20 \\
  --out /tmp/ttq_eval > "$OUT/ttq_eval.json" 2>&1; tail -c 600 "$OUT/ttq_eval.json"
""",
    ),
    "variants": (
        "gpu_next.sh STAGE=variants",
        "short time-to-quality runs of several flag sets "
        "(VARIANTS: sets separated by ';', BUDGETS)",
        """
L=${DATA:-.gpu/lego}
i=0
IFS=';' read -ra sets <<< "${VARIANTS:-}"
for v in "${sets[@]}"; do
  i=$((i+1))
  rm -rf /tmp/ttq_v$i; python3 scripts/time_to_quality.py run /tmp/ttq_v$i --budgets ${BUDGETS:-5,15,30,60} \\
    --label "v$i:$v" --chunk ${CHUNK:-400000} -- train nerf --data "$L" --field hash --device cuda \\
    --tf32 --batch 4096 --val-images 0 --quiet --no-tensorboard $v 2>&1 | tail -7 \\
    | tee "$OUT/ttq_v${i}${TAG:-}.txt"
  cp /tmp/ttq_v$i/ttq.json "$OUT/ttq_v${i}${TAG:-}.json"
done
""",
    ),
    "capture_ttq": (
        "gpu_next.sh STAGE=capture",
        "a real capture (DATA, NAME, BUDGETS) trained "
        "with snapshots, scored at each budget, a sheet of spiral frames (ROUND)",
        """
D=${DATA:-.gpu/beer}; N=${NAME:-beer}
python3 scripts/time_to_quality.py run /tmp/cap_$N --budgets ${BUDGETS:-60,120,300} \\
  --label "$N ${LABEL:-main}" --chunk 65536 -- train nerf --data "$D" --field hash \\
  --device cuda --tf32 --batch 4096 --target-samples 262144 --val-images 0 --quiet \\
  --no-tensorboard ${EXTRA:-} 2>&1 | tail -8 | tee "$OUT/cap_$N.txt"
cp /tmp/cap_$N/ttq.json "$OUT/cap_$N.json"; cp /tmp/cap_$N/run/config.json "$OUT/cap_${N}_config.json"
python3 -m warpnerf.cli render /tmp/cap_$N/run --frames ${FRAMES:-6} --size ${SIZE:-640x360} \\
  2>&1 | tail -2
# one sheet of the spiral's colour and depth frames (a call returns few files)
python3 scripts/contact_sheet.py "$OUT/spiral_$N.png" --cols ${FRAMES:-6} --every 1 \\
  /tmp/cap_$N/run/render_spiral/rgb_*.png /tmp/cap_$N/run/render_spiral/depth_*.png
if [ -n "${ROUND:-}" ]; then  # eval frame time with render rounds of ROUND samples a ray
  python3 -m warpnerf.cli eval /tmp/cap_$N/run --split val --round-samples "$ROUND" \\
    --out /tmp/cap_${N}_round > "$OUT/cap_${N}_round$ROUND.json" 2>&1
  tail -c 400 "$OUT/cap_${N}_round$ROUND.json"
fi
""",
    ),
    "ablation": (
        "gpu_recipe_ablation.sh",
        "the training recipe's ablation (issue 44): one run per "
        "row of ROWS ('name|flags;...') with BASE flags for SECS, every val image scored, "
        "appended to $OUT/ablation.md; a row that fell back from the CUDA graph is marked",
        _row_runs(
            "ablation",
            "abl",
            data=".gpu/lego",
            secs=60,
            rows="base|",
            settings="BASE=${BASE:---field hash --device cuda --tf32 --batch 4096 "
            "--target-samples 524288}\n",
            header="| data | row | flags | seconds | steps | median step ms | val images | "
            "val PSNR | val SSIM | median frame ms | step |",
            train="$BASE --iters 1000000",
            then="""  python3 -m warpnerf.cli eval "$run" --split val --chunk 400000 --out "${run}_eval" \\
    >> "$run.log" 2>&1 || echo "eval $TAG/$name failed" | tee -a "$OUT/log.txt"
  { echo "== $TAG/$name: $flags"; tail -n 15 "$run.log"; } >> "$OUT/log.txt"
  $GPU --summary ablation "$run" "$TAG" "$name" "$flags" "$SECS" | tee -a "$OUT/ablation.md"
""",
        ),
    ),
    "fog": (
        "none: issue 48",
        "fog on a capture (issue 48): one run per row of ROWS ('name|flags;...') with the "
        "capture defaults for SECS, every val image scored, scripts/fog_report.py on the spiral "
        "(FRAMES frames: its sheet and fog.json in $OUT/fog_TAG_NAME), a row each in $OUT/fog.md "
        "(about 3.5 minutes a row at SECS=120: two rows a call)",
        _row_runs(
            "fog",
            "fog",
            data="/root/stage/beer",
            secs=120,
            rows="base|;near|--near-loss 0.1",
            header="| data | row | flags | seconds | steps | val PSNR | val SSIM | "
            "near_median share | rays > 10 % | near_centre share | rays > 10 % |",
            train="--device cuda",
            then="""  python3 -m warpnerf.cli eval "$run" --split val --quiet --out "${run}_eval" >> "$run.log" 2>&1 \\
    || echo "eval $TAG/$name failed" | tee -a "$OUT/log.txt"
  python3 scripts/fog_report.py "$run" --frames "${FRAMES:-12}" --out "$OUT/fog_${TAG}_$name" \\
    >> "$run.log" 2>&1 || echo "fog_report $TAG/$name failed" | tee -a "$OUT/log.txt"
  { echo "== $TAG/$name: $flags"; tail -n 6 "$run.log" | cut -c1-400; } >> "$OUT/log.txt"
  $GPU --summary fog "$run" "$OUT/fog_${TAG}_$name/fog.json" "$TAG" "$name" "$flags" "$SECS" \\
    | tee -a "$OUT/fog.md"
""",
        ),
    ),
    "nerf_materials": (
        "gpu_nerf.sh materials",
        "MLP NeRF on materials with and without view dependence (SECS), eval",
        f"""
common="{_NERF}"
for vd in view-dependence no-view-dependence; do
  python3 -m warpnerf.cli train nerf --data .devdata/materials --out /tmp/mat_$vd --$vd $common \\
    --samples 128 --iters 20000 --max-seconds ${{SECS:-190}} --val-every 1000 --val-images 2 \\
    2>&1 | tail -4 | tee -a "$OUT/log.txt"
  python3 -m warpnerf.cli eval /tmp/mat_$vd --split val 2>&1 | tail -1 | tee -a "$OUT/log.txt"
  cp /tmp/mat_$vd/history.json "$OUT/materials_${{vd}}_history.json"
  cp /tmp/mat_$vd/eval_val/metrics.json "$OUT/materials_${{vd}}_metrics.json"
done
cp /tmp/mat_view-dependence/eval_val/val_003.png "$OUT/materials_vd_val_003.png"
cp /tmp/mat_no-view-dependence/eval_val/val_003.png "$OUT/materials_novd_val_003.png"
gpu_line
""",
    ),
    "nerf_lego_seed": (
        "gpu_nerf.sh lego_seed",
        "MLP NeRF on lego downscaled 3x",
        _nerf_lego("lego_seed"),
    ),
    "nerf_lego_full": (
        "gpu_nerf.sh lego_full",
        "MLP NeRF on lego, coarse + fine",
        _nerf_lego("lego_full"),
    ),
    "nerf_lego_hash": (
        "gpu_nerf.sh lego_hash",
        "hash NeRF on lego, coarse + fine, no grid",
        _nerf_lego("lego_hash"),
    ),
    "nerf_lego_grid": (
        "gpu_nerf.sh lego_grid",
        "hash field + occupancy grid on lego for SECS, eval",
        _lego_grid("lego_grid"),
    ),
    "nerf_lego_grid_more": (
        "gpu_nerf.sh lego_grid_more",
        "nerf_lego_grid's run resumed for SECS more, eval",
        _lego_grid("lego_grid_more"),
    ),
    "nerf_capture": (
        "gpu_nerf.sh capture",
        "a real capture (DATA, NAME) trained in STAGES of seconds, eval after each",
        """
run=/tmp/${NAME:-capture}
first=1
for secs in ${STAGES:-60 60 180}; do
  if [ $first = 1 ]; then
    python3 -m warpnerf.cli train nerf --data $DATA --out $run --device cuda --tf32 --field hash \\
      --batch 4096 --target-samples ${TARGET:-262144} ${EXTRA:-} --iters 100000 \\
      --max-seconds $secs --val-every 100000 --val-images 0 --quiet 2>&1 | tail -3 | tee -a "$OUT/log.txt"
    first=0
  else
    python3 -m warpnerf.cli train nerf --out $run --resume --iters 100000 --max-seconds $secs \\
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
gpu_line
""",
    ),
    "speed_sweep": (
        "gpu_nerf.sh sweep",
        "speed against error of nerf_lego_grid's run (speed_vs_error.py)",
        """
python3 scripts/speed_vs_error.py sweep /tmp/lego_grid "$OUT/speed_vs_error.json" --images ${EVAL_IMAGES:-5} \\
  2>&1 | tee -a "$OUT/log.txt"
gpu_line
""",
    ),
    # -- surfaces -------------------------------------------------------------------------------
    "surfaces_trace": (
        "gpu_surfaces.sh trace",
        "CUDA tests of the surface code, demos 06/07/08 on cuda",
        _VOLSDF
        + """
python3 -m pytest -o addopts=-ra -q -p no:cacheprovider tests/test_sphere_trace.py tests/test_neural_sdf.py \\
  tests/test_encoding.py tests/test_nerf.py -k cuda 2>&1 | tail -3 | tee -a "$OUT/log.txt"
python3 demos/06_sphere_trace_torus.py --device cuda --out /tmp/d06 --size 400 | tail -1 | tee -a "$OUT/log.txt"
python3 demos/07_sphere_trace_scene.py --device cuda --out /tmp/d07 --size 400 | tail -1 | tee -a "$OUT/log.txt"
python3 demos/08_neural_sdf.py --device cuda --points "$DATA/bunny_pointcloud.npz" --iters 3000 \\
  --batch 8192 --resolution 256 --out /tmp/d08 | tail -1 | tee -a "$OUT/log.txt"
cp /tmp/d06/frame_000.png "$OUT/torus_frame.png"; cp /tmp/d07/frame_000.png "$OUT/scene_frame.png"
cp /tmp/d08/run/mesh.png "$OUT/bunny_mesh.png"; cp /tmp/d08/run/metrics.json "$OUT/bunny_metrics.json"
gpu_line
""",
    ),
    "surfaces_materials": (
        "gpu_surfaces.sh volsdf_materials BETA...",
        "VolSDF on materials with "
        "fixed BETAS (space-separated; 'learned': learned), eval, geometry",
        _VOLSDF
        + """
for beta in ${BETAS:-learned}; do
  if [ "$beta" = learned ]; then extra=""; else extra="--beta $beta --fixed-beta"; fi
  run=/tmp/vs_mat_$beta
  python3 -m warpnerf.cli train volsdf --data "$DATA/materials" --out $run --aabb 1.7 $vs $extra \\
    2>&1 | tail -2 | tee -a "$OUT/log.txt"
  python3 -m warpnerf.cli eval $run --split val 2>&1 | tail -1 | tee -a "$OUT/log.txt"
  python3 scripts/materials_geometry.py $run --json "$OUT/materials_beta_${beta}_geometry.json" \\
    2>&1 | tail -1 | tee -a "$OUT/log.txt"
  cp $run/history.json "$OUT/materials_beta_${beta}_history.json"
  cp $run/eval_val/metrics.json "$OUT/materials_beta_${beta}_metrics.json"
  cp $run/eval_val/val_003.png "$OUT/materials_beta_${beta}_val_003.png"
done
gpu_line
""",
    ),
    "surfaces_lego": (
        "gpu_surfaces.sh volsdf_lego",
        "VolSDF on lego (learned beta), eval, spiral renders, mesh",
        _VOLSDF
        + """
run=/tmp/vs_lego
python3 -m warpnerf.cli train volsdf --data "$DATA/lego" --out $run $vs 2>&1 | tail -2 | tee -a "$OUT/log.txt"
python3 -m warpnerf.cli eval $run --split val --max-images ${EVAL_IMAGES:-10} 2>&1 | tail -1 | tee -a "$OUT/log.txt"
python3 -m warpnerf.cli render $run --frames ${FRAMES:-20} --size 200x200 2>&1 | tail -1 | tee -a "$OUT/log.txt"
python3 -m warpnerf.cli mesh $run --resolution 256 --out "$OUT/lego_volsdf.ply" 2>&1 | tail -1 | tee -a "$OUT/log.txt"
cp $run/history.json $run/eval_val/metrics.json "$OUT/" ; cp $run/render_spiral/geometry.gif $run/render_spiral/rgb.gif "$OUT/"
cp $run/eval_val/val_000.png "$OUT/lego_volsdf_val_000.png"
gpu_line
""",
    ),
    "hash_sdf": (
        "gpu_hash_sdf.sh",
        "hash_sdf trained SECS on DATA (TAG, EXTRA), every val image "
        "scored, meshed; GEOMETRY=1 materials' geometry, SNAP=15,30,.. snapshots scored "
        "(time_to_quality.py), SPHERE=1 surface_renderers.py",
        _AB
        + """
SECS=${SECS:-240}
TAG=${TAG:-lego}
R=/tmp/sdf_$TAG
rm -rf $R ${R}_eval
python3 -m warpnerf.cli train volsdf --data "$DATA" --field hash_sdf --device cuda --tf32 \\
  --batch 4096 --target-samples 262144 --iters 100000 --max-seconds "$SECS" --val-images 0 \\
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
$GPU --summary hash_sdf "$TAG" "$SECS" | tee "$OUT/surface_$TAG.md"
""",
    ),
    "reflect": (
        "gpu_next.sh STAGE=reflect",
        "hash_sdf on materials with the reflection-aware "
        "colour head (the hash_sdf phase with issue 17's lapB flags)",
        """
DATA=${DATA:-.gpu/materials} SECS=300 TAG=reflect GEOMETRY=1 EXTRA="--aabb 1.7 \\
  --beta-final 0.005 --beta-anneal-steps 6000 --march-step 0.0029 --max-samples 2048 \\
  --color-direction reflect" $GPU hash_sdf
""",
    ),
}


# ---------------------------------------------------------------------------------------------
# The tables the phases print (python3 scripts/gpu.py --summary NAME ARGS).
# ---------------------------------------------------------------------------------------------


def _load(path):
    with open(path) as f:
        return json.load(f)


def _median_step_ms(seconds, start=300):
    return statistics.median(1e3 * (b - a) for a, b in zip(seconds[start:], seconds[start + 1 :]))


def summary_before_after(secs):
    secs = float(secs)
    print(
        f"| version | steps in {secs:g} s | median step ms | val images | val PSNR | val SSIM | median frame ms |"
    )
    print("|---|---|---|---|---|---|---|")
    res = {}
    for v in ("base", "new"):
        h = _load(f"/tmp/ba_{v}/history.json")
        m = _load(f"/tmp/ba_{v}_eval/metrics.json")
        res[v] = m["psnr"]
        print(f"| {v} | {h['step'][-1]} | {_median_step_ms(h['seconds']):.2f} | {m['n_images']} | "
              f"{m['psnr']:.3f} | {m['ssim']:.4f} | {m['render_ms_median']:.1f} |")  # fmt: skip
    print(f"new - base: {res['new'] - res['base']:+.3f} dB")


def summary_overhead(iters, reps, ereps, out):
    iters, reps, ereps = int(iters), int(reps), int(ereps)

    def step_ms(run):
        """median step ms over steps 300..iters, and the median per 262144 kept samples"""
        h = _load(f"{run}/history.json")
        s, spr, b = h["seconds"], h["samples_per_ray"], h["batch"]
        d = [1e3 * (s[i] - s[i - 1]) for i in range(300, iters)]
        per = [d[j] * 262144 / max(spr[i] * b[i], 1) for j, i in enumerate(range(300, iters))]
        return statistics.median(d), statistics.median(per), statistics.mean(spr[300:])

    print(
        f"| version | run | median step ms (steps 300..{iters}) | ms per 262144 samples | samples/ray |"
    )
    print("|---|---|---|---|---|")
    rows = {}
    for r in range(1, reps + 1):
        for v in ("base", "new"):
            ms, per, spr = step_ms(f"/tmp/ab_{v}_{r}")
            rows.setdefault(v, []).append(ms)
            rows.setdefault(v + "_per", []).append(per)
            print(f"| {v} | {r} | {ms:.3f} | {per:.3f} | {spr:.1f} |")
    for v in ("base", "new"):
        rm = [
            _load(f"/tmp/ev_{v}_{r}/metrics.json")["render_ms_median"] for r in range(1, ereps + 1)
        ]
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
              f"+- {sd:.4f} (standard error)")  # fmt: skip
    with open(f"{out}/overhead.json", "w") as f:
        json.dump(rows, f)


def summary_hash_sdf(tag, secs):
    secs = float(secs)
    h = _load(f"/tmp/sdf_{tag}/history.json")
    m = _load(f"/tmp/sdf_{tag}_eval/metrics.json")
    s = h["seconds"]
    step = _median_step_ms(s) if len(s) > 302 else float("nan")
    beta = h.get("beta", [None])[-1]
    print(
        f"| run | steps in {secs:g} s | median step ms | final beta | val images | val PSNR | val SSIM | median frame ms |"
    )
    print("|---|---|---|---|---|---|---|---|")
    print(f"| {tag} | {h['step'][-1]} | {step:.2f} | {beta} | {m['n_images']} | {m['psnr']:.3f} | "
          f"{m['ssim']:.4f} | {m['render_ms_median']:.1f} |")  # fmt: skip
    for k in ("psnr", "samples_per_ray", "batch", "beta"):
        if k in h and h[k]:
            v = h[k]
            print(k, [round(float(v[i]), 4) for i in range(0, len(v), max(1, len(v) // 8))])


def summary_ablation(run, tag, name, flags, secs):
    try:
        h = _load(f"{run}/history.json")
        m = _load(f"{run}_eval/metrics.json")
    except OSError as e:
        print(f"| {tag} | {name} | `{flags}` | {secs} | failed: {e} | | | | | | |")
        return
    s = h["seconds"]
    step = _median_step_ms(s) if len(s) > 310 else float("nan")
    with open(f"{run}.log") as f:
        eager = "eager fallback" if "capture failed" in f.read() else "graph"
    print(f"| {tag} | {name} | `{flags}` | {secs} | {h['step'][-1]} | {step:.2f} | {m['n_images']} | "
          f"{m['psnr']:.3f} | {m['ssim']:.4f} | {m['render_ms_median']:.1f} | {eager} |")  # fmt: skip


def summary_fog(run, fog, tag, name, flags, secs):
    """One row of the fog phase: steps, val PSNR/SSIM, fog_report.py's overall figures."""
    try:
        h = _load(f"{run}/history.json")
        m = _load(f"{run}_eval/metrics.json")
        o = _load(fog)["overall"]
    except OSError as e:
        print(f"| {tag} | {name} | `{flags}` | {secs} | failed: {e} | | | | | | |")
        return
    near = [f"{o[k]['share']:.4f} | {o[k]['rays_over_10pct']:.3f}"
            for k in ("near_median", "near_centre")]  # fmt: skip
    print(f"| {tag} | {name} | `{flags}` | {secs} | {h['step'][-1]} | {m['psnr']:.3f} | "
          f"{m['ssim']:.4f} | {near[0]} | {near[1]} |")  # fmt: skip


def _graph_rows(prefix, versions, sdf):
    rows = {}
    for g in versions:
        try:
            h = _load(f"/tmp/{prefix}_{g}/history.json")
        except OSError:
            continue
        try:
            m = _load(f"/tmp/{prefix}_{g}_eval/metrics.json")
        except OSError:
            if sdf:
                continue
            m = {}
        s, n = h["seconds"], len(h["seconds"])
        half = [1e3 * (b - a) for a, b in zip(s[n // 2 :], s[n // 2 + 1 :])]
        if sdf:
            rows[g] = dict(steps=h["step"][-1], seconds=s[-1],
                           median_step_ms_second_half=statistics.median(half),
                           rays_last=h["batch"][-1], dropped_total=sum(h.get("dropped_samples", [])),
                           val_psnr=m.get("psnr"), val_ssim=m.get("ssim"),
                           frame_ms_median=m.get("render_ms_median"), n_images=m.get("n_images"),
                           beta_last=h["beta"][-1])  # fmt: skip
        else:
            rows[g] = dict(steps=h["step"][-1], seconds=s[-1], first_step_s=s[0],
                           median_step_ms_second_half=statistics.median(half),
                           steps_per_s_second_half=1e3 / statistics.median(half),
                           rays_last=h["batch"][-1], samples_per_ray_last=h["samples_per_ray"][-1],
                           dropped_total=sum(h.get("dropped_samples", [])),
                           steps_with_drops=sum(1 for d in h.get("dropped_samples", []) if d),
                           val_psnr=m.get("psnr"), val_ssim=m.get("ssim"),
                           frame_ms_median=m.get("render_ms_median"), n_images=m.get("n_images"))  # fmt: skip
    return rows


def summary_graph_speed(out):
    rows = _graph_rows("sp", ("base", "off", "auto"), sdf=False)
    with open(f"{out}/speed.json", "w") as f:
        json.dump(rows, f, indent=1)
    print(json.dumps(rows, indent=1))


def summary_graph_sdfspeed(out):
    rows = _graph_rows("sdf", ("off", "auto"), sdf=True)
    with open(f"{out}/sdf_speed.json", "w") as f:
        json.dump(rows, f, indent=1)
    print(json.dumps(rows, indent=1))


def summary_graph_profile(path, label):
    """One line of a profile_train_step.py JSON (a hash_sdf one: fewer keys and its top ops)."""
    r = _load(path)
    sdf = label.startswith("hash_sdf")
    keys = ("step_ms_median", "device_busy_ms_per_step", "host_syncs_per_step",
            *(() if sdf else ("kernel_launches_per_step",)), "launches_issued_per_step",
            "rays_per_step", *(() if sdf else ("samples_per_ray", "dropped_samples_last_50")),
            "graphs_captured")  # fmt: skip
    print(label, {k: r.get(k) for k in keys})
    if sdf:
        print(list(r["top_device_ops_ms_per_step"].items())[:6])


SUMMARIES = {
    name[len("summary_") :]: f for name, f in globals().items() if name.startswith("summary_")
}


def script(phase: str) -> str:
    """The bash script a phase runs."""
    return PRELUDE + PHASES[phase][2].lstrip("\n")


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__)
        return 0 if argv else 2
    if argv[0] == "--list":
        for name, (old, what, _) in PHASES.items():
            print(f"{name:22s} {what}  [was {old}]")
        return 0
    if argv[0] == "--summary":
        SUMMARIES[argv[1]](*argv[2:])
        return 0
    if argv[0] == "--print":
        print(script(argv[1]), end="")
        return 0
    unknown = [p for p in argv if p not in PHASES]
    if unknown:
        print(f"unknown phase(s) {' '.join(unknown)}; --list shows them", file=sys.stderr)
        return 2
    failed = []
    for phase in argv:
        print(f"=== {phase} {time.strftime('%H:%M:%S', time.gmtime())}", flush=True)
        if subprocess.run(["bash", "-c", script(phase)], env=os.environ).returncode:
            failed.append(phase)
    if failed:
        print(f"failed: {' '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
