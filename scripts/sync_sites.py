"""Where a training step synchronises the host with the GPU (issue 18): the NeRF/VolSDF task of
`warpnerf train` built from the same flags, WARM steps untimed, then STEPS steps under
``torch.cuda.set_sync_debug_mode("warn")``: every synchronising PyTorch call is counted by the
innermost warpnerf frame that made it (file:line, per step), plus the loop's own read of the loss.
Warp calls that synchronise (none on the training path: launches are asynchronous) are not seen.

    python3 scripts/sync_sites.py [--warm 200] [--steps 20] [--json out.json] -- \
        train nerf --data lego --field hash --device cuda --tf32 --batch 4096 \
        --target-samples 262144
"""

from __future__ import annotations

import argparse
import collections
import sys
import traceback
import warnings


def main():
    argv = sys.argv[1:]
    train_argv = argv[argv.index("--") + 1 :] if "--" in argv else []
    own = argv[: argv.index("--")] if "--" in argv else argv
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--warm", type=int, default=200)
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--json", default=None)
    a = p.parse_args(own)

    import torch

    from warpnerf.cli.parser import build_parser
    from warpnerf.cli.train import nerf_config_from_args
    from warpnerf.train.nerf import NeRFTask, build_model, load_data, resolve_data

    if not torch.cuda.is_available():
        raise SystemExit("sync_sites.py needs CUDA (the sync debug mode is a CUDA feature)")
    args = build_parser().parse_args([*train_argv, "--out", "/tmp/_sync_sites_unused"])
    cfg = nerf_config_from_args(args).validate()
    resolve_data(cfg)
    model = build_model(cfg)
    task = NeRFTask(cfg, model, load_data(cfg, "train"), None, log=lambda *x: None)
    torch.backends.cuda.matmul.allow_tf32 = cfg.tf32
    opt = task.optimizer(task.parameters(), cfg.lr)

    def step(i):
        loss, _ = task.loss(i)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return loss

    for i in range(a.warm):
        float(step(i))
    sites = collections.Counter()

    def record(message, category, filename, lineno, file=None, line=None):
        frames = [f for f in traceback.extract_stack() if "/warpnerf/" in f.filename]
        names = [f"{f.filename.split('/warpnerf/')[-1]}:{f.lineno}" for f in frames[-3:]]
        where = " < ".join(names[::-1]) or f"{filename}:{lineno}"
        sites[f"{str(message).split(chr(10))[0][:60]} @ {where}"] += 1

    old = warnings.showwarning
    warnings.showwarning = record
    warnings.simplefilter("always")
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("warn")
    try:
        for i in range(a.warm, a.warm + a.steps):
            loss = step(i)
            torch.cuda.set_sync_debug_mode(0)
            float(loss)  # the loop's one read (counted apart)
            torch.cuda.set_sync_debug_mode("warn")
    finally:
        torch.cuda.set_sync_debug_mode(0)
        warnings.showwarning = old
    per_step = {k: v / a.steps for k, v in sites.most_common()}
    total = sum(per_step.values())
    print(f"synchronising calls per step: {total:.2f} (+1: the loop's read of the loss)")
    for k, v in per_step.items():
        print(f"{v:6.2f}  {k}")
    if a.json:
        from warpnerf.io import write_json

        write_json(a.json, {"argv": train_argv, "steps": a.steps, "per_step": per_step,
                            "device": torch.cuda.get_device_name()})  # fmt: skip


if __name__ == "__main__":
    main()
