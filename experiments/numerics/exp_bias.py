"""Bias of float32 ``wp.exp`` on each device, against float64, for the small optical depths of a
nearly transparent ray (docs/NUMERICS.md: the one-thread-per-ray compositing backward multiplies
its running sum by exp(-tau) once per sample, so a bias adds up along the ray).

    python3 experiments/numerics/exp_bias.py            # cpu, and cuda when present

Prints, per device and decade of tau: the mean and max relative error of exp(-tau) in float32
units in the last place (2^-24), and the relative error of the product of 16384 factors
exp(-tau_i) (the running sum's decay over a 16384-sample ray) against float64.
"""

from __future__ import annotations

import json

import torch
import warp as wp


@wp.kernel
def _exp_neg(x: wp.array(dtype=wp.float32), y: wp.array(dtype=wp.float32)):
    i = wp.tid()
    y[i] = wp.exp(-x[i])


@wp.kernel
def _exp_prod(x: wp.array2d(dtype=wp.float32), y: wp.array(dtype=wp.float32)):
    r = wp.tid()
    p = float(1.0)  # noqa: UP018 (a loop-carried Warp variable needs the typed constructor)
    for k in range(x.shape[1]):
        p = p * wp.exp(-x[r, k])
    y[r] = p


def measure(device: str) -> list:
    g = torch.Generator().manual_seed(0)
    rows = []
    ulp = 2.0**-24
    for lo in range(-8, 0):  # the product of 16384 underflows from 1e-2 on
        x = (10.0 ** (lo + torch.rand(1 << 20, generator=g, dtype=torch.float64))).float()
        xd, yd = x.to(device), torch.empty(x.shape[0], device=device)
        wp.launch(_exp_neg, x.shape[0], [wp.from_torch(xd), wp.from_torch(yd)], device=device)
        ref = torch.exp(-x.double())
        rel = (yd.cpu().double() - ref) / ref / ulp
        # 64 rays of 16384 factors each with tau in this decade
        n = 16384
        xs = (10.0 ** (lo + torch.rand(64, n, generator=g, dtype=torch.float64))).float()
        ps = torch.empty(64, device=device)
        wp.launch(_exp_prod, 64, [wp.from_torch(xs.to(device)), wp.from_torch(ps)], device=device)
        pref = torch.exp(-xs.double().sum(1))
        prel = (ps.cpu().double() - pref) / pref
        if float(pref.min()) < 1e-30:  # the product underflows float32: no relative error
            prel = torch.full_like(prel, float("nan"))
        rows.append({"device": device, "tau_decade": f"1e{lo}..1e{lo + 1}",
                     "mean_rel_ulp": float(rel.mean()), "max_abs_rel_ulp": float(rel.abs().max()),
                     "product_16384_rel_err_mean": float(prel.mean()),
                     "product_16384_rel_err_max": float(prel.abs().max())})  # fmt: skip
    return rows


def main() -> None:
    wp.init()
    devices = (["cpu"] if wp.is_cpu_available() else []) + (
        ["cuda"] if torch.cuda.is_available() else []
    )
    rows = [r for d in devices for r in measure(d)]
    print(
        "| device | tau | mean rel err (ulp) | max rel err (ulp) | product of 16384: mean / max |"
    )
    print("|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['device']} | {r['tau_decade']} | {r['mean_rel_ulp']:+.3f} "
            f"| {r['max_abs_rel_ulp']:.2f} | {r['product_16384_rel_err_mean']:+.1e} "
            f"/ {r['product_16384_rel_err_max']:.1e} |"
        )
    print(json.dumps(rows))


if __name__ == "__main__":
    main()
