"""Twin of kernels/activations.py: torch's softplus with a sharpness beta, as its formula reads."""

import torch


def softplus(x: torch.Tensor, beta: float = 1.0, threshold: float = 20.0) -> torch.Tensor:
    """``x`` where ``beta x > threshold``, else ``log(1 + exp(beta x)) / beta`` (differentiable
    by autograd)."""
    z = x * beta
    return torch.where(z > threshold, x, torch.log1p(torch.exp(z.clamp_max(threshold))) / beta)
