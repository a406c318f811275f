"""VolSDF (Yariv et al. 2021): a neural SDF whose Laplace-CDF density is volume-rendered.

density  sigma(x) = alpha * Psi_beta(-d(x)),  alpha = 1 / beta,
Psi_beta the CDF of a zero-mean Laplace distribution with scale beta (laplace_cdf: stable for
small beta). beta sets how far density spreads around the surface: large beta blurs the surface
into a thick fog (easy, smooth gradients early in training, soft geometry); small beta makes the
density a near step at d = 0 (sharp surfaces, but gradients only reach points close to the
surface, so training from a poor shape is slow). Here beta = beta_min + |b| is learned (VolSDF's
choice: it shrinks as the geometry sharpens) or fixed.

Colour: a network on (x, normal = grad d, encoded view direction, geometry features). The
geometry network works in unit coordinates x / bound so the positional encoding and the
geometric (sphere) initialisation fit the scene box; distances are scaled back to world units.
The eikonal residual of the last forward pass with gradients is kept for the trainer.
"""

from __future__ import annotations

import torch
from torch import nn

from .encoding import PositionalEncoding
from .model import FieldTraits, RadianceModel, register_field
from .neural_sdf import NeuralSDF
from .sdf_volume import laplace_cdf
from .settings import MLPConfig, SDFDensityConfig

__all__ = ["VolSDFField"]


class VolSDFField(nn.Module):
    """``forward(positions [n, 3], directions [n, 3]) -> (sigmas [n], rgbs [n, 3])``."""

    def __init__(self, bound=1.5, n_layers=8, width=256, skip=4, pos_freqs=6, dir_freqs=4,
                 n_features=256, color_width=256, view_dependence=True, beta=0.1,
                 beta_min=1e-4, learn_beta=True, radius=0.5):  # fmt: skip
        super().__init__()
        self.bound, self.beta_min, self.view_dependence = (
            float(bound),
            float(beta_min),
            view_dependence,
        )
        self.geometry = NeuralSDF(n_layers, width, skip, pos_freqs, radius, n_features=n_features)
        b = torch.tensor(max(beta - beta_min, 1e-8))
        self.beta_param = nn.Parameter(b) if learn_beta else None
        if not learn_beta:
            self.register_buffer("beta_fixed", b)
        self.dir_enc = PositionalEncoding(dir_freqs) if view_dependence else None
        d_in = 3 + 3 + n_features + (self.dir_enc.out_dim if view_dependence else 0)
        self.color = nn.Sequential(
            nn.Linear(d_in, color_width), nn.ReLU(), nn.Linear(color_width, color_width),
            nn.ReLU(), nn.Linear(color_width, 3),
        )  # fmt: skip
        self._aux = {}  # regularisers of the last forward with gradients (see aux_losses)

    kind = "sdf"  # the field protocol: "density" fields give sigma, "sdf" fields a distance

    def aux_losses(self) -> dict:
        """The regularisers of the last forward pass with gradients, once: {"eikonal": mean
        (|grad d| - 1)^2 at the rendered samples} (empty after it was taken, or without one)."""
        aux, self._aux = self._aux, {}
        return aux

    @property
    def beta(self) -> torch.Tensor:
        b = self.beta_param if self.beta_param is not None else self.beta_fixed
        return self.beta_min + b.abs()

    def sdf(self, points: torch.Tensor) -> torch.Tensor:
        """World-unit signed distance at points [n, 3]."""
        return self.geometry(points / self.bound) * self.bound

    def sdf_and_gradient(self, points: torch.Tensor, create_graph: bool):
        with torch.enable_grad():
            p = points.detach().requires_grad_(True)
            d, feat = self.geometry.with_features(p / self.bound)
            (g,) = torch.autograd.grad(d.sum(), p, create_graph=create_graph)
        return d * self.bound, g * self.bound, feat

    def gradient(self, positions: torch.Tensor) -> torch.Tensor:
        """The SDF's gradient [n, 3] (world units, autograd; no graph) at positions [n, 3]."""
        return self.sdf_and_gradient(positions, create_graph=False)[1].detach()

    def eikonal(self, points: torch.Tensor) -> torch.Tensor:
        """Mean (|grad d| - 1)^2 at points (differentiable)."""
        _, g, _ = self.sdf_and_gradient(points, create_graph=True)
        return ((g.norm(dim=-1) - 1.0) ** 2).mean()

    def forward(self, positions: torch.Tensor, directions: torch.Tensor | None = None):
        graph = torch.is_grad_enabled()
        d, g, feat = self.sdf_and_gradient(positions, create_graph=graph)
        if not graph:
            d, g, feat = d.detach(), g.detach(), feat.detach()
        else:
            self._aux = {"eikonal": ((g.norm(dim=-1) - 1.0) ** 2).mean()}
            self._aux_n = {"eikonal": int(g.shape[0])}  # (its sample count: data parallelism)
        beta = self.beta.to(d.dtype)
        sigma = laplace_cdf(-d, beta) / beta
        n = torch.nn.functional.normalize(g, dim=-1)
        parts = [positions / self.bound, n, feat]
        if self.view_dependence:
            if directions is None:
                raise ValueError("a view-dependent field needs directions")
            parts.append(self.dir_enc(directions))
        return sigma, torch.sigmoid(self.color(torch.cat(parts, -1)))

    def normals(self, positions: torch.Tensor) -> torch.Tensor:
        """Unit normals (no graph) at positions [n, 3]."""
        return torch.nn.functional.normalize(self.gradient(positions), dim=-1)


# the built-in field `volsdf`, registered as an added field is (docs/ARCHITECTURE.md)


def _check_volsdf(cfg, fail) -> None:
    d_in = 3 * (1 + 2 * cfg.pos_freqs)
    if cfg.width <= d_in:
        raise fail("width", f"must exceed the encoded position size {d_in} (volsdf)")


@register_field(
    "volsdf",
    FieldTraits(
        geometry="sdf",
        in_box=True,
        cpu_cost=3.0,
        check=_check_volsdf,
        config=(MLPConfig, SDFDensityConfig),
    ),
)  # (3: the eikonal double backward)
def _volsdf(cfg) -> RadianceModel:
    """A neural SDF rendered through VolSDF's Laplace density; one network for both passes."""
    f = VolSDFField(
        cfg.aabb, cfg.n_layers, cfg.width, cfg.skip, cfg.pos_freqs, cfg.dir_freqs,
        n_features=cfg.width, color_width=cfg.width, view_dependence=cfg.view_dependence,
        beta=cfg.beta, beta_min=cfg.beta_min, learn_beta=cfg.learn_beta,
    )  # fmt: skip
    return RadianceModel(f, f if cfg.n_fine > 0 else None)
