"""The seed's analytic SDF volume: a box, sphere or torus turned into per-sample opacity.

With Psi_beta the CDF of a zero-mean Laplace distribution of scale beta, a sample at p has opacity
``o = alpha * Psi_beta(-sdf(p))`` = alpha * 0.5 exp(-sdf / beta) outside and
alpha * (1 - 0.5 exp(sdf / beta)) inside, so the shape is opaque at its surface. Used as per-sample
opacity by the box demos (``render_*(..., alphas=o)``); VolSDF uses the same value as a density.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["SDFVolume", "laplace_cdf", "sdf_box", "sdf_sphere", "sdf_torus"]


def laplace_cdf(s: torch.Tensor, beta) -> torch.Tensor:
    """CDF of Laplace(0, beta) at s, stable for tiny beta: exp only ever sees a value <= 0, so
    nothing overflows and the gradient (0.5 / beta) exp(-|s| / beta) is finite everywhere."""
    neg = torch.where(s <= 0, s, -s)  # -|s| with derivative +1 at s = 0 (the left branch)
    e = 0.5 * torch.exp(neg / beta)
    return torch.where(s <= 0, e, 1.0 - e)


def _norm(x: torch.Tensor) -> torch.Tensor:
    """|x| over the last axis, with first and second derivatives 0 (finite) at x = 0.

    torch's norm has gradient x / |x| masked to 0 at x = 0, but the derivative of that (needed
    by an eikonal loss, a double backward) is NaN there: at a sphere's centre, on a torus' axis
    and core ring, and on a box's faces, edges and corners (where the clamped outside vector is 0
    but its gradient is live). Zero rows are swapped for ones before the norm and given 0 after.
    """
    zero = (x == 0).all(-1, keepdim=True)
    n = torch.linalg.vector_norm(torch.where(zero, torch.ones_like(x), x), dim=-1)
    return torch.where(zero.squeeze(-1), torch.zeros_like(n), n)


def sdf_box(p: torch.Tensor, center: torch.Tensor, side_lengths: torch.Tensor) -> torch.Tensor:
    """Exact box SDF: |max(q, 0)| + min(max_k q_k, 0), q = |p - c| - s / 2. p [n, 3] -> [n]."""
    q = (p - center).abs() - 0.5 * side_lengths
    outside = _norm(q.clamp_min(0.0))
    inside = q.amax(-1).clamp_max(0.0)
    return outside + inside


def sdf_sphere(p: torch.Tensor, center: torch.Tensor, radius) -> torch.Tensor:
    return _norm(p - center) - radius


def sdf_torus(p: torch.Tensor, center: torch.Tensor, major: float, minor: float) -> torch.Tensor:
    """Torus around the y axis: |(|q_xz| - R, q_y)| - r."""
    q = p - center
    ring = _norm(q[:, [0, 2]]) - major
    return _norm(torch.stack([ring, q[:, 1]], -1)) - minor


class SDFVolume(nn.Module):
    """Analytic SDF scene as an opacity field. Parameters: center [3], side_lengths [3] (box),
    radius (sphere), major/minor radius (torus); alpha, beta of the Laplace CDF.

    ``color``: "rainbow" (the seed's clamp(|p - center|, 0.02, 0.98) per channel) or an RGB triple.
    ``forward(points [n, 3], directions [n, 3] | None) -> (opacity [n], rgb [n, 3])``.
    """

    SHAPES = ("box", "sphere", "torus")

    def __init__(
        self,
        shape="box",
        center=(0.0, 0.0, 0.0),
        side_lengths=(1.0, 1.0, 1.0),
        radius=0.5,
        major_radius=0.6,
        minor_radius=0.25,
        alpha=1.0,
        beta=0.05,
        color="rainbow",
        dtype=torch.float32,
    ):
        super().__init__()
        if shape not in self.SHAPES:
            raise ValueError(f"shape must be one of {self.SHAPES}, got {shape!r}")
        if not beta > 0 or not 0 < alpha <= 1:
            raise ValueError(f"need beta > 0 and 0 < alpha <= 1, got beta={beta}, alpha={alpha}")
        self.shape = shape
        self.center = nn.Parameter(torch.tensor(center, dtype=dtype))
        self.side_lengths = nn.Parameter(torch.tensor(side_lengths, dtype=dtype))
        self.radius, self.major_radius, self.minor_radius = radius, major_radius, minor_radius
        self.alpha, self.beta = alpha, beta
        if color != "rainbow":
            color = torch.tensor(color, dtype=dtype).reshape(3)
        self.color_mode = color

    def sdf(self, points: torch.Tensor) -> torch.Tensor:  # [n, 3] -> [n]
        if self.shape == "box":
            return sdf_box(points, self.center, self.side_lengths)
        if self.shape == "sphere":
            return sdf_sphere(points, self.center, self.radius)
        return sdf_torus(points, self.center, self.major_radius, self.minor_radius)

    def opacity(self, points: torch.Tensor) -> torch.Tensor:  # [n, 3] -> [n]
        return self.alpha * laplace_cdf(-self.sdf(points), self.beta)

    def color(self, points: torch.Tensor) -> torch.Tensor:  # [n, 3] -> [n, 3]
        if isinstance(self.color_mode, str):
            return (points - self.center).abs().clamp(0.02, 0.98)
        return self.color_mode.to(points).expand(points.shape[0], 3)

    def forward(self, points, directions=None):
        return self.opacity(points), self.color(points)
