"""Host cost of a kernel launch through warpnerf's bridge (issue 18: the training step is
host-bound): the ops at tiny sizes, where the host work (checks, Warp array views, argument
packing, launch) is nearly all of a call, and a tiny hash-field training step, with the bridge's
array descriptors (``from_torch(..., return_ctype=True)`` + cached generic overloads, the
default) against ``wp.array`` views (the bridge before), alternating in one process.

    python experiments/launch_overhead.py [--device cpu|cuda] [--repeats 5] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

import torch


def _old_bridge(on: bool):
    """Swaps the bridge's ``arr`` and ``_overload`` for the wp.array versions (``on``) or back."""
    from warpnerf.ops import bridge as _bridge

    if not hasattr(_bridge, "_new"):
        _bridge._new = (_bridge.arr, _bridge._overload)

        def arr_wp(t, dtype=None):
            return _bridge.load_warp().from_torch(t.contiguous(), dtype=dtype, requires_grad=False)

        _bridge._old = (arr_wp, lambda kernel, inputs: kernel)
    _bridge.arr, _bridge._overload = _bridge._old if on else _bridge._new


def _cases(dev):
    import warpnerf as wn
    from warpnerf.ops.encoding import HashGrid, hash_encode

    g = torch.Generator().manual_seed(0)
    n, s = 16, 8
    o = torch.zeros(n, 3, device=dev)
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1).to(dev)
    smp = wn.stratified_samples(torch.full((n,), 2.0, device=dev), torch.full((n,), 6.0,
                                device=dev), s, packed=True)  # fmt: skip
    m = smp.t_starts.shape[0]
    sig = torch.rand(m, generator=g).to(dev).requires_grad_()
    rgb = torch.rand(m, 3, generator=g).to(dev).requires_grad_()
    grid = HashGrid(n_levels=4, log2_size=10, base_res=4, max_res=32)
    table = torch.zeros(grid.n_rows, grid.n_features, device=dev).requires_grad_()
    x = torch.rand(n, 3, generator=g).to(dev)

    def composite():
        c, _, _ = wn.render_packed(smp.t_starts, smp.t_ends, smp.ray_indices, sig, rgb, n_rays=n,
                                   packed_info=smp.packed_info)  # fmt: skip
        c.sum().backward()

    def rays():
        wn.ray_aabb_intersect(o, d, [-1, -1, -1, 1, 1, 1])

    def encode():
        hash_encode(x, table, grid).sum().backward()

    step = _train_step(dev)
    return {"composite fwd+bwd": composite, "ray_aabb_intersect": rays, "hash fwd+bwd": encode,
            "hash-field training step (64 rays)": step}  # fmt: skip


def _train_step(dev):
    """One step of a tiny hash-field NeRF task on the built-in scene (grid marching, MLPs,
    compositing, Adam): the whole step's host work with little device work."""
    from warpnerf.cli.parser import build_parser
    from warpnerf.cli.train import nerf_config_from_args
    from warpnerf.train.nerf import NeRFTask, build_model, load_data, resolve_data

    args = build_parser().parse_args([
        "train", "nerf", "--data", "builtin", "--field", "hash", "--hash-levels", "4",
        "--hash-log2-size", "10", "--hash-max-res", "32", "--grid-res", "16", "--batch", "64",
        "--builtin-size", "16", "--hidden", "16", "--device", dev, "--out", "/tmp/_unused",
    ])  # fmt: skip
    cfg = nerf_config_from_args(args).validate()
    resolve_data(cfg)
    task = NeRFTask(cfg, build_model(cfg), load_data(cfg, "train"), None, log=lambda *a: None)
    opt = task.optimizer(task.parameters(), 1e-2)
    for i in range(300):  # past the grid's warm-up
        loss, _ = task.loss(i)
        opt.zero_grad()
        loss.backward()
        opt.step()

    def step():  # step index 1: no grid update (every 16 steps), so every timed step is alike
        loss, _ = task.loss(1)
        opt.zero_grad()
        loss.backward()
        opt.step()
        float(loss.detach())

    return step


def _time(fn, dev, n=100) -> float:
    for _ in range(20):
        fn()
    sync = torch.cuda.synchronize if dev.startswith("cuda") else (lambda: None)
    sync()
    t = time.perf_counter()
    for _ in range(n):
        fn()
    sync()
    return 1e6 * (time.perf_counter() - t) / n


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--json", default=None)
    a = p.parse_args()
    cases = _cases(a.device)
    rows = {k: {"descriptors": [], "wp.array": []} for k in cases}
    for r in range(a.repeats):
        for mode in ("descriptors", "wp.array") if r % 2 == 0 else ("wp.array", "descriptors"):
            _old_bridge(mode == "wp.array")
            for k, fn in cases.items():
                rows[k][mode].append(_time(fn, a.device))
    _old_bridge(False)
    print(f"| op (16 rays) on {a.device} | descriptors us/call | wp.array us/call | saved |")
    print("|---|---|---|---|")
    out = {}
    for k, v in rows.items():
        new, old = statistics.median(v["descriptors"]), statistics.median(v["wp.array"])
        out[k] = {"descriptors_us": new, "wp_array_us": old, "all": v}
        saved = f"{old - new:+.1f} us ({100 * (1 - new / old):.0f} %)"
        print(f"| {k} | {new:.1f} | {old:.1f} | {saved} |")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
