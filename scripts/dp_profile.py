"""Where a data-parallel training step's time goes (issue 21): the task of `warpnerf train nerf`
built from the same flags on every rank, WARM steps untimed, then STEPS steps timed as the loop
runs them (one host sync a step), then STEPS steps with a synchronisation after each phase:

- ``loss``: the grid update (every ``--grid-every`` steps; reported apart), the batch draw, the
  march, the field and the compositing forward, and in a data-parallel run the all-reduce of the
  global sample count (read on the host: it sizes the next batch);
- ``backward``: zero_grad and the backward pass;
- ``allreduce``: the gradients' one all-reduce (flattened; data-parallel only);
- ``optimizer``: the divergence flags and the Adam step;
- ``sync``: the loop's end of step: the loss/terms/flags all-reduce and host read, and rank 0's
  clock shared with all ranks.

Each phase's median over the synchronised steps is the slowest rank's. Also: the gradient
buffer's size and the all-reduce's bus bandwidth on it alone (data-parallel only).

    python3 scripts/dp_profile.py [--warm 200] [--steps 100] [--json out.json] -- train nerf \
        --data lego --field hash --device cuda --tf32 --batch 4096 --target-samples 262144
    python3 -m torch.distributed.run --standalone --nproc-per-node 2 scripts/dp_profile.py ...
"""

from __future__ import annotations

import json
import statistics
import time


def main():
    from warpnerf.cli.parser import step_tool_args

    a, train_argv = step_tool_args(__doc__, 200, 100)
    if train_argv[:2] not in (["train", "nerf"], ["train", "volsdf"]):
        raise SystemExit("after --, give a `train nerf ...` or `train volsdf ...` command line")

    import torch

    from warpnerf.cli.parser import build_parser, nerf_task_from_argv
    from warpnerf.cli.train import nerf_config_from_args
    from warpnerf.train.distributed import from_env
    from warpnerf.train.loop import LoopSettings, lr_at, nonfinite_flags, read_terms, set_lr

    want = nerf_config_from_args(build_parser().parse_args([*train_argv, "--out", "x"])).device
    dist, device = from_env(want)
    cfg, task, opt = nerf_task_from_argv(train_argv, dist, device)
    s = LoopSettings.of(cfg, "profile")
    params = task.parameters()
    cuda = cfg.device.startswith("cuda")
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    main_rank = dist is None or dist.main

    def loop_step(i, phases=None):
        """One step as run_loop runs it; with ``phases`` (a dict of lists), synchronised and
        timed after each phase."""
        marks = [time.perf_counter()]

        def mark():
            if phases is not None:
                sync()
                marks.append(time.perf_counter())

        set_lr(opt, lr_at(s, i))
        loss, terms = task.loss(i)
        mark()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        mark()
        if dist is not None:
            dist.average_grads(params)
        mark()
        flags = nonfinite_flags(loss, params)
        opt.step()
        mark()
        read_terms(loss, terms, flags, dist)
        if cuda:
            sync()
        if dist is not None:
            dist.max_(torch.tensor([0.0, 0.0], dtype=torch.float64, device=loss.device)).tolist()
        mark()
        if phases is not None:
            names = ("loss", "backward", "allreduce", "optimizer", "sync")
            key = "loss_grid_step" if i % cfg.grid_every == 0 else "loss"
            for n, t0, t1 in zip(names, marks, marks[1:]):
                phases.setdefault(key if n == "loss" else n, []).append(1e3 * (t1 - t0))
        return time.perf_counter() - marks[0]

    for i in range(a.warm):
        loop_step(i)
    sync()
    step = a.warm
    t0 = time.perf_counter()
    for _ in range(a.steps):
        loop_step(step)
        step += 1
    sync()
    step_ms = 1e3 * (time.perf_counter() - t0) / a.steps
    phases: dict = {}
    for _ in range(a.steps):
        loop_step(step, phases)
        step += 1
    med = {k: statistics.median(v) for k, v in phases.items()}
    n_grad = sum(p.numel() for p in params)
    res = {"ranks": 1 if dist is None else dist.world, "step_ms": step_ms,
           "phase_ms_median": med, "phases_sum_ms": sum(v for k, v in med.items()
                                                        if k != "loss_grid_step"),
           "grid_every": cfg.grid_every, "samples_per_step_target": cfg.target_samples,
           "rays_per_step_now": task.batch, "grad_numel": n_grad,
           "grad_mib": n_grad * 4 / 2**20,
           "device": torch.cuda.get_device_name() if cuda else "cpu"}  # fmt: skip
    if dist is not None:  # the slowest rank's figures, and the all-reduce alone
        keys = sorted(med)
        t = torch.tensor([step_ms] + [med[k] for k in keys], dtype=torch.float64,
                         device=cfg.device)  # fmt: skip
        dist.max_(t)
        vals = t.tolist()
        res["step_ms"] = vals[0]
        res["phase_ms_median"] = dict(zip(keys, vals[1:]))
        flat = torch.randn(n_grad, device=cfg.device)
        for _ in range(5):
            dist.sum_(flat)
        sync()
        reps, t0 = 20, time.perf_counter()
        for _ in range(reps):
            dist.sum_(flat)
        sync()
        sec = (time.perf_counter() - t0) / reps
        w = dist.world
        res["allreduce_alone_ms"] = 1e3 * sec
        res["allreduce_bus_gb_s"] = n_grad * 4 * 2 * (w - 1) / w / sec / 1e9
    if main_rank:
        print(json.dumps(res, indent=1), flush=True)
        if a.json:
            with open(a.json, "w") as f:
                json.dump(res, f, indent=1)
    if dist is not None:
        dist.close()


if __name__ == "__main__":
    main()
