"""Demo 02: recover a box's center and side lengths from images by gradient descent.

Without --data: renders its own ground truth (a known rainbow box from 24 cameras), fits a box
started at the origin with unit sides, and checks the recovery (center and sides within 0.02).
With --data DIR: reads a Blender-format folder (transforms.json or transforms_train.json, images
alpha-composited on black) and fits the rainbow box to it: rays through pixel centres, unit
directions, --near/--far (default 0 and 5), 64 samples per ray, random batches of 4096 rays, MSE,
Adam. The last line printed is JSON: {"center": [...], "side_lengths": [...], "final_loss": ...}.

    python demos/02_fit_box.py --out out/02                 # built-in scene
    python demos/02_fit_box.py --data path/to/scene --out out/02
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from warpnerf.box_demo import CAMERA_RADIUS, FOV_X, GT_BOX
from warpnerf.data import intrinsics_from_fov, orbit_views
from warpnerf.errors import exit_status
from warpnerf.fields import SDFVolume
from warpnerf.outputs import write_image, write_json
from warpnerf.train import BoxFitConfig, fit_box, render_box_views
from warpnerf.train.box_fit import run_box_fit_on_folder


def fit_builtin(cfg: BoxFitConfig, out: Path, device: str, views: int, size: int) -> dict:
    gt = SDFVolume("box", **GT_BOX, beta=cfg.beta).to(device)
    cams = orbit_views(views, radius=CAMERA_RADIUS).to(device)
    k = intrinsics_from_fov(size, size, FOV_X).to(device).expand(views, 4)
    images, _ = render_box_views(gt, cams, k, size, size, cfg)
    fit = fit_box(images, cams, k, cfg, progress=True)
    volume = fit.pop("volume")
    fitted, _ = render_box_views(volume, cams[:1], k[:1], size, size, cfg)
    write_image(out / "gt_vs_fit.png", torch.cat([images[0], fitted[0]], 1))
    err_c = max(abs(a - b) for a, b in zip(fit["center"], GT_BOX["center"]))
    err_s = max(abs(a - b) for a, b in zip(fit["side_lengths"], GT_BOX["side_lengths"]))
    res = {k_: fit[k_] for k_ in ("center", "side_lengths", "final_loss")}
    res |= {
        "center_max_abs_error": err_c,
        "side_max_abs_error": err_s,
        "recovered_within_0.02": bool(err_c <= 0.02 and err_s <= 0.02),
        "seconds": round(fit["seconds"], 2),
    }
    write_json(out / "result.json", res | {"losses": fit["losses"]})
    return res


def main(argv=None) -> int:
    """Runs the demo; a user error or a refusal of the machine: one line on stderr, status 2."""
    return exit_status("02_fit_box", _main, argv)


def _main(argv) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default=None, help="Blender-format folder (default: built-in scene)")
    p.add_argument("--out", default="out/02_fit_box")
    p.add_argument("--device", default="cpu")
    p.add_argument("--iters", type=int, default=300)
    p.add_argument("--batch", type=int, default=4096)
    p.add_argument("--samples", type=int, default=64)
    p.add_argument("--near", type=float, default=0.0)
    p.add_argument("--far", type=float, default=5.0)
    p.add_argument("--lr", type=float, default=0.02)
    p.add_argument("--views", type=int, default=24, help="built-in scene: training views")
    p.add_argument("--size", type=int, default=64, help="built-in scene: image size")
    p.add_argument("--frames", type=int, default=40, help="--data: spiral video frames (0: none)")
    args = p.parse_args(argv)
    if min(args.iters, args.batch, args.samples, args.views, args.size) < 1:
        p.error("--iters, --batch, --samples, --views and --size must be positive")
    if not args.far > args.near:
        p.error(f"--far ({args.far}) must be greater than --near ({args.near})")
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        p.error("--device cuda: no CUDA device available")
    if Path(args.out).exists() and not Path(args.out).is_dir():
        p.error(f"--out {args.out} is a file")
    cfg = BoxFitConfig(
        iters=args.iters,
        batch=args.batch,
        n_samples=args.samples,
        near=args.near,
        far=args.far,
        lr=args.lr,
    )
    out = Path(args.out)  # created by the writers, only once the data has loaded
    if args.data:
        res = run_box_fit_on_folder(
            args.data, out, cfg, args.device, frames=args.frames, progress=True
        )
    else:
        res = fit_builtin(cfg, out, args.device, args.views, args.size)
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
