"""A neural signed distance function: positional encoding + MLP with geometric initialisation.

Geometric initialisation (Atzmon & Lipman, SAL 2020; as in IDR/NeuS): hidden layers N(0, 2/width),
the last layer N(sqrt(pi / width), 1e-4) with bias -radius, and the encoded (non-raw) inputs'
first-layer weights zero, so that at initialisation f(x) ~ |x| - radius: a sphere. Softplus
(beta = 100) activations keep f smooth, so the eikonal term's double backward is well defined.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from .encoding import PositionalEncoding

__all__ = ["NeuralSDF"]


class NeuralSDF(nn.Module):
    """``forward(points [n, 3]) -> sdf [n]``; ``gradient(points)`` -> (sdf [n], grad [n, 3]);
    ``with_features(points)`` -> (sdf [n], features [n, n_features]) for VolSDF's colour net."""

    def __init__(self, n_layers=6, width=128, skip=3, pos_freqs=6, radius=0.5, softplus_beta=100,
                 n_features=0):  # fmt: skip
        super().__init__()
        self.enc = PositionalEncoding(pos_freqs)
        self.skip, self.beta = skip, softplus_beta
        d_in = self.enc.out_dim
        if skip < n_layers and width <= d_in:
            raise ValueError(f"width {width} must exceed the encoded input size {d_in} (skip)")
        self.layers = nn.ModuleList()
        for i in range(n_layers):
            fan_in = d_in if i == 0 else width
            fan_out = width - d_in if (i + 1 == skip and skip < n_layers) else width
            layer = nn.Linear(fan_in, fan_out)
            nn.init.normal_(layer.weight, 0.0, math.sqrt(2.0) / math.sqrt(fan_out))
            nn.init.zeros_(layer.bias)
            if i == 0 and pos_freqs > 0:
                nn.init.zeros_(layer.weight[:, 3:])  # only the raw xyz start non-zero
            if i == skip and pos_freqs > 0:
                nn.init.zeros_(layer.weight[:, -(d_in - 3) :])
            self.layers.append(layer)
        self.out = nn.Linear(width, 1 + n_features)
        nn.init.normal_(self.out.weight[:1], math.sqrt(math.pi) / math.sqrt(width), 1e-4)
        nn.init.constant_(self.out.bias[:1], -radius)
        self.n_features = n_features

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return self.with_features(points)[0]

    def with_features(self, points: torch.Tensor):
        x = self.enc(points)
        h = x
        for i, layer in enumerate(self.layers):
            if i == self.skip and i > 0:
                h = torch.cat([h, x], -1) / math.sqrt(2.0)
            h = F.softplus(layer(h), beta=self.beta)
        out = self.out(h)
        return out[:, 0], out[:, 1:]

    def gradient(self, points: torch.Tensor, create_graph: bool = True):
        """(sdf [n], d sdf / d points [n, 3]); create_graph for losses on the gradient."""
        with torch.enable_grad():
            p = points if points.requires_grad else points.detach().requires_grad_(True)
            f = self(p)
            (g,) = torch.autograd.grad(f.sum(), p, create_graph=create_graph)
        return f, g
