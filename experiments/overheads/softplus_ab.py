"""Issue 47: does the SDF network's softplus run faster as a Warp kernel than as torch's op? On
an H200 (2026-12-03, docs/design/training.md "Issue 47, ninth round") torch's softplus took 5.4
of a 400x400 hash_sdf frame's 20.6 ms of GPU time: 0.96 G values, under a third of the copy
bandwidth for one read and one write. This times, alternating in one process, for each row
count:

- the activation alone on [rows, 64] float32: torch's ``softplus(beta=100)`` against
  ``warpnerf.ops.softplus`` (kernels/activations.py), forward and forward + backward, with the
  share of the copy bandwidth each reaches (forward 8 B a value, backward 12 B more);
- hash_sdf's SDF network as a frame runs it (Linear 35 -> 64, softplus, Linear 64 -> 64,
  softplus, Linear 64 -> 16, TF32, no gradient) and as a training step does (forward +
  backward), with either softplus;

- the network's input [2 u - 1, features] (hash_sdf's default grid: 16 levels of 2 features):
  ``hash_encode`` then ``torch.cat`` against ``hash_encode(..., centred=True)``, one kernel
  (3.3 ms of the frame went to concatenations), forward and forward + backward (the table's
  gradient);

and the largest difference of the outputs (and gradients) between the two.

    python experiments/overheads/softplus_ab.py [--device cuda] [--rows 262144,1048576,7471104]
        [--json F]
"""

from __future__ import annotations

import argparse
import json
import statistics

import torch
import torch.nn.functional as F

from warpnerf.bench import _time, measure_copy_bandwidth  # median seconds (CUDA events)
from warpnerf.ops.activations import Softplus, activation_kernels
from warpnerf.ops.encoding import HashGrid, hash_encode

BETA = 100.0


def _alternate(fns: dict, dev, repeat: int) -> dict:
    """Median ms of each callable, timed in turns (5 rounds of ``repeat`` calls)."""
    for f in fns.values():
        f()
    ms = {k: [] for k in fns}
    for _ in range(5):
        for k, f in fns.items():
            ms[k].append(1e3 * _time(f, dev, repeat, warmup=1))
    return {k: statistics.median(v) for k, v in ms.items()}


def _network(dev):
    torch.manual_seed(0)
    return torch.nn.Sequential(
        torch.nn.Linear(35, 64), Softplus(BETA), torch.nn.Linear(64, 64), Softplus(BETA),
        torch.nn.Linear(64, 16),
    ).to(dev)  # fmt: skip


def measure(device: str, rows_list, repeat: int) -> dict:
    dev = torch.device(device)
    torch.backends.cuda.matmul.allow_tf32 = True  # (the GPU preset's --tf32)
    res = {"device": device, "repeat": repeat, "rows": {}}
    if dev.type == "cuda":
        res["gpu"] = torch.cuda.get_device_name(dev)
        res["copy_gbs"] = measure_copy_bandwidth(dev, 1 << 30) / 1e9
    net = _network(dev)
    grid = HashGrid()  # (hash_sdf's default: 16 levels of 2 features, 2^19 rows a level)
    table = (torch.rand(grid.n_rows, grid.n_features, device=dev) * 2e-2 - 1e-2).requires_grad_()
    for rows in rows_list:
        g = torch.Generator(device=dev).manual_seed(1)
        x = (torch.randn(rows, 64, device=dev, generator=g) * 0.05).requires_grad_(True)
        gy = torch.randn(rows, 64, device=dev, generator=g)

        def act(kind, backward, x=x, gy=gy):
            x.grad = None
            if kind == "warp":
                with activation_kernels("warp"):
                    y = Softplus(BETA)(x)
            else:
                y = F.softplus(x, BETA)
            if backward:
                y.backward(gy)
            return y

        y_t, y_w = act("torch", True), None
        gt = x.grad.clone()
        y_w = act("warp", True)
        err = {"out": (y_t - y_w).abs().max().item(), "grad": (gt - x.grad).abs().max().item()}
        del y_t, y_w, gt
        with torch.no_grad():
            t_fwd = _alternate({k: (lambda k=k: act(k, False)) for k in ("torch", "warp")}, dev,
                               repeat)  # fmt: skip
        t_both = _alternate({k: (lambda k=k: act(k, True)) for k in ("torch", "warp")}, dev,
                            repeat)  # fmt: skip
        inp = torch.randn(rows, 35, device=dev, generator=g)

        def net_run(kind, backward, inp=inp):
            for p in net.parameters():
                p.grad = None
            with activation_kernels(kind):
                if backward:
                    net(inp).sum().backward()
                else:
                    with torch.no_grad():
                        net(inp)

        n_fwd = _alternate({k: (lambda k=k: net_run(k, False)) for k in ("torch", "warp")}, dev,
                           repeat)  # fmt: skip
        n_both = _alternate({k: (lambda k=k: net_run(k, True)) for k in ("torch", "warp")}, dev,
                            repeat)  # fmt: skip
        u = torch.rand(rows, 3, device=dev, generator=g)
        gin = torch.randn(rows, 3 + grid.out_dim, device=dev, generator=g)

        def encode(kind, backward, u=u, gin=gin):
            table.grad = None
            with torch.set_grad_enabled(backward):
                if kind == "centred":
                    x = hash_encode(u, table, grid, centred=True)
                else:
                    x = torch.cat([2.0 * u - 1.0, hash_encode(u, table, grid)], -1)
                if backward:
                    x.backward(gin)
            return x

        x_c, x_k = encode("cat", True), None
        gk = table.grad.clone()
        x_k = encode("centred", True)
        err["input"] = (x_c - x_k).abs().max().item()
        err["input_grad"] = (gk - table.grad).abs().max().item()
        del x_c, x_k, gk
        e_fwd = _alternate({k: (lambda k=k: encode(k, False)) for k in ("cat", "centred")}, dev,
                           repeat)  # fmt: skip
        e_both = _alternate({k: (lambda k=k: encode(k, True)) for k in ("cat", "centred")}, dev,
                            repeat)  # fmt: skip
        row = {"act_fwd_ms": t_fwd, "act_fwd_bwd_ms": t_both, "net_fwd_ms": n_fwd,
               "net_fwd_bwd_ms": n_both, "input_fwd_ms": e_fwd, "input_fwd_bwd_ms": e_both,
               "max_abs_diff": err}  # fmt: skip
        if "copy_gbs" in res:
            vals = rows * 64
            row["act_fwd_pct_copy"] = {
                k: 100 * 8 * vals / (v * 1e-3) / 1e9 / res["copy_gbs"] for k, v in t_fwd.items()
            }
            row["act_fwd_bwd_pct_copy"] = {
                k: 100 * 20 * vals / (v * 1e-3) / 1e9 / res["copy_gbs"] for k, v in t_both.items()
            }
        res["rows"][rows] = row
        print(f"rows {rows}: softplus fwd torch {t_fwd['torch']:.3f} / warp {t_fwd['warp']:.3f} "
              f"ms, fwd+bwd {t_both['torch']:.3f} / {t_both['warp']:.3f}; SDF network fwd "
              f"{n_fwd['torch']:.3f} / {n_fwd['warp']:.3f}, fwd+bwd {n_both['torch']:.3f} / "
              f"{n_both['warp']:.3f}; input cat / centred fwd {e_fwd['cat']:.3f} / "
              f"{e_fwd['centred']:.3f}, fwd+bwd {e_both['cat']:.3f} / {e_both['centred']:.3f}; "
              f"max diff {err}", flush=True)  # fmt: skip
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--rows", default="262144,1048576,7471104",
                    help="row counts, comma-separated (7471104: a lego frame)")  # fmt: skip
    ap.add_argument("--repeat", type=int, default=10)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    rows = [int(r) for r in a.rows.split(",") if r.strip()]
    if not rows or min(rows) < 1:
        ap.error("--rows: positive integers, comma-separated")
    res = measure(a.device, rows, a.repeat)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(res, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
