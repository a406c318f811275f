"""Torch bridge for the distortion loss (kernels/distortion.py; the maths is documented there).
``warpnerf.reference.distortion`` is the readable pure-PyTorch twin with the same signature."""

from __future__ import annotations

import torch

from . import bridge
from .composite import check_packed_info, packed_info_from_ray_indices

__all__ = ["distortion_loss"]


class _Distortion(torch.autograd.Function):
    @staticmethod
    def forward(ctx, packed_info, s_starts, s_ends, weights):
        from warpnerf.kernels import distortion as K

        n_rays = packed_info.shape[0]
        out = torch.empty(n_rays, device=weights.device, dtype=weights.dtype)
        a = bridge.arr
        bridge.launch(K.distortion_fwd, n_rays,
                       [a(packed_info), a(s_starts), a(s_ends), a(weights), a(out)],
                       weights.device)  # fmt: skip
        ctx.save_for_backward(packed_info, s_starts, s_ends, weights)
        return out

    @staticmethod
    def backward(ctx, v_loss):
        from warpnerf.kernels import distortion as K

        packed_info, s_starts, s_ends, weights = ctx.saved_tensors
        v_weights = torch.zeros_like(weights)  # (samples of no ray keep a zero gradient)
        a = bridge.arr
        bridge.launch(K.distortion_bwd, packed_info.shape[0],
                       [a(packed_info), a(s_starts), a(s_ends), a(weights),
                        a(v_loss.contiguous()), a(v_weights)], weights.device)  # fmt: skip
        return None, None, None, v_weights


def distortion_loss(
    s_starts: torch.Tensor,  # [n] interval starts in a normalised ray coordinate
    s_ends: torch.Tensor,  # [n]
    ray_indices: torch.Tensor,  # [n] sorted, int
    weights: torch.Tensor,  # [n] compositing weights (render_packed(..., return_weights=True))
    n_rays: int,
    *,
    packed_info: torch.Tensor | None = None,  # [n_rays, 2] int32, computed if None
    check: bool = True,
) -> torch.Tensor:
    """mip-NeRF 360's distortion loss of each ray, ``[n_rays]``:
    ``sum_ij w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 (s_end_i - s_start_i)`` with m_i the
    intervals' midpoints, computed in O(n) per ray (exclusive prefix sums) by a Warp kernel with
    a hand-written backward. Differentiable with respect to ``weights`` only.

    A ray's samples must be in increasing order of s (as marched or sampled; their midpoints
    non-decreasing: the O(n) form relies on it), each with s_end >= s_start (a backwards
    interval would subtract). ``check=True`` verifies both and the index layout
    (``ray_indices`` sorted in [0, n_rays), ``packed_info`` their exact layout), one host sync on
    CUDA; ``check=False`` is for the library's own marched samples. Rays with no samples get 0;
    a NaN or Inf input makes its ray's loss NaN/Inf.
    """
    n_rays = bridge.check_int("n_rays", n_rays)
    n = weights.shape[0] if weights.dim() == 1 else -1
    dev, dt = weights.device, weights.dtype
    bridge.check_float("weights", weights, (None,))
    for name, t in (("s_starts", s_starts), ("s_ends", s_ends)):
        bridge.check_float(name, t, (n,), dt, dev)
    if n > bridge.INT32_MAX:
        raise ValueError(f"{n} samples exceed int32 offsets")
    bridge.check_index("ray_indices", ray_indices, (n,))
    ri = ray_indices.to(dev)
    if packed_info is None:
        packed_info = packed_info_from_ray_indices(ri, n_rays)
    else:
        bridge.check_index("packed_info", packed_info, (n_rays, 2))
        packed_info = packed_info.to(dev)
        if check:
            check_packed_info(packed_info, ri, n, n_rays)
    if check and n:
        m = s_starts + s_ends
        same_ray = ri[1:] == ri[:-1]
        ordered, forward = bridge.host_flags(
            (~same_ray | ~(m[1:] < m[:-1])).all(), ~(s_ends < s_starts).any()
        )
        if not forward:
            raise ValueError("every interval needs s_end >= s_start")
        if not ordered:
            raise ValueError("each ray's samples must be in increasing order of s")
    return _Distortion.apply(
        packed_info.to(dev, torch.int32).contiguous(),
        s_starts.contiguous(),
        s_ends.contiguous(),
        weights.contiguous(),
    )
