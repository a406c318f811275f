"""A hash-grid SDF for fitting point clouds (``warpnerf train sdf --field hash``): the geometry of
:class:`~warpnerf.fields.hash_sdf.HashSDFField` without its rendering parts, behind
:class:`~warpnerf.fields.neural_sdf.NeuralSDF`'s interface.

On the box [-1, 1]^3: the coordinates c and the Warp hash encoding of (c + 1) / 2 feed a small
Softplus MLP whose output is a residual on the sphere prior, f(c) = |c| - radius + mlp(c, enc)
(outside the box the residual is the one at the nearest box point).
The MLP's last layer starts at zero, so training starts from the exact sphere SDF (the role of
SAL's geometric initialisation).

Coarse to fine (Neuralangelo, Li et al. 2023): :meth:`set_open_levels` masks the finer levels
out, so early training fits a smooth field that can still change its topology (a hash grid with
all levels open keeps the parts of the initial sphere that no point touches: they satisfy the
eikonal equation).

The hash encoding gives no position gradient, so the gradient is a central finite difference of
step h (second order; one stencil of 7 points, the centre and +-h along each axis, in one
call): grad_i f(x) ~ (f(x + h e_i) - f(x - h e_i)) / (2 h), differentiable in the parameters,
which is all the eikonal term needs. h is ``fd_step``, or 0: the cell of the finest open level.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from ..ops.encoding import HashGrid
from .encoding import HashEncoding

__all__ = ["HashPointSDF", "central_gradient"]


def central_gradient(fn, points: torch.Tensor, h: float):
    """(fn(points) [n], central-difference gradient [n, 3]) of a scalar field ``fn`` at points
    [n, 3], from one call of ``fn`` on the 7-point stencil (the points, then +-h e_i)."""
    e = torch.eye(3, device=points.device, dtype=points.dtype) * h
    offsets = torch.cat([e.new_zeros(1, 3), e, -e]).unsqueeze(1)  # [7, 1, 3]
    d = fn((points.unsqueeze(0) + offsets).reshape(-1, 3)).reshape(7, -1)
    return d[0], ((d[1:4] - d[4:7]) / (2.0 * h)).T


class HashPointSDF(nn.Module):
    """``forward(points [n, 3]) -> sdf [n]``; ``gradient(points)`` -> (sdf [n], grad [n, 3]) by
    central differences (box units)."""

    def __init__(self, grid: HashGrid | None = None, width: int = 64, n_hidden: int = 2,
                 radius: float = 0.5, fd_step: float = 0.0):  # fmt: skip
        super().__init__()
        self.encoding = HashEncoding(grid)
        g = self.encoding.grid
        self.cells = [2.0 / res for res, _, _ in g.levels]  # box [-1, 1]^3: side 2
        self.radius, self.fixed_step = float(radius), float(fd_step)
        self.register_buffer("level_mask", torch.ones(g.out_dim), persistent=False)
        self.open_levels = g.n_levels
        layers, d_in = [], 3 + g.out_dim
        for _ in range(n_hidden):
            layers += [nn.Linear(d_in, width), nn.Softplus(beta=100)]
            nn.init.normal_(layers[-2].weight, 0.0, math.sqrt(2.0 / width))
            nn.init.zeros_(layers[-2].bias)
            d_in = width
        layers.append(nn.Linear(d_in, 1))
        nn.init.zeros_(layers[-1].weight)
        nn.init.zeros_(layers[-1].bias)
        self.mlp = nn.Sequential(*layers)

    def set_open_levels(self, n: int) -> None:
        """Uses the ``n`` coarsest hash levels (at least one); the others read as zero."""
        g = self.encoding.grid
        n = max(1, min(int(n), g.n_levels))
        if n != self.open_levels:
            self.level_mask.zero_()
            self.level_mask[: n * g.n_features] = 1.0
            self.open_levels = n

    @property
    def fd_step(self) -> float:
        """The finite-difference step: ``fd_step``, or the cell of the finest open level."""
        return self.fixed_step or self.cells[self.open_levels - 1]

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        p = points.detach()
        c = p.clamp(-1.0, 1.0)  # outside the box: the sphere prior + the residual at the box
        enc = self.encoding((c + 1.0) / 2.0) * self.level_mask.to(c.dtype)
        return p.norm(dim=-1) - self.radius + self.mlp(torch.cat([c, enc], -1))[:, 0]

    def gradient(self, points: torch.Tensor, create_graph: bool = True):
        """(sdf [n], d sdf / d points [n, 3]); ``create_graph``: differentiable in the
        parameters (for losses on the gradient), else computed without autograd."""
        with torch.set_grad_enabled(create_graph and torch.is_grad_enabled()):
            return central_gradient(self, points.detach(), self.fd_step)
