"""Positional (frequency) encoding: x -> [x, sin(2^k x), cos(2^k x)] for k = 0..n_freqs-1."""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["PositionalEncoding"]


class PositionalEncoding(nn.Module):
    """NeRF's frequency encoding of each input coordinate.

    ``gamma(x) = (x, sin(2^0 x), cos(2^0 x), ..., sin(2^(L-1) x), cos(2^(L-1) x))`` per coordinate
    (the input is included when ``include_input``); ``n_freqs = 0`` is the identity. Output size
    ``in_dim * (include_input + 2 * n_freqs)``.
    """

    def __init__(self, n_freqs: int, in_dim: int = 3, include_input: bool = True):
        super().__init__()
        if n_freqs < 0:
            raise ValueError(f"n_freqs must be >= 0, got {n_freqs}")
        if n_freqs == 0 and not include_input:
            raise ValueError("n_freqs = 0 without the input would encode nothing")
        self.n_freqs, self.in_dim, self.include_input = n_freqs, in_dim, include_input
        self.register_buffer(
            "freqs", 2.0 ** torch.arange(n_freqs, dtype=torch.float32), persistent=False
        )
        self.out_dim = in_dim * (int(include_input) + 2 * n_freqs)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # [n, in_dim] -> [n, out_dim]
        parts = [x] if self.include_input else []
        if self.n_freqs:
            xf = x.unsqueeze(-1) * self.freqs.to(x.dtype)  # [n, in_dim, L]
            parts += [torch.sin(xf).flatten(1), torch.cos(xf).flatten(1)]
        return torch.cat(parts, -1)
