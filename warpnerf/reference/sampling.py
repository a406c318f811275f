"""Pure-PyTorch twin of warpnerf.ops.sampling (same maths; its jitter comes from torch's RNG)."""

from __future__ import annotations

import torch

from warpnerf.ops.sampling import Samples

__all__ = ["stratified_samples"]


def stratified_samples(near, far, n_samples, *, perturb=False, seed=0, packed=False):
    """Reference for :func:`warpnerf.stratified_samples`."""
    n_rays = near.shape[0]
    hi = torch.maximum(far, near)
    step = ((hi - near) / n_samples).unsqueeze(-1)
    k = torch.arange(1, n_samples, dtype=near.dtype, device=near.device)
    u = torch.full((n_rays, n_samples - 1), 0.5, dtype=near.dtype, device=near.device)
    if perturb:
        g = torch.Generator(device="cpu").manual_seed(seed)
        u = torch.rand(u.shape, generator=g, dtype=near.dtype).to(near.device)
    inner = near.unsqueeze(-1) + (k + u - 0.5) * step
    edges = torch.cat([near.unsqueeze(-1), inner, hi.unsqueeze(-1)], -1)
    t_starts, t_ends = edges[:, :-1], edges[:, 1:]
    if not packed:
        return Samples(t_starts, t_ends)
    keep = far > near
    counts = torch.where(keep, n_samples, 0)
    starts = torch.cumsum(counts, 0) - counts
    ray_indices = torch.arange(n_rays, device=near.device).repeat_interleave(counts)
    return Samples(
        t_starts[keep].reshape(-1),
        t_ends[keep].reshape(-1),
        ray_indices,
        torch.stack([starts, counts], -1).to(torch.int32),
    )
