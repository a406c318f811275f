"""Pure-PyTorch twin of warpnerf.ops.composite: same names, signatures and maths, autograd backward.

Readable rather than fast: packed samples are scattered into a zero-padded dense block (padding has
zero length and zero density, so it changes nothing) and composited with cumulative sums in log
space.
"""

from __future__ import annotations

import torch

from warpnerf.ops.composite import background_rows, density_or_alpha, packed_info_from_ray_indices

__all__ = ["render_dense", "render_packed"]


def _alpha_tau(values, deltas, use_alpha):
    """(alpha, tau) per sample; NaN for an invalid sample (delta not finite and >= 0, density
    < 0, opacity outside [0, 1]), as in the kernel, so its ray comes out NaN."""
    ok = torch.isfinite(deltas) & (deltas >= 0) & (values >= 0)
    if use_alpha:
        ok = ok & (values <= 1)
        alpha, tau = values, -torch.log1p(-values)
    else:
        tau = values * deltas
        alpha = -torch.expm1(-tau)
    nan = torch.full_like(tau, float("nan"))
    return torch.where(ok, alpha, nan), torch.where(ok, tau, nan)


def render_dense(
    t_starts,
    t_ends,
    sigmas,
    rgbs,
    background=None,
    *,
    alphas=None,
    t_threshold=0.0,
    return_weights=False,
):
    """Reference for :func:`warpnerf.render_dense` (shapes [n_rays, n_samples])."""
    values, use_alpha = density_or_alpha(sigmas, alphas)
    n_rays = values.shape[0]
    bg = background_rows(background, n_rays, values.device, values.dtype)
    alpha, tau = _alpha_tau(values, t_ends - t_starts, use_alpha)
    # Exclusive cumulative sum: log T_i = -sum_{j<i} tau_j.
    log_t = -torch.cumsum(torch.cat([torch.zeros_like(tau[:, :1]), tau[:, :-1]], 1), 1)
    trans = torch.exp(log_t)
    # Early termination: T is non-increasing, so "from the first T_i < thr on" = "every T_i < thr".
    live = ~(trans < t_threshold)
    weights = torch.where(live, trans * alpha, torch.zeros_like(alpha))
    t_mid = 0.5 * (t_starts + t_ends)
    # Transmittance left after the last composited sample.
    log_t_end = -(torch.where(live, tau, torch.zeros_like(tau))).sum(1)
    rgb = (weights.unsqueeze(-1) * rgbs).sum(1) + torch.exp(log_t_end).unsqueeze(-1) * bg
    depth = (weights * t_mid).sum(1)
    opacity = weights.sum(1)
    return (rgb, depth, opacity, weights) if return_weights else (rgb, depth, opacity)


def render_packed(
    t_starts,
    t_ends,
    ray_indices,
    sigmas,
    rgbs,
    n_rays,
    background=None,
    *,
    alphas=None,
    packed_info=None,
    t_threshold=0.0,
    return_weights=False,
):
    """Reference for :func:`warpnerf.render_packed` (packed samples, sorted ray_indices)."""
    values, use_alpha = density_or_alpha(sigmas, alphas)
    if packed_info is None:
        packed_info = packed_info_from_ray_indices(ray_indices, n_rays)
    starts, counts = packed_info[:, 0].long(), packed_info[:, 1].long()
    width = int(counts.max()) if n_rays and values.numel() else 0
    width = max(width, 1)
    ray = ray_indices.long()
    col = torch.arange(values.shape[0], device=values.device) - starts[ray]

    def dense(x, fill=0.0):
        out = torch.full((n_rays, width) + tuple(x.shape[1:]), fill, dtype=x.dtype, device=x.device)
        return out.index_put((ray, col), x)

    t0 = dense(t_starts)
    out = render_dense(
        t0,
        t0 + dense(t_ends - t_starts),
        None if use_alpha else dense(values),
        dense(rgbs),
        background,
        alphas=dense(values) if use_alpha else None,
        t_threshold=t_threshold,
        return_weights=True,
    )
    rgb, depth, opacity, weights = out
    if return_weights:
        return rgb, depth, opacity, weights[ray, col]
    return rgb, depth, opacity
