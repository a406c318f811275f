"""The ``toy_mlp`` field: a small MLP radiance field (raw positions in, no encoding), with its
own setting ``--toy-hidden``. Importing this module registers it (the entry point)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from warpnerf.fields import FieldTraits, RadianceModel, register_field
from warpnerf.options import option


@dataclass
class ToyOptions:
    """The toy field's own settings (flags of `train nerf --field toy_mlp`)."""

    toy_hidden: int = option(16, "hidden width of the toy MLP", check="positive")


class ToyField(nn.Module):
    kind = "density"

    def __init__(self, hidden: int):
        super().__init__()
        self.trunk = nn.Sequential(nn.Linear(3, hidden), nn.ReLU(), nn.Linear(hidden, 1 + hidden))
        self.rgb = nn.Linear(hidden, 3)

    def density(self, x):  # x [n, 3] -> (sigma [n], features [n, hidden])
        h = self.trunk(x)
        return torch.nn.functional.softplus(h[:, 0] - 1.0), h[:, 1:]

    def color(self, x, d, features):  # -> rgb [n, 3]
        return torch.sigmoid(self.rgb(torch.relu(features)))

    def forward(self, x, d=None):
        s, h = self.density(x)
        return s, self.color(x, d, h)

    def aux_losses(self):
        return {}


@register_field("toy_mlp", FieldTraits(lr=1e-3, options=ToyOptions))
def _toy(cfg):
    return RadianceModel(ToyField(cfg.field_settings().toy_hidden))
