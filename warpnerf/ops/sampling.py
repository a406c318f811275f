"""Torch bridge for stratified sampling (kernels/sampling.py). No gradients."""

from __future__ import annotations

from typing import NamedTuple

import torch

from . import _bridge

__all__ = ["stratified_samples", "Samples"]


class Samples(NamedTuple):
    """Intervals along rays. Dense: t_starts/t_ends [n_rays, n_samples], ray_indices and
    packed_info None. Packed: t_starts/t_ends/ray_indices [n], packed_info [n_rays, 2] int32."""

    t_starts: torch.Tensor
    t_ends: torch.Tensor
    ray_indices: torch.Tensor | None = None
    packed_info: torch.Tensor | None = None

    def midpoints(self) -> torch.Tensor:
        return 0.5 * (self.t_starts + self.t_ends)


def stratified_samples(
    near: torch.Tensor,  # [n_rays]
    far: torch.Tensor,  # [n_rays]
    n_samples: int,
    *,
    perturb: bool = False,
    seed: int = 0,
    packed: bool = False,
) -> Samples:
    """Stratified intervals partitioning [near, far] on every ray.

    Evaluation (perturb=False): n equal bins, fields evaluated at bin midpoints. Training
    (perturb=True): interior bin edges jittered uniformly by up to half a bin (Warp RNG keyed by
    ``seed`` and ray index; pass a new seed every step). Packed: rays with far <= near get no
    samples.
    Non-finite near/far raise ValueError (they would otherwise yield plausible-looking samples).
    """
    from warpnerf.kernels import sampling as K

    _bridge.check_float("near", near, (None,))
    n_rays, dev, dt = near.shape[0], near.device, near.dtype
    _bridge.check_float("far", far, (n_rays,), dt, dev)
    if n_samples < 1:
        raise ValueError(f"n_samples must be >= 1, got {n_samples}")
    if n_rays and not bool(torch.isfinite(near).all() & torch.isfinite(far).all()):
        raise ValueError("near and far must be finite (a NaN/Inf bound would hide a bad ray)")
    if packed:
        counts = torch.where(far > near, n_samples, 0).to(torch.int64)
        starts = torch.cumsum(counts, 0) - counts
        packed_info = torch.stack([starts, counts], -1).to(torch.int32)
        n = int(counts.sum())
        ray_indices = torch.empty(n, device=dev, dtype=torch.int64)
    else:
        n = n_rays * n_samples
        packed_info = torch.empty(0, 2, device=dev, dtype=torch.int32)
        ray_indices = torch.empty(0, device=dev, dtype=torch.int64)
    t_starts = torch.empty(n, device=dev, dtype=dt)
    t_ends = torch.empty(n, device=dev, dtype=dt)
    a = _bridge.arr
    _bridge.launch(
        K.stratified_fwd,
        n_rays,
        [
            a(near),
            a(far),
            int(n_samples),
            a(packed_info),
            int(perturb),
            int(seed) & 0x7FFFFFFF,
            a(t_starts),
            a(t_ends),
            a(ray_indices),
        ],
        dev,
    )
    if packed:
        return Samples(t_starts, t_ends, ray_indices, packed_info)
    return Samples(t_starts.reshape(n_rays, n_samples), t_ends.reshape(n_rays, n_samples))
