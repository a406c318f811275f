"""Positional (frequency) encoding: x -> [x, sin(2^k x), cos(2^k x)] for k = 0..n_freqs-1."""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["PositionalEncoding", "HashEncoding", "SphericalHarmonics"]


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


class HashEncoding(nn.Module):
    """Learnable multiresolution hash-grid encoding (Warp kernels, hand-written backward) of
    points in [0, 1]^3: ``forward(x [n, 3]) -> [n, n_levels * n_features]``.

    The table is initialised uniformly in [-1e-4, 1e-4] (instant-ngp's choice: near-zero features,
    so the first layers see almost only their biases and the grid fills in where data needs it).
    """

    def __init__(self, grid=None):
        super().__init__()
        from ..ops.encoding import HashGrid

        self.grid = grid or HashGrid()
        self.table = nn.Parameter(
            torch.empty(self.grid.n_rows, self.grid.n_features).uniform_(-1e-4, 1e-4)
        )
        self.out_dim = self.grid.out_dim

    def forward(self, x: torch.Tensor, given: torch.Tensor | None = None,
                centred: bool = False) -> torch.Tensor:  # fmt: skip
        """``given``: this encoding of ``x`` computed before without gradients (returned with
        the gradient attached, see :func:`warpnerf.ops.encoding.hash_encode_given`);
        ``centred``: rows [2 x - 1, features] (:func:`~warpnerf.ops.encoding.hash_encode`)."""
        from ..ops.encoding import hash_encode, hash_encode_given

        if given is not None:
            if centred:
                raise ValueError("given features are never centred")
            return hash_encode_given(x, self.table.to(x.dtype), self.grid, given)
        return hash_encode(x, self.table.to(x.dtype), self.grid, centred=centred)


class SphericalHarmonics(nn.Module):
    """Real spherical harmonics of unit directions up to ``degree`` (1..4): ``degree^2`` values
    (the usual orthonormal basis, constants as in instant-ngp / tiny-cuda-nn)."""

    def __init__(self, degree: int = 4):
        super().__init__()
        if not 1 <= degree <= 4:
            raise ValueError(f"degree must be 1..4, got {degree}")
        self.degree, self.out_dim = degree, degree * degree

    def forward(self, d: torch.Tensor) -> torch.Tensor:  # [n, 3] -> [n, degree^2]
        from ..ops.encoding import spherical_harmonics

        return spherical_harmonics(d, self.degree)
