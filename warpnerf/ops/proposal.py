"""Torch bridge for proposal sampling (kernels/proposal.py; the maths is documented there):
inverse-CDF resampling of a per-ray histogram (:func:`proposal_resample`, no gradient) and the
interlevel loss (:func:`interlevel_loss`, differentiable with respect to the proposal weights).
``warpnerf.reference.proposal`` holds the pure-PyTorch twins with the same signatures."""

from __future__ import annotations

import torch

from . import bridge

__all__ = ["proposal_resample", "interlevel_loss", "HISTOGRAM_PADDING", "INTERLEVEL_EPS"]

HISTOGRAM_PADDING = 0.01  # nerfacto's PDFSampler: added to every bin's (annealed) weight
INTERLEVEL_EPS = 1e-7  # nerfstudio's lossfun_outer: w / (w + eps)


def _check_edges(name: str, edges: torch.Tensor, n_rays: int, n: int, dt, dev) -> None:
    bridge.check_float(name, edges, (n_rays, n + 1), dt, dev)


def _sorted_and_finite(*edges: torch.Tensor) -> list:
    """Device flags (one host read later): each edge tensor finite and non-decreasing per row."""
    flags = []
    for e in edges:
        flags += [torch.isfinite(e).all(), ~(e[:, 1:] < e[:, :-1]).any()]
    return flags


def proposal_resample(
    s_edges: torch.Tensor,  # [n_rays, n + 1] bin edges, increasing along each ray
    weights: torch.Tensor,  # [n_rays, n] the bins' weights (compositing weights), >= 0
    n_samples: int,
    *,
    jitter: torch.Tensor | None = None,  # None, [n_rays] or [n_rays, n_samples + 1] in [0, 1)
    anneal: float | torch.Tensor = 1.0,
    padding: float = HISTOGRAM_PADDING,
    check: bool = True,
) -> torch.Tensor:
    """``n_samples + 1`` new sorted edges per ray ``[n_rays, n_samples + 1]`` (so
    ``n_samples`` intervals), drawn by the inverse CDF of the piecewise-constant histogram whose
    bin i (between ``s_edges[:, i]`` and ``s_edges[:, i + 1]``) has the mass
    ``weights^anneal + padding`` (nerfacto's annealing and padding; all-zero masses count one
    per bin). Quantiles ``(j + U) / (n_samples + 1)``: U = 1/2 without ``jitter``
    (deterministic), else its values: one per ray (nerfacto's single jitter) or one per edge.
    The new edges lie in [first edge, last edge] of their ray. No gradient (nerfacto detaches
    the resampled positions). ``anneal``: a float or a one-element tensor (on the device: a
    training step needs no host value), in [0, 1].

    ``check=True`` verifies on the host (one sync on CUDA) that the edges are finite and
    non-decreasing, the weights finite and >= 0 and the jitter in [0, 1); ``check=False`` (the
    library's own samples) skips it, and a non-finite weight or edge makes its ray's new edges
    NaN.
    """
    from warpnerf.kernels import proposal as K

    n_samples = bridge.check_int("n_samples", n_samples, lo=1, hi=bridge.INT32_MAX - 1)
    bridge.check_float("weights", weights, (None, None))
    n_rays, n = weights.shape
    dev, dt = weights.device, weights.dtype
    if n < 1:
        raise ValueError("weights needs at least one bin per ray")
    _check_edges("s_edges", s_edges, n_rays, n, dt, dev)
    if n_rays * (n_samples + 1) > bridge.INT32_MAX or n_rays * (n + 1) > bridge.INT32_MAX:
        raise ValueError("too many rays x samples for int32 offsets")
    if not (isinstance(padding, (int, float)) and 0 <= padding < float("inf")):
        raise ValueError(f"padding must be a finite number >= 0, got {padding!r}")
    if isinstance(anneal, torch.Tensor):
        bridge.check_float("anneal", anneal, tuple(anneal.shape))
        if anneal.numel() != 1:
            raise ValueError(f"anneal must be a number or a one-element tensor, got {anneal.shape}")
        a = anneal.detach().reshape(1).to(dev, dt)
    else:
        if not 0 <= float(anneal) <= 1:
            raise ValueError(f"anneal must be in [0, 1], got {anneal}")
        a = bridge.constant([float(anneal)], dev, dt)
    mode, jit = 0, torch.zeros(1, 1, device=dev, dtype=dt)
    if jitter is not None:
        if jitter.dim() == 1:
            bridge.check_float("jitter", jitter, (n_rays,), None, dev)
            mode, jit = 1, jitter.detach().to(dt).reshape(n_rays, 1)
        else:
            bridge.check_float("jitter", jitter, (n_rays, n_samples + 1), None, dev)
            mode, jit = 2, jitter.detach().to(dt)
    if check and n_rays:
        w = weights.detach()
        flags = _sorted_and_finite(s_edges.detach())
        flags += [torch.isfinite(w).all() & (w >= 0).all()]
        flags += [((jit >= 0) & (jit < 1)).all()] if mode else []
        ok = bridge.host_flags(*flags)
        if not ok[0]:
            raise ValueError("s_edges must be finite")
        if not ok[1]:
            raise ValueError("s_edges must be non-decreasing along each ray")
        if not ok[2]:
            raise ValueError("weights must be finite and >= 0")
        if mode and not ok[3]:
            raise ValueError("jitter must be in [0, 1)")
        if isinstance(anneal, torch.Tensor) and not bridge.host_flags((a >= 0) & (a <= 1))[0]:
            raise ValueError("anneal must be in [0, 1]")
    out = torch.empty(n_rays, n_samples + 1, device=dev, dtype=dt)
    arr = bridge.arr
    bridge.launch(K.resample_fwd, n_rays,
                  [arr(s_edges.detach()), arr(weights.detach()), arr(a),
                   bridge.scalar(float(padding), dt), arr(jit.contiguous()), mode, arr(out)],
                  dev)  # fmt: skip
    return out


class _Interlevel(torch.autograd.Function):
    @staticmethod
    def forward(ctx, s_fine, w_fine, s_prop, w_prop, eps):
        from warpnerf.kernels import proposal as K

        out = torch.empty(w_prop.shape[0], device=w_prop.device, dtype=w_prop.dtype)
        a = bridge.arr
        e = bridge.scalar(eps, w_prop.dtype)
        bridge.launch(K.interlevel_fwd, w_prop.shape[0],
                      [a(s_fine), a(w_fine), a(s_prop), a(w_prop), e, a(out)],
                      w_prop.device)  # fmt: skip
        ctx.save_for_backward(s_fine, w_fine, s_prop, w_prop)
        ctx.eps = eps
        return out

    @staticmethod
    def backward(ctx, v_loss):
        from warpnerf.kernels import proposal as K

        s_fine, w_fine, s_prop, w_prop = ctx.saved_tensors
        v_w_prop = torch.zeros_like(w_prop)
        a = bridge.arr
        e = bridge.scalar(ctx.eps, w_prop.dtype)
        bridge.launch(K.interlevel_bwd, w_prop.shape[0],
                      [a(s_fine), a(w_fine), a(s_prop), a(w_prop), e, a(v_loss.contiguous()),
                       a(v_w_prop)], w_prop.device)  # fmt: skip
        return None, None, None, v_w_prop, None


def interlevel_loss(
    s_fine: torch.Tensor,  # [n_rays, n_f + 1] the final samples' edges
    w_fine: torch.Tensor,  # [n_rays, n_f] their compositing weights (detached here)
    s_prop: torch.Tensor,  # [n_rays, n_p + 1] one proposal level's edges (same coordinate)
    w_prop: torch.Tensor,  # [n_rays, n_p] its weights
    *,
    eps: float = INTERLEVEL_EPS,
    check: bool = True,
) -> torch.Tensor:
    """mip-NeRF 360's interlevel loss of each ray, ``[n_rays]``:
    ``sum_i max(0, w_i - outer_i)^2 / (w_i + eps)``, with ``outer_i`` the proposal weights of
    every proposal interval overlapping fine interval i (nerfstudio's ``outer``): the proposal
    histogram must bound the fine one from above. Differentiable with respect to ``w_prop``
    only (the fine weights are a fixed target, as in nerfacto).

    ``check=True`` verifies (one host sync on CUDA) that both edge sets are finite and
    non-decreasing along each ray (the two-pointer walk relies on it); a NaN weight makes its
    ray's loss NaN."""
    bridge.check_float("w_prop", w_prop, (None, None))
    n_rays, n_p = w_prop.shape
    dev, dt = w_prop.device, w_prop.dtype
    bridge.check_float("w_fine", w_fine, (n_rays, None), dt, dev)
    n_f = w_fine.shape[1]
    if n_p < 1:
        raise ValueError("w_prop needs at least one interval per ray")
    _check_edges("s_fine", s_fine, n_rays, n_f, dt, dev)
    _check_edges("s_prop", s_prop, n_rays, n_p, dt, dev)
    if not (isinstance(eps, (int, float)) and 0 < eps < float("inf")):
        raise ValueError(f"eps must be a positive number, got {eps!r}")
    if check and n_rays:
        ok = bridge.host_flags(*_sorted_and_finite(s_fine.detach(), s_prop.detach()))
        if not all(ok):
            raise ValueError("s_fine and s_prop must be finite and non-decreasing along each ray")
    return _Interlevel.apply(s_fine.detach().contiguous(), w_fine.detach().contiguous(),
                             s_prop.detach().contiguous(), w_prop.contiguous(),
                             float(eps))  # fmt: skip
