"""The effect of pose refinement (issue 20) where the true poses are known: a scene's training
cameras perturbed by random rotations and translations (zero mean), trained with and without
``--pose-refine``, plus the true poses as the ceiling; val PSNR on the true held-out poses and
the training cameras' pose error before and after.

    python3 experiments/recipe/pose_refine_effect.py [--rot-deg 1.0] [--trans 0.02] [--iters 600]
        [--json out.json] -- train nerf --data builtin --field hash ... (the run's flags;
        --pose-refine is added for the refining run)

The perturbation is applied in world space about each camera's centre (the model the correction
learns), with its mean removed (a common motion of all cameras is a motion of the scene that
the images cannot tell apart, and the corrections are mean-free too). Any dataset works whose
poses are taken as the truth (the built-in scene's are exact).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time


def rotation_deg(a, b):
    """Angles (degrees) between rotation matrices a, b [n, 3, 3]."""
    import torch

    tr = (a.transpose(-1, -2) @ b).diagonal(dim1=-2, dim2=-1).sum(-1)
    return torch.rad2deg(torch.acos(((tr - 1) / 2).clamp(-1, 1)))


def pose_errors(c2w, true):
    """(mean rotation error in degrees, mean translation error) of c2w against true."""
    rot = rotation_deg(c2w[:, :3, :3], true[:, :3, :3]).mean().item()
    trans = (c2w[:, :3, 3] - true[:, :3, 3]).norm(dim=-1).mean().item()
    return rot, trans


def perturb(c2w, rot_deg, trans, seed):
    """c2w with each camera rotated about its centre by ~rot_deg and moved by ~trans (random
    directions, magnitudes uniform in [0.5, 1.5] x, means removed)."""
    import torch

    from warpnerf.fields.poses import so3_exp

    g = torch.Generator().manual_seed(seed)
    n = c2w.shape[0]

    def vecs(scale):
        v = torch.nn.functional.normalize(
            torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1
        )
        v = v * scale * (0.5 + torch.rand(n, 1, generator=g, dtype=torch.float64))
        return v - v.mean(0)

    out = c2w.double().clone()
    out[:, :3, :3] = so3_exp(vecs(math.radians(rot_deg))) @ out[:, :3, :3]
    out[:, :3, 3] = out[:, :3, 3] + vecs(trans)
    return out.to(c2w.dtype)


def one_run(train_argv, refine, perturbed, iters, seed):
    import dataclasses

    import torch

    from warpnerf.cli.parser import nerf_task_from_argv
    from warpnerf.train.loop import LoopSettings, run_loop
    from warpnerf.train.nerf import load_data, validate

    argv = [*train_argv, "--iters", str(iters)] + (["--pose-refine"] if refine else [])
    cfg, task, _ = nerf_task_from_argv(argv)
    true = task.train.c2w.clone()
    if perturbed:
        task.train = dataclasses.replace(task.train, c2w=perturb(true, *perturbed, seed))
    given = task.train.c2w.clone()
    t0 = time.perf_counter()
    hist = run_loop(task, LoopSettings.of(cfg, "pose", iters=iters), run=None)
    secs = time.perf_counter() - t0
    val = load_data(cfg, "val")
    cfg = dataclasses.replace(cfg, val_images=len(val)).freeze()
    with torch.no_grad():
        psnr = validate(task.model, cfg, val)
        refined = given if task.model.poses is None else task.model.poses.corrected_c2w(given)
    before, after = pose_errors(given, true), pose_errors(refined, true)
    return {"pose_refine": refine, "perturbed": bool(perturbed), "iters": iters,
            "train_seconds": secs, "val_psnr": psnr, "val_images": len(val),
            "final_train_psnr": hist["psnr"][-1],
            "rot_err_deg_before": before[0], "trans_err_before": before[1],
            "rot_err_deg_after": after[0], "trans_err_after": after[1]}  # fmt: skip


def main():
    from warpnerf.cli.parser import split_command

    own, train_argv = split_command(sys.argv[1:])
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rot-deg", type=float, default=1.0)
    p.add_argument("--trans", type=float, default=0.02, help="in the scene's world units")
    p.add_argument("--iters", type=int, default=600)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", default=None)
    a = p.parse_args(own)
    if train_argv[:2] != ["train", "nerf"]:
        raise SystemExit("after --, give a `train nerf ...` command line")
    rows = []
    pert = (a.rot_deg, a.trans)
    for refine, perturbed in ((False, None), (False, pert), (True, pert)):
        r = one_run(train_argv, refine, perturbed, a.iters, a.seed)
        rows.append(r)
        print(json.dumps(r), flush=True)
    from warpnerf.bench import markdown_rows

    print(markdown_rows(rows, [
        ("poses", lambda r: "perturbed" if r["perturbed"] else "true"),
        ("refinement", lambda r: "on" if r["pose_refine"] else "off"),
        ("val PSNR", "{val_psnr:.2f}"),
        ("rotation error (deg)", "{rot_err_deg_before:.3f} -> {rot_err_deg_after:.3f}"),
        ("translation error", "{trans_err_before:.4f} -> {trans_err_after:.4f}"),
    ]))  # fmt: skip
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"rot_deg": a.rot_deg, "trans": a.trans, "argv": train_argv, "rows": rows},
                      f, indent=1)  # fmt: skip


if __name__ == "__main__":
    main()
