"""How often a hash-field training step synchronises the host with the GPU (issue 18: the step
is host-bound, and every sync serialises host and GPU). CUDA only; CPU has no such syncs."""

import pytest

from warpnerf.cli.parser import nerf_task_from_argv
from warpnerf.train.loop import bare_step, sync_sites


def test_training_step_syncs(device):
    if device.type != "cuda":
        pytest.skip("host syncs are a CUDA matter")
    _, task, opt = nerf_task_from_argv(
        "train nerf --data builtin --builtin-size 32 --field hash --batch 512 "
        "--target-samples 16384 --device cuda".split()
    )
    for i in range(40):  # past the grid's warm-up
        float(bare_step(task, opt, i))
    steps = 16  # one grid update every 16 steps (cfg.grid_every) falls in the window
    sites = sync_sites(lambda: [bare_step(task, opt, i) for i in range(40, 40 + steps)])
    # the marcher's sample total and the live-sample selection's size (both size allocations),
    # plus the grid update's few syncs once every 16 steps; the loop's read of the loss is apart
    assert sum(sites.values()) / steps <= 2.5, sites
