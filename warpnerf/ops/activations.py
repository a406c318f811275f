"""Torch bridge for kernels/activations.py: ``softplus(x, beta, threshold)``, differentiable in
``x``, the same values as ``torch.nn.functional.softplus`` (to float rounding); and
:class:`Softplus`, the module the SDF networks use, which runs torch's op unless
:func:`activation_kernels` switches it to the Warp kernels (the A/B of issue 47: adopted as the
default only once measured faster on a GPU)."""

from __future__ import annotations

import contextlib

import torch
from torch import nn

from . import bridge

__all__ = ["softplus", "Softplus", "activation_kernels"]

_IMPL = {"softplus": "torch"}


@contextlib.contextmanager
def activation_kernels(softplus: str = "warp"):
    """Within the block :class:`Softplus` modules run ``softplus`` ("warp": the Warp kernels,
    "torch": torch's op); restored on exit (benchmarks and tests compare them)."""
    if softplus not in ("warp", "torch"):
        raise ValueError(f"softplus must be 'warp' or 'torch', got {softplus!r}")
    saved = dict(_IMPL)
    _IMPL["softplus"] = softplus
    try:
        yield
    finally:
        _IMPL.clear()
        _IMPL.update(saved)


class _Softplus(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, beta, threshold):
        from warpnerf.kernels import activations as K

        flat = x.contiguous().view(-1)
        out = torch.empty_like(flat)
        dt = x.dtype
        bridge.launch(K.softplus_fwd, flat.numel(), [bridge.arr(flat), bridge.scalar(beta, dt),
                      bridge.scalar(threshold, dt), bridge.arr(out)], x.device)  # fmt: skip
        ctx.save_for_backward(flat)
        ctx.beta, ctx.threshold, ctx.shape = beta, threshold, x.shape
        return out.view(x.shape)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, v_out):
        from warpnerf.kernels import activations as K

        (flat,) = ctx.saved_tensors
        g = v_out.contiguous().view(-1)
        v_x = torch.empty_like(flat)
        dt = flat.dtype
        bridge.launch(K.softplus_bwd, flat.numel(), [bridge.arr(flat), bridge.arr(g),
                      bridge.scalar(ctx.beta, dt), bridge.scalar(ctx.threshold, dt),
                      bridge.arr(v_x)], flat.device)  # fmt: skip
        return v_x.view(ctx.shape), None, None


def softplus(x: torch.Tensor, beta: float = 1.0, threshold: float = 20.0) -> torch.Tensor:
    """``x`` where ``beta x > threshold``, else ``log(1 + exp(beta x)) / beta``, elementwise,
    by the Warp kernels (float32 or float64, any shape); differentiable in ``x`` (a hand-written
    backward: ``sigmoid(beta x)``, 1 above the threshold)."""
    bridge.check_float("x", x, tuple(None for _ in x.shape))
    beta, threshold = float(beta), float(threshold)
    if not beta > 0.0:
        raise ValueError(f"beta must be > 0, got {beta}")
    return _Softplus.apply(x, beta, threshold)


class Softplus(nn.Module):
    """``nn.Softplus(beta, threshold)`` (no parameters: a checkpoint's keys are the same) that
    runs the Warp kernels within :func:`activation_kernels` and torch's op otherwise."""

    def __init__(self, beta: float = 1.0, threshold: float = 20.0):
        super().__init__()
        self.beta, self.threshold = float(beta), float(threshold)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if _IMPL["softplus"] == "warp" and x.dtype in (torch.float32, torch.float64):
            return softplus(x, self.beta, self.threshold)
        return torch.nn.functional.softplus(x, self.beta, self.threshold)

    def extra_repr(self) -> str:
        return f"beta={self.beta:g}, threshold={self.threshold:g}"
