"""Render time of one val image of a grid run against --round-samples and chunking (GPU; on the
CPU for a smoke test).

python3 scripts/render_profile.py RUN [--rounds 0,8,16,32,64]
"""

import argparse
import dataclasses
import json
import math
import time

import torch

from warpnerf.ops import generate_rays
from warpnerf.train.nerf import load_data, load_run, render_rays_of


def main():
    p = argparse.ArgumentParser()
    p.add_argument("run")
    p.add_argument("--rounds", default="0,4,8,16,32,64")
    a = p.parse_args()
    cfg, model, _ = load_run(a.run)
    ds = load_data(cfg, "val")
    o, d = generate_rays(ds.c2w[0], ds.intrinsics[0], ds.width, ds.height)
    gt = ds.images[0].reshape(-1, 3)
    counts = {"rounds": 0}
    import warpnerf.render as R

    orig = R.render_packed

    def counting(*x, **k):
        counts["rounds"] += 1
        return orig(*x, **k)

    R.render_packed = counting
    sync = torch.cuda.synchronize if cfg.device.startswith("cuda") else (lambda: None)
    for rs in [int(x) for x in a.rounds.split(",")]:
        cfg = dataclasses.replace(cfg, round_samples=rs).freeze()
        times = []
        with torch.no_grad():
            for _ in range(6):
                counts["rounds"] = 0
                sync()
                t0 = time.perf_counter()
                out = render_rays_of(model, cfg, o, d, chunk=1 << 20)
                sync()
                times.append(1e3 * (time.perf_counter() - t0))
        psnr = -10 * math.log10(float(((out["rgb"] - gt) ** 2).mean()))
        print(json.dumps({"round_samples": rs, "ms": sorted(times)[len(times) // 2],
                          "rounds": counts["rounds"], "psnr": psnr,
                          "n_marched": out["n_marched"], "n_kept": out["n_kept"]}))  # fmt: skip


if __name__ == "__main__":
    main()
