"""How often a hash-field training step synchronises the host with the GPU (issue 18: the step
is host-bound, and every sync serialises host and GPU). CUDA only; CPU has no such syncs."""

import collections
import traceback
import warnings

import pytest
import torch


def _task(device):
    from warpnerf.cli.parser import build_parser
    from warpnerf.cli.train import nerf_config_from_args
    from warpnerf.train.nerf import NeRFTask, build_model, load_data, resolve_data

    argv = ("train nerf --data builtin --builtin-size 32 --field hash --batch 512 "
            f"--target-samples 16384 --out unused --device {device}").split()  # fmt: skip
    cfg = nerf_config_from_args(build_parser().parse_args(argv)).validate()
    resolve_data(cfg)
    task = NeRFTask(cfg, build_model(cfg), load_data(cfg, "train"), None, log=lambda *x: None)
    return task, task.optimizer(task.parameters(), cfg.lr)


def test_training_step_syncs(device):
    if device.type != "cuda":
        pytest.skip("host syncs are a CUDA matter")
    task, opt = _task("cuda")
    steps = 16  # one grid update every 16 steps (cfg.grid_every) falls in the window

    def step(i):
        loss, _ = task.loss(i)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return loss

    for i in range(40):  # past the grid's warm-up
        float(step(i))
    sites = collections.Counter()

    def record(message, *a, **k):
        if "synchronizing" not in str(message):  # (the debug mode's own notice)
            return
        frames = [f for f in traceback.extract_stack() if "/warpnerf/" in f.filename]
        where = frames[-1] if frames else traceback.extract_stack()[-2]
        sites[f"{where.filename.split('/warpnerf/')[-1]}:{where.lineno}"] += 1

    old = warnings.showwarning
    warnings.showwarning = record
    torch.cuda.synchronize()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            warnings.showwarning = record
            torch.cuda.set_sync_debug_mode("warn")
            for i in range(40, 40 + steps):
                step(i)
    finally:
        torch.cuda.set_sync_debug_mode(0)
        warnings.showwarning = old
    per_step = sum(sites.values()) / steps
    # the marcher's sample total and the live-sample selection's size (both size allocations),
    # plus the grid update's few syncs once every 16 steps; the loop's read of the loss is apart
    assert per_step <= 2.5, dict(sites)
