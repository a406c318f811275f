"""Cost of the index checks of the public ops (issue 15), measured in one process.

For each checked op, the median time of a call with its value checks (``check=True``, what a user
calling the public op gets) and without (``check=False``, what the library's own renderers use),
on inputs of a training step's size (``--rays`` rays, ``--samples`` samples per ray). The training
and rendering paths themselves are A/B-timed against the previous release by
the `overhead` phase of ``scripts/gpu.py``.

    python experiments/overheads/bounds_overhead.py --device cuda            # GPU figures
    python experiments/overheads/bounds_overhead.py --device cpu --quick     # smoke run on CPU
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch

from warpnerf.ops import generate_rays, render_packed
from warpnerf.ops.composite import packed_info_from_ray_indices
from warpnerf.ops.occupancy import grid_cell_points, live_samples, march_rays
from warpnerf.ops.rays import random_pixels
from warpnerf.ops.sampling import Samples


def _time(fn, dev, reps: int) -> float:
    """Median milliseconds of ``fn()`` over ``reps`` calls after 3 warm-up calls."""
    for _ in range(3):
        fn()
    ts = []
    for _ in range(reps):
        if dev.type == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        if dev.type == "cuda":
            torch.cuda.synchronize()
        ts.append(1e3 * (time.perf_counter() - t0))
    return statistics.median(ts)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--rays", type=int, default=4096)
    ap.add_argument("--samples", type=int, default=64, help="samples per ray")
    ap.add_argument("--reps", type=int, default=50)
    ap.add_argument("--quick", action="store_true", help="small sizes, few repetitions")
    ap.add_argument("--json", help="also write the figures here")
    a = ap.parse_args(argv)
    if a.quick:
        a.rays, a.samples, a.reps = 256, 16, 5
    dev = torch.device(a.device)
    g = torch.Generator(device="cpu").manual_seed(0)
    n_rays, n = a.rays, a.rays * a.samples

    # packed samples of a training step: every ray a random count, about --samples on average
    counts = torch.randint(0, 2 * a.samples, (n_rays,), generator=g)
    ri = torch.repeat_interleave(torch.arange(n_rays), counts).to(dev, torch.int32)
    n = ri.shape[0]
    t0 = torch.rand(n, generator=g).to(dev)
    ts, te = t0, t0 + 0.01
    sig = torch.rand(n, generator=g).to(dev) * 10
    rgb = torch.rand(n, 3, generator=g).to(dev)
    info = packed_info_from_ray_indices(ri, n_rays)

    def composite(check):
        return lambda: render_packed(ts, te, ri, sig, rgb, n_rays, packed_info=info, check=check)

    smp = Samples(ts, te, ri, info)

    def live(check):
        return lambda: live_samples(smp, sig, 1e-4, check=check)

    c2w = torch.eye(4).repeat(100, 1, 1).to(dev)
    c2w[:, 2, 3] = 4.0
    k = torch.tensor([400.0, 400.0, 200.0, 200.0]).repeat(100, 1).to(dev)
    cam, px, py, _ = random_pixels(100, 400, 400, n_rays, generator=g, device=dev)

    def rays(check):
        return lambda: generate_rays(c2w, k, cam_idx=cam, px=px, py=py, check=check)

    res = 128
    cells = torch.randint(0, res**3, (n_rays * 16,), generator=g).to(dev, torch.int32)
    jit = torch.rand(cells.shape[0], 3, generator=g).to(dev)

    def cellpts(check):
        box = [-1.5, -1.5, -1.5, 1.5, 1.5, 1.5]
        return lambda: grid_cell_points(cells, jit, res, box, check=check)

    rows = []
    for name, make in (
        ("render_packed", composite),
        ("live_samples", live),
        ("generate_rays", rays),
        ("grid_cell_points", cellpts),
    ):
        on, off = _time(make(True), dev, a.reps), _time(make(False), dev, a.reps)
        rows.append({"op": name, "checked_ms": on, "unchecked_ms": off, "ratio": on / off})

    # march_rays: its checks ride on the sync it needs anyway; timed as a reference only
    o, d = generate_rays(c2w[:1], k[:1], 400, 400)
    o, d = o[: n_rays * 4], d[: n_rays * 4]
    bits = torch.full((res**3 // 8,), 255, dtype=torch.uint8, device=dev)
    box = [-1.5, -1.5, -1.5, 1.5, 1.5, 1.5]
    ms = _time(lambda: march_rays(o, d, 2.0, 6.0, bits, res, box, 3**0.5 * 3 / 1024), dev, a.reps)
    rows.append({"op": "march_rays (checks always on)", "checked_ms": ms, "unchecked_ms": None})

    name = torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu"
    print(f"device {name}; {n_rays} rays, {n} packed samples; median of {a.reps} calls")
    print("| op | checked ms | unchecked ms | ratio |\n|---|---|---|---|")
    for r in rows:
        off = "-" if r["unchecked_ms"] is None else f"{r['unchecked_ms']:.3f}"
        ratio = f"{r['ratio']:.2f}" if "ratio" in r else "-"
        print(f"| {r['op']} | {r['checked_ms']:.3f} | {off} | {ratio} |")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump({"device": name, "rays": n_rays, "samples": n, "rows": rows}, fh, indent=1)


if __name__ == "__main__":
    main()
