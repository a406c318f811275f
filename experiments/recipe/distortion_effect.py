"""What the distortion loss (``--distortion-loss W``, issue 20) does to a run: the same training
with several weights, each scored on the val images (PSNR) and on how spread out the rendered
weight of its val rays is (the mean distortion loss of every val pixel's ray, with the run's
own coordinate; lower: the weight sits in a shorter stretch of the ray), plus the training
time. A CPU-sized default (the built-in scene); pass a capture's flags for the real question.

    python3 experiments/recipe/distortion_effect.py [--weights 0,0.01,0.1] [--json out.json] -- \
        train nerf --data builtin --field hash --iters 600 ...
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path


def val_distortion(run) -> float:
    """Mean distortion loss of the val images' rays under the run's final model."""
    import torch

    from warpnerf.render import render_marched
    from warpnerf.train.nerf import dataset_rays, distortion_coordinate, load_data, load_run

    cfg, model, _ = load_run(run)
    val = load_data(cfg, "val")
    total, count = 0.0, 0
    for i in range(val.images.shape[0]):
        o, d = dataset_rays(cfg, val, image=i)
        for s in range(0, o.shape[0], 1 << 14):
            sl = slice(s, s + (1 << 14))
            with torch.enable_grad():
                out = render_marched(model.grid, model.coarse, o[sl], d[sl], cfg.near, cfg.far,
                                     background=cfg.background, t_threshold=cfg.t_threshold,
                                     max_samples=cfg.max_samples,
                                     distortion_s=distortion_coordinate(cfg))  # fmt: skip
            total += float(out["distortion"].detach().sum())
            count += o[sl].shape[0]
    return total / max(count, 1)


def main():
    from warpnerf.cli.parser import split_command

    own, argv = split_command(sys.argv[1:])
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--weights", default="0,0.01,0.1")
    p.add_argument("--json", default=None)
    a = p.parse_args(own)
    weights = [float(w) for w in a.weights.split(",")]

    from warpnerf.cli.parser import main as cli
    from warpnerf.train.nerf_eval import evaluate_run

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for w in weights:
            run = Path(tmp) / f"w{w:g}"
            extra = ["--distortion-loss", str(w)] if w else []
            t = time.perf_counter()
            rc = cli(argv + extra + ["--out", str(run), "--quiet", "--no-tensorboard"])
            if rc != 0:
                raise SystemExit(f"training with --distortion-loss {w} failed ({rc})")
            train_s = time.perf_counter() - t
            m = evaluate_run(run, "val", out_dir=Path(tmp) / f"eval{w:g}")
            spread = val_distortion(run)
            rows.append({"weight": w, "val_psnr": m["psnr"], "val_ssim": m["ssim"],
                         "val_distortion": spread, "train_wall_s": train_s})  # fmt: skip
            print(json.dumps(rows[-1]), flush=True)
    from warpnerf.bench import markdown_rows

    print(markdown_rows(rows, [
        ("--distortion-loss", "{weight:g}"), ("val PSNR", "{val_psnr:.2f}"),
        ("val SSIM", "{val_ssim:.4f}"), ("val rays' distortion", "{val_distortion:.5f}"),
        ("wall s", "{train_wall_s:.0f}"),
    ]))  # fmt: skip
    if a.json:
        from warpnerf.outputs import write_json

        write_json(a.json, {"argv": argv, "rows": rows})


if __name__ == "__main__":
    main()
