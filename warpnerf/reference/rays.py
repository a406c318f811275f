"""Pure-PyTorch twins of warpnerf.ops.rays (same names and signatures)."""

from __future__ import annotations

import torch

__all__ = ["generate_rays", "ray_aabb_intersect"]


def generate_rays(
    c2w, intrinsics, width=None, height=None, *, cam_idx=None, px=None, py=None, normalize=True
):
    """Reference for :func:`warpnerf.generate_rays`."""
    if c2w.dim() == 2:
        c2w = c2w.unsqueeze(0)
    if intrinsics.dim() == 1:
        intrinsics = intrinsics.unsqueeze(0)
    dt, dev = c2w.dtype, c2w.device
    if cam_idx is None:
        n_cams = c2w.shape[0]
        ys, xs = torch.meshgrid(
            torch.arange(height, dtype=dt, device=dev),
            torch.arange(width, dtype=dt, device=dev),
            indexing="ij",
        )
        cam_idx = torch.arange(n_cams, device=dev).repeat_interleave(width * height)
        px = (xs.reshape(-1) + 0.5).repeat(n_cams)
        py = (ys.reshape(-1) + 0.5).repeat(n_cams)
    k = intrinsics[cam_idx]
    d_cam = torch.stack(
        [
            (px.to(dt) - k[:, 2]) / k[:, 0],
            -(py.to(dt) - k[:, 3]) / k[:, 1],
            -torch.ones_like(k[:, 0]),
        ],
        -1,
    )
    m = c2w[cam_idx]
    directions = (m[:, :3, :3] @ d_cam.unsqueeze(-1)).squeeze(-1)
    if normalize:
        directions = directions / directions.norm(dim=-1, keepdim=True)
    return m[:, :3, 3].clone(), directions


def ray_aabb_intersect(origins, directions, aabb, t_min=0.0):
    """Reference for :func:`warpnerf.ray_aabb_intersect` (slab test, zero components exact)."""
    box = torch.as_tensor(aabb, dtype=origins.dtype, device=origins.device).reshape(2, 3)
    zero = directions == 0
    safe = torch.where(zero, torch.ones_like(directions), directions)
    t1 = (box[0] - origins) / safe
    t2 = (box[1] - origins) / safe
    inside = (origins >= box[0]) & (origins <= box[1])
    inf = torch.full_like(t1, float("inf"))
    lo = torch.where(zero, -inf, torch.minimum(t1, t2)).amax(-1).clamp_min(t_min)
    hi = torch.where(zero, inf, torch.maximum(t1, t2)).amin(-1)
    hit = (lo <= hi) & (inside | ~zero).all(-1)
    # A NaN anywhere: a miss with NaN bounds, never a plausible interval.
    bad = origins.isnan().any(-1) | directions.isnan().any(-1)
    hit = hit & ~bad
    miss = torch.where(bad, torch.full_like(lo, float("nan")), torch.full_like(lo, t_min))
    return torch.where(hit, lo, miss), torch.where(hit, hi, miss), hit
