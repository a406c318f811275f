"""Where a grid run's frame spends its field evaluations, counted (device-independent): for the
first ``--images`` val views, the samples one round marches (``render_marched``'s rounds path
with ``round_samples=0``), those before compositing stops at T < t_threshold, and those whose
weight reaches the colour threshold of the rule before 2026-12-03, ``COLOR_WEIGHT_EPS`` (the
samples the colour head, and a surface field's normal, was evaluated on; since then the rounds
path colours fewer, ``render_marched``'s ``RENDER_COLOR_EPS``, whose count is its own
``n_colored``, as ``scripts/bench_frame.py`` reports). Counts, not times: run it on a CPU with
a small run.

python3 experiments/surfaces/frame_sample_counts.py RUN [--images 2] [--device cpu]
"""

from __future__ import annotations

import argparse
import json

import torch

from warpnerf.field_protocol import density as field_density
from warpnerf.ops import render_packed
from warpnerf.ops.occupancy import live_samples
from warpnerf.ops.tracer import COLOR_WEIGHT_EPS
from warpnerf.train.nerf import dataset_rays, load_data, load_run, with_refined_poses


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run")
    p.add_argument("--images", type=int, default=2)
    p.add_argument("--device", default="cpu")
    a = p.parse_args()
    cfg, model, _ = load_run(a.run, a.device)
    ds = with_refined_poses(model, load_data(cfg, "val"), "val")
    tot = {"rays": 0, "marched": 0, "live": 0, "colored": 0}
    with torch.no_grad():
        for i in range(min(a.images, ds.images.shape[0])):
            o, d = dataset_rays(cfg, ds, image=i)
            smp, _ = model.grid.march(o, d, cfg.near, cfg.far, max_samples=cfg.max_samples)
            ri = smp.ray_indices
            pos = o[ri] + d[ri] * smp.midpoints().unsqueeze(-1)
            sig = field_density(model.coarse, pos, d[ri])[0]
            keep, _ = live_samples(smp, sig, cfg.t_threshold, check=False)
            zero = sig.new_zeros(1, 3).expand(sig.shape[0], 3)
            w = render_packed(smp.t_starts, smp.t_ends, ri, sig, zero, o.shape[0],
                              packed_info=smp.packed_info, return_weights=True,
                              check=False)[3]  # fmt: skip
            tot["rays"] += o.shape[0]
            tot["marched"] += smp.t_starts.shape[0]
            tot["live"] += int(keep.sum())
            tot["colored"] += int((w >= COLOR_WEIGHT_EPS).sum())
    per_ray = {k: v / tot["rays"] for k, v in tot.items() if k != "rays"}
    print(json.dumps({"run": a.run, "totals": tot, "per_ray": per_ray}, indent=1))


if __name__ == "__main__":
    main()
