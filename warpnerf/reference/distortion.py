"""Pure-PyTorch twin of warpnerf.ops.distortion: the distortion loss as its definition, the double
sum over every pair of a ray's samples (O(n^2) per ray), with autograd's backward."""

from __future__ import annotations

import torch

from warpnerf.ops.composite import packed_info_from_ray_indices

__all__ = ["distortion_loss"]


def distortion_loss(s_starts, s_ends, ray_indices, weights, n_rays, *, packed_info=None):
    """Reference for :func:`warpnerf.ops.distortion.distortion_loss`: per ray,
    ``sum_ij w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 (s_end_i - s_start_i)``."""
    if packed_info is None:
        packed_info = packed_info_from_ray_indices(ray_indices, n_rays)
    out = []
    for start, count in packed_info.tolist():
        sl = slice(start, start + count)
        w, s0, s1 = weights[sl], s_starts[sl], s_ends[sl]
        m = 0.5 * (s0 + s1)
        pairs = (w[:, None] * w[None, :] * (m[:, None] - m[None, :]).abs()).sum()
        out.append(pairs + (w * w * (s1 - s0)).sum() / 3.0)
    if not out:
        return weights.new_zeros(0)
    return torch.stack(out)
