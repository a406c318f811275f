"""Running the fields' small MLPs (``nn.Sequential`` of ``nn.Linear`` and ``nn.ReLU``) with each
Linear + ReLU pair fused on CUDA: cuBLASLt applies the bias and the ReLU in the matrix product's
epilogue (``torch._addmm_activation``), so the ReLU's separate pass over the activations (a
quarter of a hash-field training step's elementwise memory traffic) is gone. PyTorch has no
gradient for that op: :class:`_LinearReLU` gives the usual one (the ReLU's mask from the
output, then the Linear's). CPU runs, float64 and autocast keep the modules as they are, so
their results are unchanged. Also the fields' density activation, :func:`trunc_exp`.

Training may run the matrix products in half precision (``--mlp-precision bf16|fp16``): the
MLP under autocast (float32 weights, cast per call; float32 outputs), switched on for a
training step's rendering only (:func:`mlp_precision`), so validation and saved runs render in
float32. Under fp16 the gradients through the MLP are scaled by ``FP16_GRAD_SCALE`` (a fixed
power of two, undone exactly on the way out): a hash table's gradients are far below fp16's
smallest number (6e-8) and would flush to zero; bf16 keeps float32's range and needs none."""

from __future__ import annotations

import contextlib

import torch
from torch import nn

__all__ = ["run_mlp", "trunc_exp", "PRECISIONS", "mlp_precision"]

# --mlp-precision: the autocast dtype of the fields' MLPs in training (None: float32)
PRECISIONS = {"fp32": None, "bf16": torch.bfloat16, "fp16": torch.float16}
# fp16: the gradients inside the MLP are this many times the true ones (outputs' gradients
# scaled up before their cast to fp16, inputs' and weights' scaled back down in float32)
FP16_GRAD_SCALE = 1024.0


class _ScaleGrad(torch.autograd.Function):
    """Identity forward; the gradient times ``s`` (a power of two: exact)."""

    @staticmethod
    def forward(ctx, x, s: float):
        ctx.s = s
        return x.view_as(x)

    @staticmethod
    def backward(ctx, g):
        return g * ctx.s, None


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


@contextlib.contextmanager
def mlp_precision(field, precision: str = "fp32"):
    """Within it, ``field``'s MLPs run under autocast to ``PRECISIONS[precision]`` (a field
    with an ``mlp_dtype`` attribute; "fp32": nothing changes). ValueError for a field without
    one or an unknown name."""
    if precision not in PRECISIONS:
        raise ValueError(f"mlp precision must be one of {', '.join(PRECISIONS)}, "
                         f"got {precision!r}")  # fmt: skip
    dtype = PRECISIONS[precision]
    if dtype is None:
        yield
        return
    if not hasattr(field, "mlp_dtype"):
        raise ValueError(f"{type(field).__name__} has no half-precision MLP option")
    old, field.mlp_dtype = field.mlp_dtype, dtype
    try:
        yield
    finally:
        field.mlp_dtype = old


def run_mlp(mlp: nn.Sequential, x: torch.Tensor, dtype: torch.dtype | None = None) -> torch.Tensor:
    """``mlp(x)``, with Linear + ReLU pairs fused on CUDA (float32, no autocast); ``dtype``
    (bfloat16 or float16): under autocast to it (no weight cache: the step may be captured in
    a CUDA graph), the output back in ``x``'s dtype."""
    if dtype is not None:
        return _half_mlp(mlp, x, dtype)
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


def _half_mlp(mlp: nn.Sequential, x: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """``mlp(x)`` under autocast to ``dtype`` (no weight cache: the step may be captured in a
    CUDA graph), in ``x``'s dtype; fp16 with gradients: scaled by FP16_GRAD_SCALE inside."""
    scale = dtype == torch.float16 and torch.is_grad_enabled()
    with torch.autocast(x.device.type, dtype=dtype, cache_enabled=False):
        if not scale:
            return mlp(x).to(x.dtype)
        s = FP16_GRAD_SCALE
        params = {n: _ScaleGrad.apply(p, 1.0 / s) for n, p in mlp.named_parameters()}
        y = torch.func.functional_call(mlp, params, (_ScaleGrad.apply(x, 1.0 / s),))
    return _ScaleGrad.apply(y.to(x.dtype), s)
