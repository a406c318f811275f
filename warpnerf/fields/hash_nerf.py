"""A fast NeRF field: hash-grid encoding (Warp kernels) + small torch MLPs (instant-ngp's design).

density: positions in the scene box -> hash features [L * F] -> MLP (one hidden layer) -> 16
values; sigma = exp(first value) (truncated: the exponent is clamped at 15 in the forward pass,
its gradient is not cut), zero outside the box. colour: those 16 values + spherical harmonics of
the direction (degree 4; left out without view dependence) [+ the image's appearance code] -> MLP
(two hidden layers) -> sigmoid.

Unbounded scenes (``contract=a``): positions are first contracted (the inner cube [-a, a]^3 as it
is, everything beyond squeezed into [-2a, 2a]^3, :func:`warpnerf.ops.occupancy.contract_points`)
and the grid covers that cube, so all of space has density.
"""

from __future__ import annotations

import torch
from torch import nn

from ..ops.encoding import HashGrid, sh_concat
from ..ops.occupancy import contract_points, is_contracted_box
from ..options import section_of
from .encoding import HashEncoding, SphericalHarmonics
from .mlp import run_mlp, trunc_exp
from .model import FieldTraits, RadianceModel, register_field
from .settings import HashConfig

__all__ = ["HashNeRFField", "hash_grid_of", "with_occupancy_grid"]

GEO_FEATURES = 16  # density MLP outputs: raw density + 15 features for the colour MLP


def _one_kernel(h: torch.Tensor, directions: torch.Tensor) -> bool:
    """Whether the colour MLP's input [h | SH(d)] can be one kernel (sh_concat): float32, and
    directions without a gradient (pose refinement gives them one: torch's ops then)."""
    return h.dtype == directions.dtype == torch.float32 and not directions.requires_grad


class HashNeRFField(nn.Module):
    """``forward(positions [n, 3], directions [n, 3]) -> (sigmas [n], rgbs [n, 3])``.

    Args:
        aabb: scene box [xmin, ymin, zmin, xmax, ymax, zmax]; the grid covers it, density is zero
            outside it.
        grid: a :class:`warpnerf.ops.HashGrid` (levels, table size, resolutions).
        hidden: width of the MLPs' hidden layers.
        view_dependence: feed SH-encoded directions to the colour MLP.
        appearance: (n_images, dim): a learned code of ``dim`` values per training image, fed
            to the colour MLP (NeRF-W / nerfstudio's appearance embedding: exposure and white
            balance that change between photos); ``color(..., image_ids=None)`` (held-out views)
            uses the mean of the codes. None: no codes.
        contract: 0, or the inner half-size a of an unbounded scene (aabb is then the contracted
            cube [-2a, 2a]^3).
    """

    mlp_dtype = None  # the MLPs' autocast dtype (fields/mlp.py's mlp_precision sets it)

    def __init__(self, aabb, grid: HashGrid | None = None, hidden=64, view_dependence=True,
                 appearance: tuple | None = None, contract: float = 0.0):  # fmt: skip
        super().__init__()
        box = torch.as_tensor(aabb, dtype=torch.float32).reshape(-1)
        if box.shape != (6,) or not bool((box[3:] > box[:3]).all()):
            raise ValueError("aabb must be [xmin, ymin, zmin, xmax, ymax, zmax] with min < max")
        self.contract = float(contract)
        if self.contract and not is_contracted_box(box, self.contract):
            raise ValueError("a contracted field's aabb must be the cube [-2a, 2a]^3, a = contract")
        self.register_buffer("aabb", box)
        self.encoding = HashEncoding(grid)
        self.view_dependence = view_dependence
        self.sh = SphericalHarmonics(4) if view_dependence else None
        self.density_mlp = nn.Sequential(
            nn.Linear(self.encoding.out_dim, hidden), nn.ReLU(), nn.Linear(hidden, GEO_FEATURES)
        )
        d_col = GEO_FEATURES + (self.sh.out_dim if view_dependence else 0)
        self.appearance = None
        if appearance is not None:
            n_images, dim = (int(v) for v in appearance)
            self.appearance = nn.Embedding(n_images, dim)
            nn.init.zeros_(self.appearance.weight)  # (the mean code: zero until trained)
            d_col += dim
        self.color_mlp = nn.Sequential(
            nn.Linear(d_col, hidden),
            nn.ReLU(),
            nn.Linear(hidden, hidden),
            nn.ReLU(),
            nn.Linear(hidden, 3),
        )

    def _unit(self, positions: torch.Tensor) -> torch.Tensor:
        """Positions in the grid's unit cube (contracted first in an unbounded scene)."""
        lo, hi = self.aabb[:3].to(positions.dtype), self.aabb[3:].to(positions.dtype)
        x = positions  # (a gradient reaches the positions only when they need one: poses)
        if self.contract:
            x = contract_points(x, self.contract)
        return (x - lo) / (hi - lo)

    def encode(self, positions: torch.Tensor) -> torch.Tensor:
        """The hash encoding of positions [n, L * F] (for :meth:`density`'s ``encoded``)."""
        return self.encoding(self._unit(positions))

    def density(self, positions: torch.Tensor, encoded: torch.Tensor | None = None):
        """sigmas [n] and the density MLP's outputs [n, 16]. ``encoded``: :meth:`encode` of
        these positions, computed before without gradients (a renderer's first pass): the
        encoding's forward does not run again, its gradient does."""
        x = self._unit(positions)
        inside = ((x >= 0) & (x <= 1)).all(-1)
        h = run_mlp(self.density_mlp, self.encoding(x, given=encoded), self.mlp_dtype)
        sigma = trunc_exp(h[:, 0]) * inside.to(h.dtype)
        return sigma, h

    def color(self, h: torch.Tensor, directions: torch.Tensor | None = None, image_ids=None):
        """rgbs [n, 3] from the density MLP's outputs h [n, 16] (and directions [n, 3]; with
        appearance codes, ``image_ids`` [n] int: each sample's training image, None: the codes'
        mean)."""
        feat = [h]
        if self.view_dependence:
            if directions is None:
                raise ValueError("a view-dependent field needs directions")
            if self.appearance is None and _one_kernel(h, directions):  # [h | SH(d)]
                return torch.sigmoid(run_mlp(self.color_mlp,
                                             sh_concat(h, directions, self.sh.degree),
                                             self.mlp_dtype))  # fmt: skip
            feat.append(self.sh(directions.to(h.dtype)))
        if self.appearance is not None:
            if image_ids is None:
                code = self.appearance.weight.mean(0).to(h.dtype).expand(h.shape[0], -1)
            else:
                code = self.appearance(image_ids.to(h.device, torch.int64)).to(h.dtype)
            feat.append(code)
        x = torch.cat(feat, -1) if len(feat) > 1 else h
        return torch.sigmoid(run_mlp(self.color_mlp, x, self.mlp_dtype))

    kind = "density"  # the field protocol (see VolSDFField for an "sdf" field)

    def aux_losses(self) -> dict:
        """Regularisers of the last forward pass: none for this field."""
        return {}

    def forward(self, positions: torch.Tensor, directions: torch.Tensor | None = None):
        sigma, h = self.density(positions)
        return sigma, self.color(h, directions)

    def n_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())


# the built-in field `hash`, registered as an added field is (docs/ARCHITECTURE.md), and the
# helpers the hash fields' builders share (hash_sdf.py)


def hash_grid_of(cfg):
    """The hash encoding of a config's :class:`HashConfig` section."""
    return HashGrid(**section_of(cfg, HashConfig).grid_kwargs())


def _contraction(cfg) -> dict:
    """The grid's contraction settings of a run with ``--contract on`` ({} otherwise)."""
    if getattr(cfg, "contract", "off") != "on":
        return {}
    return {"contract": float(cfg.aabb), "cone": float(cfg.march_cone)}


def with_occupancy_grid(cfg, f, box) -> RadianceModel:
    """The model of a hash field ``f``: with the occupancy grid when ``cfg.grid_res`` > 0 (then
    no fine pass), else ``f`` serves the fine pass too when there is one."""
    from ..occupancy import OccupancyGrid

    grid = None
    proposal = getattr(cfg, "sampler", "grid") == "proposal"  # (its nets replace the grid)
    if cfg.grid_res and not proposal:
        grid = OccupancyGrid(
            box, cfg.grid_res, dt=cfg.march_step, occ_threshold=cfg.occ_threshold,
            warmup=-(-cfg.grid_warmup // cfg.grid_every), **_contraction(cfg),
        )  # fmt: skip
    model = RadianceModel(f, f if cfg.n_fine > 0 and not cfg.grid_res else None, grid)
    if proposal:
        from .proposal import proposal_sampler_of

        model.proposal = proposal_sampler_of(cfg)
    return model


@register_field("hash", FieldTraits(in_box=True, hash=True, grid=True, captures=True, lr=1e-2,
                                    lr_decay=20.0, config=(HashConfig,)))  # fmt: skip
def _hash(cfg) -> RadianceModel:
    """Hash-grid encoding + small MLPs, one network for both passes; the occupancy grid when
    ``cfg.grid_res`` > 0 (then there is no fine pass)."""
    box = cfg.aabb_box()
    from ..errors import UserError

    app = None
    if cfg.appearance_dim > 0:
        if cfg.appearance_images < 1:  # (a run's config without the count: no mean code)
            raise UserError("appearance_dim needs appearance_images >= 1 (the training images)")
        app = (cfg.appearance_images, cfg.appearance_dim)
    f = HashNeRFField(box, hash_grid_of(cfg), cfg.hidden, cfg.view_dependence, app,
                      contract=_contraction(cfg).get("contract", 0.0))  # fmt: skip
    return with_occupancy_grid(cfg, f, box)
