"""The NeRF MLP: positional encoding, a skip connection, a density head and a colour head that
sees the view direction only after the density branch (so density cannot depend on it)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .encoding import PositionalEncoding
from .model import FieldTraits, RadianceModel, register_field
from .settings import MLPConfig

__all__ = ["NeRFField"]


class NeRFField(nn.Module):
    """``forward(positions [n, 3], directions [n, 3]) -> (sigmas [n], rgbs [n, 3])``.

    Args:
        n_layers, width: trunk depth and width (the original: 8 x 256); ``skip`` re-injects the
            encoded position before that layer (0-based; 4 in the original).
        pos_freqs, dir_freqs: encoding frequencies for positions and directions (10 and 4).
        view_dependence: feed the encoded direction to the colour head; off, colour depends on
            position only (fewer parameters, cannot show specular highlights).
        density_activation: "relu" (the original) or "softplus" (no dead rays at initialisation;
            shifted by -1 so empty space starts near zero density).
        pos_scale: positions are multiplied by this before encoding (fit the scene into ~[-pi, pi]).
    """

    def __init__(
        self,
        n_layers=8,
        width=256,
        skip=4,
        pos_freqs=10,
        dir_freqs=4,
        view_dependence=True,
        density_activation="softplus",
        pos_scale=1.0,
    ):
        super().__init__()
        if density_activation not in ("relu", "softplus"):
            raise ValueError(f"density_activation: relu or softplus, got {density_activation}")
        self.pos_enc = PositionalEncoding(pos_freqs)
        self.view_dependence = view_dependence
        self.dir_enc = PositionalEncoding(dir_freqs) if view_dependence else None
        self.skip, self.density_activation, self.pos_scale = skip, density_activation, pos_scale
        d_in = self.pos_enc.out_dim
        layers = []
        for i in range(n_layers):
            fan_in = d_in if i == 0 else width
            if i == skip and i > 0:
                fan_in += d_in
            layers.append(nn.Linear(fan_in, width))
        self.trunk = nn.ModuleList(layers)
        self.sigma_head = nn.Linear(width, 1)
        self.feature = nn.Linear(width, width)
        d_dir = self.dir_enc.out_dim if view_dependence else 0
        self.color_hidden = nn.Linear(width + d_dir, width // 2)
        self.color_out = nn.Linear(width // 2, 3)

    def density(self, positions: torch.Tensor):
        """sigmas [n] and the trunk's features [n, width]."""
        x = self.pos_enc(positions * self.pos_scale)
        h = x
        for i, layer in enumerate(self.trunk):
            if i == self.skip and i > 0:
                h = torch.cat([h, x], -1)
            h = F.relu(layer(h))
        raw = self.sigma_head(h).squeeze(-1)
        sigma = F.relu(raw) if self.density_activation == "relu" else F.softplus(raw - 1.0)
        return sigma, h

    kind = "density"  # the field protocol (see VolSDFField for an "sdf" field)

    def aux_losses(self) -> dict:
        """Regularisers of the last forward pass: none for this field."""
        return {}

    def forward(self, positions: torch.Tensor, directions: torch.Tensor | None = None):
        sigma, h = self.density(positions)
        feat = self.feature(h)
        if self.view_dependence:
            if directions is None:
                raise ValueError("a view-dependent field needs directions")
            feat = torch.cat([feat, self.dir_enc(directions)], -1)
        rgb = torch.sigmoid(self.color_out(F.relu(self.color_hidden(feat))))
        return sigma, rgb

    def n_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())


# the built-in field `mlp`, registered as an added field is (docs/ARCHITECTURE.md)
@register_field("mlp", FieldTraits(config=(MLPConfig,)))  # density, samples near..far
def _mlp(cfg) -> RadianceModel:
    """NeRF's MLP (positional encoding, skip connection); a second one for the fine pass."""

    def make():
        return NeRFField(
            cfg.n_layers, cfg.width, cfg.skip, cfg.pos_freqs, cfg.dir_freqs,
            cfg.view_dependence, cfg.density_activation,
        )  # fmt: skip

    coarse = make()
    return RadianceModel(coarse, make() if cfg.n_fine > 0 else None)
