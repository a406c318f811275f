"""Where a training step synchronises the host with the GPU (issue 18): the NeRF/VolSDF task of
`warpnerf train` built from the same flags, WARM steps untimed, then STEPS steps under
``torch.cuda.set_sync_debug_mode("warn")``: every synchronising PyTorch call is counted by the
innermost warpnerf frames that made it (file:line, per step; the loss is not read in the window:
the loop reads it once a step on top).
Warp calls that synchronise (none on the training path: launches are asynchronous) are not seen.

    python3 scripts/sync_sites.py [--warm 200] [--steps 20] [--json out.json] -- \
        train nerf --data lego --field hash --device cuda --tf32 --batch 4096 \
        --target-samples 262144
"""

from __future__ import annotations


def main():
    from warpnerf.cli.parser import step_tool_args

    a, train_argv = step_tool_args(__doc__, 200, 20)

    import torch

    from warpnerf.cli.parser import nerf_task_from_argv
    from warpnerf.train.loop import bare_step, sync_sites

    if not torch.cuda.is_available():
        raise SystemExit("sync_sites.py needs CUDA (the sync debug mode is a CUDA feature)")
    _, task, opt = nerf_task_from_argv(train_argv)
    for i in range(a.warm):
        float(bare_step(task, opt, i))

    def steps():  # (the loss is not read: the loop's one read per step is apart)
        for i in range(a.warm, a.warm + a.steps):
            bare_step(task, opt, i)

    found = sync_sites(steps)
    per_step = {k: v / a.steps for k, v in sorted(found.items(), key=lambda kv: -kv[1])}
    total = sum(per_step.values())
    print(f"synchronising calls per step: {total:.2f} (+1: the loop's read of the loss)")
    for k, v in per_step.items():
        print(f"{v:6.2f}  {k}")
    if a.json:
        from warpnerf.outputs import write_json

        write_json(a.json, {"argv": train_argv, "steps": a.steps, "per_step": per_step,
                            "device": torch.cuda.get_device_name()})  # fmt: skip


if __name__ == "__main__":
    main()
