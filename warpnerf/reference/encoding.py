"""Pure-PyTorch twins of the hash-grid encoding (same layout, same hash, autograd backward) and
of the colour input ``[features | SH(d)]``."""

from __future__ import annotations

import torch

from warpnerf.ops.encoding import spherical_harmonics  # pure torch: shared, not twinned

__all__ = ["hash_encode", "sh_concat"]

_MASK = 0xFFFFFFFF
_PRIMES = (1, 2654435761, 805459861)


def hash_encode(x, table, grid, centred=False):
    """x [n, 3] in [0, 1]^3, table [rows, F], grid: warpnerf.ops.HashGrid -> [n, L * F];
    ``centred``: [2 x - 1, features] ([n, 3 + L * F])."""
    if centred:
        return torch.cat([2.0 * x - 1.0, hash_encode(x, table, grid)], -1)
    xc = x.clamp(0.0, 1.0)
    bad = ~torch.isfinite(x).all(-1)
    outs = []
    for res, offset, rows in grid.levels:
        p = xc.nan_to_num(0.0) * res
        corner = p.floor().long().clamp(max=res - 1)
        frac = p - corner.to(x.dtype)
        acc = torch.zeros(x.shape[0], table.shape[1], dtype=x.dtype, device=x.device)
        for v in range(8):
            bits = torch.tensor([(v >> k) & 1 for k in range(3)], device=x.device)
            idx = corner + bits
            w = torch.where(bits.bool(), frac, 1.0 - frac).prod(-1)
            if (res + 1) ** 3 <= rows:
                row = idx[:, 0] + (res + 1) * (idx[:, 1] + (res + 1) * idx[:, 2])
            else:
                h = idx[:, 0] * _PRIMES[0]
                h = h ^ ((idx[:, 1] * _PRIMES[1]) & _MASK)
                h = h ^ ((idx[:, 2] * _PRIMES[2]) & _MASK)
                row = h % rows
            acc = acc + w.unsqueeze(-1) * table[offset + row]
        outs.append(acc)
    out = torch.cat(outs, -1)
    return torch.where(bad.unsqueeze(-1), torch.full_like(out, float("nan")), out)


def sh_concat(features, directions, degree=4):
    """Reference for :func:`warpnerf.ops.encoding.sh_concat`."""
    return torch.cat([features, spherical_harmonics(directions, degree)], -1)
