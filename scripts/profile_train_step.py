"""Where a training step's time goes (issue 18): the NeRF/VolSDF task of `warpnerf train` built from
the same flags, WARM steps run untimed, then STEPS steps timed (wall clock, synchronised) and one
window profiled with torch.profiler (CPU + CUDA): the top operators by device time and by host
time, the host syncs, and the share of device-busy time in the step (a step far longer than its
device time is host-bound: launches and syncs).

    python3 scripts/profile_train_step.py [--warm 300] [--steps 50] [--json out.json] -- \
        train nerf --data lego --field hash --device cuda --tf32 --batch 4096 \
        --target-samples 262144
"""

from __future__ import annotations

import json
import statistics
import time


def main():
    from warpnerf.cli.parser import step_tool_args

    def own(p):
        p.add_argument("--cprofile", type=int, default=50,
                       help="steps run under cProfile for the host side (0: none)")  # fmt: skip
        p.add_argument("--softplus", choices=("torch", "warp"), default="torch",
                       help="the SDF networks' softplus: torch's op or the Warp kernels "
                       "(warpnerf.ops.activations; issue 47's A/B)")  # fmt: skip
        p.add_argument("--centred", action="store_true",
                       help="the SDF networks' input [2 u - 1, features] from the encoding's "
                       "kernel instead of a concatenation (issue 47's A/B)")  # fmt: skip

    a, train_argv = step_tool_args(__doc__, 300, 50, add=own)
    from warpnerf.ops.activations import activation_kernels
    from warpnerf.ops.encoding import encoding_kernels

    with activation_kernels(a.softplus), encoding_kernels(centred=a.centred):
        _profile(a, train_argv)


def _profile(a, train_argv):
    import torch
    from torch.profiler import ProfilerActivity, profile

    from warpnerf.cli.parser import nerf_task_from_argv
    from warpnerf.train.loop import LoopSettings, bare_step, lr_at

    cfg, task, opt = nerf_task_from_argv(train_argv)
    s = LoopSettings.of(cfg, "profile")
    cuda = cfg.device.startswith("cuda")
    sync = torch.cuda.synchronize if cuda else (lambda: None)

    history = {}

    def step(i):  # the loop's one host sync a step: the loss and terms, recorded
        return float(bare_step(task, opt, i, lr_at(s, i), history=history))

    for i in range(a.warm):
        step(i)
    sync()
    times = []
    for i in range(a.warm, a.warm + a.steps):
        t = time.perf_counter()
        step(i)
        sync()
        times.append(1e3 * (time.perf_counter() - t))
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    n_prof = 10
    with profile(activities=acts) as prof:
        for i in range(a.warm + a.steps, a.warm + a.steps + n_prof):
            step(i)
        sync()
    ka = prof.key_averages()
    dev_key = "self_device_time_total" if cuda else "self_cpu_time_total"
    print(ka.table(sort_by=dev_key, row_limit=25))
    print(ka.table(sort_by="self_cpu_time_total", row_limit=15))
    # device time of the kernels themselves (an autograd Function's range reports its kernels'
    # time again as its own: counting every row would count those twice)
    from torch.autograd import DeviceType

    kernels = [k for k in ka if k.device_type == DeviceType.CUDA]
    dev_total = sum(k.self_device_time_total for k in kernels) / 1e3 / n_prof  # ms per step
    syncs = {k.key: k.count // n_prof for k in ka
             if k.key in ("aten::_local_scalar_dense", "aten::item", "aten::nonzero",
                          "cudaStreamSynchronize", "cudaDeviceSynchronize")}  # fmt: skip
    launches = sum(k.count for k in ka if k.key in ("cudaLaunchKernel", "cuLaunchKernel"))
    # what the host issues besides kernels: graph replays (each runs a whole captured step)
    # and copies
    issued = {k.key: k.count / n_prof for k in ka
              if k.key in ("cudaGraphLaunch", "cudaMemcpyAsync", "cudaMemsetAsync")}  # fmt: skip
    top = sorted(ka, key=lambda k: -getattr(k, dev_key, 0.0))[:15]
    res = {
        "step_ms_median": statistics.median(times),
        "device_busy_ms_per_step": dev_total if cuda else None,
        "host_syncs_per_step": syncs,
        "kernel_launches_per_step": launches / n_prof,
        "other_issued_per_step": issued,
        "launches_issued_per_step": launches / n_prof + sum(issued.values()),
        "rays_per_step": task.batch,
        "samples_per_ray": history.get("samples_per_ray", [None])[-1],
        "dropped_samples_last_50": sum(history.get("dropped_samples", [])[-50:]),
        "graphs_captured": getattr(getattr(task, "graph", None), "captures", None),
        "top_device_ops_ms_per_step": {k.key: getattr(k, dev_key) / 1e3 / n_prof for k in top},
        "device": torch.cuda.get_device_name() if cuda else "cpu",
    }
    res["softplus"], res["centred"] = a.softplus, a.centred
    if a.cprofile:
        res["host_python"] = host_profile(step, a.warm + a.steps + n_prof, a.cprofile, sync)
    print(json.dumps(res, indent=1))
    if a.json:
        with open(a.json, "w") as f:
            json.dump(res, f, indent=1)


def host_profile(step, first, n, sync):
    """Where the host's time goes: ``n`` steps under cProfile (Python functions; a CUDA launch is
    counted in the function that enqueues it, a host sync in the function that waits). Returns
    ms per step of the top functions by own time and by cumulative time."""
    import cProfile
    import pstats

    sync()
    prof = cProfile.Profile()
    t = time.perf_counter()
    prof.enable()
    for i in range(first, first + n):
        step(i)
    sync()
    prof.disable()
    wall = 1e3 * (time.perf_counter() - t) / n
    st = pstats.Stats(prof)

    def name(k):
        f, line, fn = k
        parts = f.replace("\\", "/").split("/")
        return f"{'/'.join(parts[-2:])}:{line}({fn})"

    rows = [(name(k), v[2] * 1e3 / n, v[3] * 1e3 / n, v[1] // n) for k, v in st.stats.items()]
    own = sorted(rows, key=lambda r: -r[1])[:30]
    cum = sorted(rows, key=lambda r: -r[2])[:40]
    print(f"host profile: {wall:.2f} ms a step under cProfile (n={n})")
    for r in own[:20]:
        print(f"  own {r[1]:7.3f} ms  cum {r[2]:7.3f} ms  x{r[3]:<4d} {r[0]}")
    return {
        "wall_ms_per_step_under_cprofile": wall,
        "top_own_ms": [{"fn": r[0], "own_ms": r[1], "cum_ms": r[2], "calls": r[3]} for r in own],
        "top_cum_ms": [{"fn": r[0], "own_ms": r[1], "cum_ms": r[2], "calls": r[3]} for r in cum],
    }


if __name__ == "__main__":
    main()
