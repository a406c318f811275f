"""Torch bridge for emission-absorption compositing (kernels/composite.py).

The maths (forward, early termination and the exact backward) is documented in the kernel module;
``warpnerf.reference.composite`` is the readable pure-PyTorch twin with the same signatures.
"""

from __future__ import annotations

import contextlib

import torch

from . import bridge

__all__ = ["render_packed", "render_dense", "packed_info_from_ray_indices"]


# Which kernels composite float32 densities: "tiled" (kernels/composite_tiled.py: one block per
# ray, coalesced loads, no per-sample state; the default) or "sequential" (one thread per ray, the
# only choice for float64 and for alphas). Switched only through composite_kernels() (tests and
# benchmarks compare them).
_IMPL = {"float32_sigma": "tiled", "block_dim": 32}
_KINDS = ("tiled", "sequential")


@contextlib.contextmanager
def composite_kernels(float32_sigma: str = "tiled", block_dim: int = 32):
    """Within the block, float32 densities are composited by the ``"tiled"`` kernels (one block
    of ``block_dim`` lanes per ray, the default) or the ``"sequential"`` ones (one thread per
    ray); restored on exit. For tests and benchmarks: both give the same results within float32
    round-off (tests/test_composite_tiled.py)."""
    if float32_sigma not in _KINDS:
        raise ValueError(f"float32_sigma must be one of {_KINDS}, got {float32_sigma!r}")
    block_dim = bridge.check_int("block_dim", block_dim, lo=1, hi=1024)
    saved = dict(_IMPL)
    _IMPL.update(float32_sigma=float32_sigma, block_dim=block_dim)
    try:
        yield
    finally:
        _IMPL.clear()
        _IMPL.update(saved)


def _kernels(values: torch.Tensor, use_alpha: int) -> str:
    """Which kernels composite ``values``: the chosen float32 kernels for float32 densities,
    else ``"sequential"``."""
    if values.dtype == torch.float32 and not use_alpha:
        return _IMPL["float32_sigma"]
    return "sequential"


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
        # per-sample state for the backward: the transmittances (sequential) or the
        # optical depth at each chunk's first sample (tiled: written once per chunk, and never for
        # rays of at most one chunk; the rest of the buffer is never touched)
        state, weights = new(n), new(n if want_weights else 0)
        n_eff = new(n_rays, dtype=torch.int32)
        a = bridge.arr
        head = [a(packed_info), n_dense, a(t_starts), a(t_ends), a(values)]
        tail = [
            a(rgbs),
            a(background),
            bridge.scalar(t_threshold, dt),
            int(want_weights),
            a(rgb),
            a(depth),
            a(opacity),
            a(t_final),
            a(state),
            a(weights),
            a(n_eff),
        ]
        ctx.kernels = _kernels(values, use_alpha)
        ctx.block_dim = _IMPL["block_dim"]
        if ctx.kernels == "sequential":
            bridge.launch(K.composite_fwd, n_rays, head + [int(use_alpha)] + tail, dev)
        else:
            from warpnerf.kernels import composite_tiled as T

            bridge.launch_tiled(T.composite_fwd_tiled, n_rays, ctx.block_dim, head + tail, dev)
        ctx.save_for_backward(
            packed_info, t_starts, t_ends, values, rgbs, background, state, n_eff, t_final
        )
        ctx.n_dense, ctx.use_alpha, ctx.n_rays = n_dense, use_alpha, n_rays
        ctx.t_threshold = t_threshold
        ctx.mark_non_differentiable(n_eff)
        return rgb, depth, opacity, weights

    @staticmethod
    def backward(ctx, v_rgb, v_depth, v_opacity, v_weights):
        from warpnerf.kernels import composite as K

        saved = ctx.saved_tensors
        packed_info, t_starts, t_ends, values, rgbs, background, state, n_eff, t_final = saved
        dev, dt = values.device, values.dtype
        n_rays = ctx.n_rays

        def grad_or_zeros(g, shape):
            return torch.zeros(shape, device=dev, dtype=dt) if g is None else g.contiguous()

        v_rgb = grad_or_zeros(v_rgb, (n_rays, 3))
        v_depth = grad_or_zeros(v_depth, (n_rays,))
        v_opacity = grad_or_zeros(v_opacity, (n_rays,))
        if v_weights is None or v_weights.numel() == 0:
            v_weights = torch.empty(0, device=dev, dtype=dt)
        # The kernels write every sample's gradient, the samples no ray covers (the unused slots
        # of a fixed-capacity buffer) included, so no zero-fill first (16 B per sample).
        alloc = torch.zeros_like if n_rays == 0 else torch.empty_like
        v_values, v_rgbs = alloc(values), alloc(rgbs)
        a = bridge.arr
        head = [a(packed_info), ctx.n_dense, a(t_starts), a(t_ends), a(values)]
        upstream = [a(v_rgb), a(v_depth), a(v_opacity), a(v_weights), a(v_values), a(v_rgbs)]
        if ctx.kernels == "sequential":
            inputs = head + [int(ctx.use_alpha), a(rgbs), a(background), a(state), a(n_eff)]
            bridge.launch(K.composite_bwd, n_rays, inputs + upstream, dev)
        else:
            from warpnerf.kernels import composite_tiled as T

            threshold = bridge.scalar(ctx.t_threshold, dt)
            inputs = head + [a(rgbs), a(background), threshold, a(state), a(n_eff), a(t_final)]
            bridge.launch_tiled(
                T.composite_bwd_tiled, n_rays, ctx.block_dim, inputs + upstream, dev
            )
        v_background = None
        if ctx.needs_input_grad[7]:
            # d rgb / d background = T_m, the forward's own final transmittance (not 1 - opacity,
            # whose rounding error exceeds T_m on nearly opaque rays).
            v_bg = t_final.unsqueeze(-1) * v_rgb
            v_background = v_bg.sum(0, keepdim=True) if background.shape[0] == 1 else v_bg
        return None, None, None, None, v_values, None, v_rgbs, v_background, None, None


def packed_info_from_ray_indices(ray_indices: torch.Tensor, n_rays: int) -> torch.Tensor:
    """``[n_rays, 2]`` int32 (start, count) from sorted ``ray_indices`` ``[n]`` (int32/int64).

    Raises ValueError unless the indices are sorted and lie in [0, n_rays) (one pass over them and
    one host sync on CUDA), IndexDtypeError (a TypeError and ValueError) for a float tensor.
    """
    n_rays = bridge.check_int("n_rays", n_rays)
    bridge.check_index("ray_indices", ray_indices, (None,))
    n = ray_indices.shape[0]
    if n > bridge.INT32_MAX:
        raise ValueError(f"{n} samples exceed int32 offsets: render fewer samples at once")
    if n:
        ordered, lo_ok, hi_ok = bridge.host_flags(
            (ray_indices[1:] >= ray_indices[:-1]).all(),
            ray_indices[0] >= 0,  # sorted: the ends bound all of them
            ray_indices[-1] < n_rays,
        )
        if not ordered:
            raise ValueError("ray_indices must be sorted (each ray's samples contiguous)")
        if not (lo_ok and hi_ok):
            raise ValueError(f"ray_indices must lie in [0, {n_rays}), n_rays={n_rays}")
    counts = torch.bincount(ray_indices.long(), minlength=n_rays)
    starts = torch.cumsum(counts, 0) - counts
    return torch.stack([starts, counts], -1).to(torch.int32)


def check_packed_info(packed_info, ray_indices, n: int, n_rays: int) -> None:
    """Raises ValueError unless ``packed_info`` [n_rays, 2] lays out exactly the samples of the
    sorted ``ray_indices`` [n]: start, count >= 0, start + count <= n, every ray's first and last
    sample belong to it, and the counts add up to n (so segments are disjoint and cover every
    sample, whose weight and gradient would otherwise be left unwritten). One host sync."""
    # int64, clamped to [-1, n + 1] (which keeps every refusal): no wrap-around in the sums
    info = packed_info.to(torch.int64).clamp(-1, n + 1)
    starts, counts = info[:, 0], info[:, 1]
    ends = starts + counts
    flags = [info.amin() >= 0 if n_rays else torch.ones((), dtype=torch.bool, device=info.device)]
    flags.append(ends.amax() <= n if n_rays else flags[0])
    flags.append(counts.sum() == n)
    if n:
        ri = ray_indices
        rays = torch.arange(n_rays, device=ri.device)
        first = ri[starts.clamp(0, n - 1)]
        last = ri[(ends - 1).clamp(0, n - 1)]
        flags += [
            (ri[1:] >= ri[:-1]).all(),
            (ri[0] >= 0) & (ri[-1] < n_rays),
            ((first == rays) & (last == rays) | (counts <= 0)).all(),
        ]
    ok = bridge.host_flags(*flags) + [1] * (6 - len(flags))
    if not ok[0]:
        raise ValueError("packed_info has a negative start or count")
    if not ok[1]:
        raise ValueError(f"packed_info has a segment past the end of the {n} samples")
    if not ok[3]:
        raise ValueError("ray_indices must be sorted (each ray's samples contiguous)")
    if not ok[4]:
        raise ValueError(f"ray_indices must lie in [0, {n_rays}), n_rays={n_rays}")
    if not (ok[2] and ok[5]):
        raise ValueError(
            "packed_info does not match ray_indices: each ray's (start, count) must cover exactly "
            "its samples (as packed_info_from_ray_indices gives)"
        )


def background_rows(background, n_rays, device, dtype) -> torch.Tensor:
    """The background as [1, 3] or [n_rays, 3] rows (black for None); checks its shape."""
    if background is None:
        return torch.zeros(1, 3, device=device, dtype=dtype)
    bg = bridge.constant(background, device, dtype)  # (numbers: made once, no sync per call)
    if bg.dim() == 0:
        bg = bg.expand(3)
    if bg.shape == (3,):
        return bg.reshape(1, 3)
    if bg.shape == (n_rays, 3):
        return bg
    raise ValueError(
        f"background must be a scalar, [3] or [n_rays={n_rays}, 3], got {list(bg.shape)}"
    )


def density_or_alpha(sigmas, alphas) -> tuple:
    """(values, 1 if they are alphas else 0): exactly one of sigmas, alphas must be given."""
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
    check: bool = True,
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

    Index checks: ``ray_indices`` and ``packed_info`` must be int32/int64 tensors
    (IndexDtypeError, a TypeError and ValueError, for floats); ``ray_indices`` sorted in
    [0, n_rays) and ``packed_info`` the exact layout of those samples (start, count >= 0,
    start + count <= n, counts summing to n; ValueError otherwise, never an out-of-bounds read).
    This costs one pass over ``ray_indices`` and ``packed_info`` and one host sync per call on
    CUDA. ``check=False`` skips these value checks (shapes and dtypes are still checked, on the
    host); it is for callers that built ``packed_info`` themselves, as the library's renderers
    do (from :func:`stratified_samples`, :func:`importance_samples` or :func:`march_rays`):
    wrong values then read outside the arrays.

    Returns:
        rgb [n_rays, 3], depth [n_rays], opacity [n_rays] (and weights [n] if return_weights).
    """
    values, use_alpha = density_or_alpha(sigmas, alphas)
    n_rays = bridge.check_int("n_rays", n_rays)
    n = values.shape[0] if values.dim() == 1 else -1
    dev, dt = values.device, values.dtype
    bridge.check_float("sigmas" if not use_alpha else "alphas", values, (None,))
    for name, t, shape in (
        ("t_starts", t_starts, (n,)),
        ("t_ends", t_ends, (n,)),
        ("rgbs", rgbs, (n, 3)),
    ):
        bridge.check_float(name, t, shape, dt, dev)
    if n > bridge.INT32_MAX:
        raise ValueError(f"{n} samples exceed int32 offsets: render fewer samples at once")
    bridge.check_index("ray_indices", ray_indices, (n,))
    if packed_info is None:
        packed_info = packed_info_from_ray_indices(ray_indices.to(dev), n_rays)
    else:
        bridge.check_index("packed_info", packed_info, (n_rays, 2))
        packed_info = packed_info.to(dev)
        if check:
            check_packed_info(packed_info, ray_indices.to(dev), n, n_rays)
    bg = background_rows(background, n_rays, dev, dt)
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
    values, use_alpha = density_or_alpha(sigmas, alphas)
    name = "alphas" if use_alpha else "sigmas"
    bridge.check_float(name, values, (None, None))
    n_rays, n_s = values.shape
    if values.numel() > bridge.INT32_MAX:
        raise ValueError(f"{values.numel()} samples exceed int32 offsets: render fewer at once")
    dev, dt = values.device, values.dtype
    for nm, t, shape in (
        ("t_starts", t_starts, (n_rays, n_s)),
        ("t_ends", t_ends, (n_rays, n_s)),
        ("rgbs", rgbs, (n_rays, n_s, 3)),
    ):
        bridge.check_float(nm, t, shape, dt, dev)
    bg = background_rows(background, n_rays, dev, dt)
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
