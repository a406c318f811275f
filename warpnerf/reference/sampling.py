"""Pure-PyTorch twin of warpnerf.ops.sampling (same maths; its jitter comes from torch's RNG)."""

from __future__ import annotations

import torch

from warpnerf.ops.sampling import PDF_PADDING, Samples

__all__ = ["stratified_samples", "importance_samples"]


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


def importance_samples(samples, weights, n_fine, *, perturb=False, seed=0):
    """Reference for :func:`warpnerf.ops.sampling.importance_samples` (no input checks).

    Packed rays are grouped by their number of coarse intervals and sampled densely.
    """
    if samples.packed_info is None:
        return _importance_dense(samples.t_starts, samples.t_ends, weights, n_fine, perturb, seed)
    starts, counts = samples.packed_info[:, 0].long(), samples.packed_info[:, 1].long()
    out_counts = torch.where(counts > 0, counts + n_fine, 0)
    out_starts = torch.cumsum(out_counts, 0) - out_counts
    n_out = int(out_counts.sum())
    t_starts = samples.t_starts.new_empty(n_out)
    t_ends = samples.t_ends.new_empty(n_out)
    for c in counts.unique().tolist():
        if c == 0:
            continue
        rays = torch.nonzero(counts == c).squeeze(1)
        src = starts[rays, None] + torch.arange(c, device=rays.device)  # [n_sel, c]
        fine = _importance_dense(
            samples.t_starts[src], samples.t_ends[src], weights[src], n_fine, perturb, seed
        )
        dst = out_starts[rays, None] + torch.arange(c + n_fine, device=rays.device)
        t_starts[dst], t_ends[dst] = fine.t_starts, fine.t_ends
    ray_indices = torch.arange(counts.shape[0], device=counts.device).repeat_interleave(out_counts)
    info = torch.stack([out_starts, out_counts], -1).to(torch.int32)
    return Samples(t_starts, t_ends, ray_indices, info)


def _importance_dense(t_starts, t_ends, weights, n_fine, perturb, seed):
    """Dense rays [n_rays, n_c]: inverse-CDF positions, then a sort merges them with the edges."""
    n_rays, n_c = t_starts.shape
    dtype, device = t_starts.dtype, t_starts.device
    weights = weights.detach()
    edges = torch.cat([t_starts[:, :1], t_ends], -1)  # [n_rays, n_c + 1]
    near = edges[:, :1]
    length = edges[:, -1:] - near
    # Mass per interval: the weight plus a constant padding density eps * n_c / L.
    scale = torch.tensor(PDF_PADDING, dtype=dtype, device=device) * n_c / length
    mass = weights + scale * (t_ends - t_starts)  # [n_rays, n_c]
    cdf = torch.cumsum(mass, -1)  # C_1 .. C_nc (unnormalised)
    cdf = torch.cat([torch.zeros_like(cdf[:, :1]), cdf], -1)  # C_0 .. C_nc
    u = torch.full((n_rays, n_fine), 0.5, dtype=dtype, device=device)
    if perturb:
        g = torch.Generator(device="cpu").manual_seed(seed)
        u = torch.rand(u.shape, generator=g, dtype=dtype).to(device)
    j = torch.arange(n_fine, dtype=dtype, device=device)
    v = (j + u) / n_fine * cdf[:, -1:]  # [n_rays, n_fine], sorted
    # Interval i: the last one (i <= n_c - 1) whose running mass C_i is <= v.
    i = torch.searchsorted(cdf[:, :-1].contiguous(), v.contiguous(), right=True) - 1
    m = mass.gather(1, i)
    frac = torch.where(m > 0, (v - cdf.gather(1, i)) / m, 0.0).clamp(0.0, 1.0)
    e0, e1 = edges.gather(1, i), edges.gather(1, i + 1)
    t = torch.minimum(e0 + frac * (e1 - e0), e1)
    t = torch.where(length > 0, t, near)  # a zero-length ray: everything at near
    merged = torch.sort(torch.cat([edges, t], -1), dim=-1).values  # [n_rays, n_c + n_fine + 1]
    return Samples(merged[:, :-1], merged[:, 1:])
