"""Torch bridge for emission-absorption compositing (kernels/composite.py).

The maths (forward, early termination and the exact backward) is documented in the kernel module;
``warpnerf.reference.composite`` is the readable pure-PyTorch twin with the same signatures.
"""

from __future__ import annotations

import torch

from . import _bridge

__all__ = ["render_packed", "render_dense", "packed_info_from_ray_indices"]


# Which kernels composite float32 densities: "tiled" (one block per ray, coalesced loads; the
# default) or "sequential" (one thread per ray, the only choice for float64 and for alphas). Tests
# switch this to check the two against each other; users have no reason to.
_IMPL = {"float32_sigma": "tiled", "block_dim": 32}


def _use_tiled(values: torch.Tensor, use_alpha: int) -> bool:
    return values.dtype == torch.float32 and not use_alpha and _IMPL["float32_sigma"] == "tiled"


class _Composite(torch.autograd.Function):
    """values = sigmas or alphas; returns (rgb, depth, opacity, weights)."""

    @staticmethod
    def forward(
        ctx,
        packed_info,
        n_dense,
        t_starts,
        t_ends,
        values,
        use_alpha,
        rgbs,
        background,
        t_threshold,
        want_weights,
    ):
        from warpnerf.kernels import composite as K

        dev, dt = values.device, values.dtype
        n_rays = packed_info.shape[0] if n_dense == 0 else values.shape[0] // max(n_dense, 1)
        n = values.shape[0]

        def new(*shape, dtype=dt):
            return torch.empty(shape, device=dev, dtype=dtype)

        rgb, depth, opacity, t_final = new(n_rays, 3), new(n_rays), new(n_rays), new(n_rays)
        trans, weights = new(n), new(n if want_weights else 0)
        n_eff = new(n_rays, dtype=torch.int32)
        a = _bridge.arr
        head = [a(packed_info), n_dense, a(t_starts), a(t_ends), a(values)]
        tail = [
            a(rgbs),
            a(background),
            _bridge.scalar(t_threshold, dt),
            int(want_weights),
            a(rgb),
            a(depth),
            a(opacity),
            a(t_final),
            a(trans),
            a(weights),
            a(n_eff),
        ]
        ctx.tiled = _use_tiled(values, use_alpha)
        if ctx.tiled:
            _bridge.launch_tiled(
                K.composite_fwd_tiled, n_rays, _IMPL["block_dim"], head + tail, dev
            )
        else:
            _bridge.launch(K.composite_fwd, n_rays, head + [int(use_alpha)] + tail, dev)
        ctx.save_for_backward(
            packed_info, t_starts, t_ends, values, rgbs, background, trans, n_eff, t_final
        )
        ctx.n_dense, ctx.use_alpha, ctx.n_rays = n_dense, use_alpha, n_rays
        ctx.mark_non_differentiable(n_eff)
        return rgb, depth, opacity, weights

    @staticmethod
    def backward(ctx, v_rgb, v_depth, v_opacity, v_weights):
        from warpnerf.kernels import composite as K

        saved = ctx.saved_tensors
        packed_info, t_starts, t_ends, values, rgbs, background, trans, n_eff, t_final = saved
        dev, dt = values.device, values.dtype
        n_rays = ctx.n_rays

        def grad_or_zeros(g, shape):
            return torch.zeros(shape, device=dev, dtype=dt) if g is None else g.contiguous()

        v_rgb = grad_or_zeros(v_rgb, (n_rays, 3))
        v_depth = grad_or_zeros(v_depth, (n_rays,))
        v_opacity = grad_or_zeros(v_opacity, (n_rays,))
        if v_weights is None or v_weights.numel() == 0:
            v_weights = torch.empty(0, device=dev, dtype=dt)
        v_values = torch.empty_like(values)
        v_rgbs = torch.empty_like(rgbs)
        a = _bridge.arr
        head = [a(packed_info), ctx.n_dense, a(t_starts), a(t_ends), a(values)]
        upstream = [a(v_rgb), a(v_depth), a(v_opacity), a(v_weights), a(v_values), a(v_rgbs)]
        if ctx.tiled:
            inputs = head + [a(rgbs), a(background), a(trans), a(n_eff), a(t_final)] + upstream
            _bridge.launch_tiled(K.composite_bwd_tiled, n_rays, _IMPL["block_dim"], inputs, dev)
        else:
            inputs = head + [int(ctx.use_alpha), a(rgbs), a(background), a(trans), a(n_eff)]
            _bridge.launch(K.composite_bwd, n_rays, inputs + upstream, dev)
        v_background = None
        if ctx.needs_input_grad[7]:
            # d rgb / d background = T_m, the forward's own final transmittance (not 1 - opacity,
            # whose rounding error exceeds T_m on nearly opaque rays).
            v_bg = t_final.unsqueeze(-1) * v_rgb
            v_background = v_bg.sum(0, keepdim=True) if background.shape[0] == 1 else v_bg
        return None, None, None, None, v_values, None, v_rgbs, v_background, None, None


def packed_info_from_ray_indices(ray_indices: torch.Tensor, n_rays: int) -> torch.Tensor:
    """``[n_rays, 2]`` int32 (start, count) from sorted ``ray_indices`` ``[n]``."""
    if ray_indices.numel() > 1 and bool((ray_indices[1:] < ray_indices[:-1]).any()):
        raise ValueError("ray_indices must be sorted (each ray's samples contiguous)")
    if ray_indices.numel() and (int(ray_indices.min()) < 0 or int(ray_indices.max()) >= n_rays):
        raise ValueError(f"ray_indices must lie in [0, {n_rays}), n_rays={n_rays}")
    counts = torch.bincount(ray_indices.long(), minlength=n_rays)
    starts = torch.cumsum(counts, 0) - counts
    return torch.stack([starts, counts], -1).to(torch.int32)


def _background(background, n_rays, device, dtype):
    if background is None:
        return torch.zeros(1, 3, device=device, dtype=dtype)
    bg = torch.as_tensor(background, device=device, dtype=dtype)
    if bg.dim() == 0:
        bg = bg.expand(3)
    if bg.shape == (3,):
        return bg.reshape(1, 3)
    if bg.shape == (n_rays, 3):
        return bg
    raise ValueError(
        f"background must be a scalar, [3] or [n_rays={n_rays}, 3], got {list(bg.shape)}"
    )


def _values(sigmas, alphas):
    if (sigmas is None) == (alphas is None):
        raise ValueError("pass exactly one of sigmas (densities) or alphas (per-sample opacities)")
    return (sigmas, 0) if alphas is None else (alphas, 1)


def render_packed(
    t_starts: torch.Tensor,  # [n]
    t_ends: torch.Tensor,  # [n]
    ray_indices: torch.Tensor,  # [n] sorted, int
    sigmas: torch.Tensor | None,  # [n]
    rgbs: torch.Tensor,  # [n, 3]
    n_rays: int,
    background=None,  # scalar, [3] or [n_rays, 3]; None = black
    *,
    alphas: torch.Tensor | None = None,  # [n] per-sample opacities instead of sigmas
    packed_info: torch.Tensor | None = None,  # [n_rays, 2] int32, computed if None
    t_threshold: float = 0.0,
    return_weights: bool = False,
):
    """Composites packed samples into per-ray colour, expected depth and opacity.

    With delta_i = t_end_i - t_start_i, alpha_i = 1 - exp(-sigma_i delta_i) (or the given alphas),
    T_i = exp(-sum_{j<i} sigma_j delta_j) computed in log space and w_i = T_i alpha_i:
    ``rgb = sum_i w_i c_i + T_end * background``, ``depth = sum_i w_i (t_start_i + t_end_i) / 2``
    (not normalised: divide by opacity for the depth of the visible surface),
    ``opacity = sum_i w_i``. A ray stops at the first sample with T_i < t_threshold (0 = never);
    forward and backward skip the same samples. Differentiable w.r.t. sigmas/alphas, rgbs and
    background (not t_starts/t_ends) through a hand-written exact backward. NaN inputs, and
    invalid samples (t_end < t_start or a non-finite length, sigma < 0, alpha outside [0, 1]),
    make their ray's outputs and gradients NaN rather than a plausible value (checked in the
    kernel: no host sync); other rays are unaffected. See docs/NUMERICS.md.

    Returns:
        rgb [n_rays, 3], depth [n_rays], opacity [n_rays] (and weights [n] if return_weights).
    """
    values, use_alpha = _values(sigmas, alphas)
    n = values.shape[0] if values.dim() == 1 else -1
    dev, dt = values.device, values.dtype
    _bridge.check_float("sigmas" if not use_alpha else "alphas", values, (None,))
    for name, t, shape in (
        ("t_starts", t_starts, (n,)),
        ("t_ends", t_ends, (n,)),
        ("rgbs", rgbs, (n, 3)),
    ):
        _bridge.check_float(name, t, shape, dt, dev)
    if ray_indices.shape != (n,):
        raise ValueError(f"ray_indices must have shape [{n}], got {list(ray_indices.shape)}")
    if packed_info is None:
        packed_info = packed_info_from_ray_indices(ray_indices.to(dev), n_rays)
    elif packed_info.shape != (n_rays, 2):
        raise ValueError(
            f"packed_info must have shape [{n_rays}, 2], got {list(packed_info.shape)}"
        )
    bg = _background(background, n_rays, dev, dt)
    rgb, depth, opacity, weights = _Composite.apply(
        packed_info.to(dev, torch.int32).contiguous(),
        0,
        t_starts.contiguous(),
        t_ends.contiguous(),
        values.contiguous(),
        use_alpha,
        rgbs.contiguous(),
        bg,
        float(t_threshold),
        bool(return_weights),
    )
    return (rgb, depth, opacity, weights) if return_weights else (rgb, depth, opacity)


def render_dense(
    t_starts: torch.Tensor,  # [n_rays, n_samples]
    t_ends: torch.Tensor,  # [n_rays, n_samples]
    sigmas: torch.Tensor | None,  # [n_rays, n_samples]
    rgbs: torch.Tensor,  # [n_rays, n_samples, 3]
    background=None,  # scalar, [3] or [n_rays, 3]
    *,
    alphas: torch.Tensor | None = None,  # [n_rays, n_samples]
    t_threshold: float = 0.0,
    return_weights: bool = False,
):
    """Dense counterpart of :func:`render_packed`: every ray has the same n_samples.

    Returns:
        rgb [n_rays, 3], depth [n_rays], opacity [n_rays] (and weights [n_rays, n_samples]).
    """
    values, use_alpha = _values(sigmas, alphas)
    name = "alphas" if use_alpha else "sigmas"
    _bridge.check_float(name, values, (None, None))
    n_rays, n_s = values.shape
    dev, dt = values.device, values.dtype
    for nm, t, shape in (
        ("t_starts", t_starts, (n_rays, n_s)),
        ("t_ends", t_ends, (n_rays, n_s)),
        ("rgbs", rgbs, (n_rays, n_s, 3)),
    ):
        _bridge.check_float(nm, t, shape, dt, dev)
    bg = _background(background, n_rays, dev, dt)
    empty_info = torch.empty(n_rays, 2, device=dev, dtype=torch.int32)
    if n_s == 0:
        rgb = bg.expand(n_rays, 3) + 0 * values.sum()
        zeros = torch.zeros(n_rays, device=dev, dtype=dt)
        out = (rgb, zeros, zeros.clone())
        return out + (values.clone(),) if return_weights else out
    rgb, depth, opacity, weights = _Composite.apply(
        empty_info,
        n_s,
        t_starts.reshape(-1).contiguous(),
        t_ends.reshape(-1).contiguous(),
        values.reshape(-1).contiguous(),
        use_alpha,
        rgbs.reshape(-1, 3).contiguous(),
        bg,
        float(t_threshold),
        bool(return_weights),
    )
    if return_weights:
        return rgb, depth, opacity, weights.reshape(n_rays, n_s)
    return rgb, depth, opacity
