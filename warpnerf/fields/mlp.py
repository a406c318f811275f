"""Running the fields' small MLPs (``nn.Sequential`` of ``nn.Linear`` and ``nn.ReLU``) with each
Linear + ReLU pair fused on CUDA: cuBLASLt applies the bias and the ReLU in the matrix product's
epilogue (``torch._addmm_activation``), so the ReLU's separate pass over the activations (a
quarter of a hash-field training step's elementwise memory traffic) is gone. PyTorch has no
gradient for that op: :class:`_LinearReLU` gives the usual one (the ReLU's mask from the
output, then the Linear's). CPU runs, float64 and autocast keep the modules as they are, so
their results are unchanged. Also the fields' density activation, :func:`trunc_exp`."""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["run_mlp", "trunc_exp"]


class _LinearReLU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, weight, bias):
        y = torch._addmm_activation(bias, x, weight.t())
        ctx.save_for_backward(x, weight, y)
        return y

    @staticmethod
    def backward(ctx, v_y):
        x, weight, y = ctx.saved_tensors
        # the ReLU's mask, fused (one pass: autograd's own ReLU backward), not a comparison,
        # a zero fill and a where over the activations (three passes)
        g = torch.ops.aten.threshold_backward(v_y, y, 0)
        v_x = g @ weight if ctx.needs_input_grad[0] else None
        v_w = g.t() @ x if ctx.needs_input_grad[1] else None
        v_b = g.sum(0) if ctx.needs_input_grad[2] else None
        return v_x, v_w, v_b


def _fusable(x: torch.Tensor) -> bool:
    return x.is_cuda and x.dtype == torch.float32 and not torch.is_autocast_enabled("cuda")


def run_mlp(mlp: nn.Sequential, x: torch.Tensor) -> torch.Tensor:
    """``mlp(x)``, with Linear + ReLU pairs fused on CUDA (float32, no autocast)."""
    if not _fusable(x):
        return mlp(x)
    layers = list(mlp)
    i = 0
    while i < len(layers):
        layer = layers[i]
        nxt = layers[i + 1] if i + 1 < len(layers) else None
        if isinstance(layer, nn.Linear) and layer.bias is not None and isinstance(nxt, nn.ReLU):
            x = _LinearReLU.apply(x, layer.weight, layer.bias)
            i += 2
        else:
            x = layer(x)
            i += 1
    return x


class _TruncExp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        return torch.exp(x.clamp(max=15.0))

    @staticmethod
    def backward(ctx, g):
        (x,) = ctx.saved_tensors
        return g * torch.exp(x.clamp(-15.0, 15.0))


def trunc_exp(x: torch.Tensor) -> torch.Tensor:
    """instant-ngp's density activation: exp(x) with x clamped at 15 in the forward pass only
    (the gradient is exp(clamp(x, -15, 15)), never cut)."""
    return _TruncExp.apply(x)
