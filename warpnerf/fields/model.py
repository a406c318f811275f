"""The model of a NeRF or VolSDF run (:class:`RadianceModel`) and the registry of radiance
fields that builds it from a config (:data:`FIELDS`, :func:`register_field`, :func:`build_model`).

A field is an ``nn.Module`` with a declared ``kind`` ("density": ``density(x) -> (sigma,
features)``; "sdf": a signed distance turned into a density by the field itself, e.g. VolSDF's
Laplace CDF), ``color(x, d, features)``, ``forward(x, d) -> (sigma, rgb)`` and ``aux_losses()``
(the regularisers of its last forward pass with gradients). The model holds the field of the
coarse pass, the fine pass's field (None, or the same module when one network serves both) and
the occupancy grid (None without one); it is what a run checkpoints (:meth:`parts`) and what the
renderers of train/nerf.py take.

Adding a field: write the module (one new file in ``warpnerf/fields/``), then one builder::

    @register_field("myfield")
    def _my_field(cfg):
        return RadianceModel(MyField(cfg.width).to(cfg.device))

and ``--field myfield`` trains it (the config's choices come from this registry).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

__all__ = ["RadianceModel", "FIELDS", "register_field", "build_model"]


class RadianceModel(nn.Module):
    """The coarse field, the fine field (None or the same module) and the occupancy grid (None)
    of a run. Parameters shared by both passes are counted once (``parameters()``)."""

    def __init__(self, coarse: nn.Module, fine: nn.Module | None = None, grid=None):
        super().__init__()
        self.coarse = coarse
        self._fine_is_coarse = fine is coarse
        self.fine_field = None if fine is coarse else fine
        self.grid = grid
        self.poses = None  # pose refinement: a CameraCorrection of the training cameras

    @property
    def fine(self) -> nn.Module | None:
        return self.coarse if self._fine_is_coarse else self.fine_field

    @property
    def kind(self) -> str:
        return self.coarse.kind

    @property
    def field(self) -> nn.Module:
        """The field that renders final images (the fine one when there is one)."""
        return self.fine if self.fine is not None else self.coarse

    def parts(self) -> dict:
        """{"coarse", "fine", "grid"[, "poses"]}: each module once (None for a fine pass that
        shares the coarse network, or that is absent; "poses" only with pose refinement): the
        layout of a checkpoint's ``fields``."""
        parts = {"coarse": self.coarse, "fine": self.fine_field, "grid": self.grid}
        if self.poses is not None:
            parts["poses"] = self.poses
        return parts

    def load_parts(self, saved, path) -> None:
        """Loads a checkpoint's ``fields`` (the layout of :meth:`parts`): every part this model
        has must be there with each of its parameters and buffers of their shapes (a strict
        load), and no part the model lacks may be; a :class:`~warpnerf.errors.UserError` naming
        checkpoint ``path`` and the part or key otherwise (nothing is left freshly initialised).
        """
        from ..errors import UserError
        from ..io import load_weights

        parts = self.parts()
        if not isinstance(saved, dict):
            raise UserError(f"{path}: entry 'fields' must be a dict of the model's parts")
        held = sorted(str(k) for k, v in saved.items() if v is not None)
        for k, m in parts.items():
            if m is not None and saved.get(k) is None:
                raise UserError(
                    f"{path}: the checkpoint has no weights for the {k} part that the run's "
                    f"config.json gives the model ('fields' holds {held or 'nothing'})"
                )
        for k in held:
            if parts.get(k) is None:
                raise UserError(
                    f"{path}: the checkpoint holds a {k!r} part that the model of the run's "
                    "config.json does not have (was the config edited?)"
                )
        for k, m in parts.items():
            if m is not None:
                load_weights(m, saved[k], path, f"{k} field's weights")

    def eikonal_parts(self) -> list:
        """(mean, sample count) of each SDF field's eikonal term at its last rendered samples,
        coarse then fine ((None, 0) for a field without one), taken once like
        :meth:`aux_losses`: the parts a data-parallel rank needs for the mean over every rank's
        samples."""
        out = []
        for f in (self.coarse, self.fine_field):
            if f is None:
                continue
            mean = f.aux_losses().get("eikonal")
            n = getattr(f, "_aux_n", {}).get("eikonal", 0) if mean is not None else 0
            out.append((mean, n))
        return out

    def aux_losses(self) -> dict:
        """The regularisers of the fields' last forward passes (e.g. VolSDF's eikonal term)."""
        out = dict(self.coarse.aux_losses())
        if self.fine_field is not None:
            for k, v in self.fine_field.aux_losses().items():
                out[k] = out[k] + v if k in out else v
        return out


# name -> builder(cfg) -> RadianceModel; cfg is a NeRFConfig (resolved by the builder if needed)
FIELDS: dict[str, Callable] = {}


def register_field(name: str):
    """Decorator: registers ``builder(cfg) -> RadianceModel`` under ``name`` (``--field name``)."""

    def add(builder):
        if name in FIELDS:
            raise ValueError(f"field {name!r} is registered already")
        FIELDS[name] = builder
        return builder

    return add


def build_model(cfg) -> RadianceModel:
    """The model of config ``cfg`` (its ``field`` names a registered builder), initialised from
    ``cfg.seed``, on ``cfg.device``."""
    if cfg.field not in FIELDS:
        raise ValueError(f"unknown field {cfg.field!r}; registered: {', '.join(FIELDS)}")
    torch.manual_seed(cfg.seed)
    model = FIELDS[cfg.field](cfg)
    if getattr(cfg, "pose_refine", False):
        from ..errors import UserError
        from .poses import CameraCorrection

        if cfg.pose_images < 1:  # (a run's config without the count)
            raise UserError("pose_refine needs pose_images >= 1 (the training images)")
        model.poses = CameraCorrection(cfg.pose_images)
    return model.to(cfg.device)


@register_field("mlp")
def _mlp(cfg) -> RadianceModel:
    """NeRF's MLP (positional encoding, skip connection); a second one for the fine pass."""
    from .nerf import NeRFField

    def make():
        return NeRFField(
            cfg.n_layers, cfg.width, cfg.skip, cfg.pos_freqs, cfg.dir_freqs,
            cfg.view_dependence, cfg.density_activation,
        )  # fmt: skip

    coarse = make()
    return RadianceModel(coarse, make() if cfg.n_fine > 0 else None)


def _contraction(cfg) -> dict:
    """The grid's contraction settings of a run with ``--contract on`` ({} otherwise)."""
    if getattr(cfg, "contract", "off") != "on":
        return {}
    return {"contract": float(cfg.aabb), "cone": float(cfg.march_cone)}


def _on_grid(cfg, f, box) -> RadianceModel:
    """The model of a hash field ``f``: with the occupancy grid when ``cfg.grid_res`` > 0 (then
    no fine pass), else ``f`` serves the fine pass too when there is one."""
    from ..occupancy import OccupancyGrid

    grid = None
    if cfg.grid_res:
        grid = OccupancyGrid(
            box, cfg.grid_res, dt=cfg.march_step, occ_threshold=cfg.occ_threshold,
            warmup=-(-cfg.grid_warmup // cfg.grid_every), **_contraction(cfg),
        )  # fmt: skip
    return RadianceModel(f, f if cfg.n_fine > 0 and not cfg.grid_res else None, grid)


@register_field("hash")
def _hash(cfg) -> RadianceModel:
    """Hash-grid encoding + small MLPs, one network for both passes; the occupancy grid when
    ``cfg.grid_res`` > 0 (then there is no fine pass)."""
    from ..ops.encoding import HashGrid
    from .hash_nerf import HashNeRFField

    box = cfg.resolve().aabb_box()
    from ..errors import UserError

    app = None
    if cfg.appearance_dim > 0:
        if cfg.appearance_images < 1:  # (a run's config without the count: no mean code)
            raise UserError("appearance_dim needs appearance_images >= 1 (the training images)")
        app = (cfg.appearance_images, cfg.appearance_dim)
    f = HashNeRFField(box, HashGrid(**cfg._grid_kwargs()), cfg.hidden, cfg.view_dependence, app,
                      contract=_contraction(cfg).get("contract", 0.0))  # fmt: skip
    return _on_grid(cfg, f, box)


@register_field("volsdf")
def _volsdf(cfg) -> RadianceModel:
    """A neural SDF rendered through VolSDF's Laplace density; one network for both passes."""
    from .volsdf import VolSDFField

    cfg.resolve()
    f = VolSDFField(
        cfg.aabb, cfg.n_layers, cfg.width, cfg.skip, cfg.pos_freqs, cfg.dir_freqs,
        n_features=cfg.width, color_width=cfg.width, view_dependence=cfg.view_dependence,
        beta=cfg.beta, beta_min=cfg.beta_min, learn_beta=cfg.learn_beta,
    )  # fmt: skip
    return RadianceModel(f, f if cfg.n_fine > 0 else None)


@register_field("hash_sdf")
def _hash_sdf(cfg) -> RadianceModel:
    """A hash-grid SDF with VolSDF's density on the occupancy-grid fast path (hash_sdf.py)."""
    from ..ops.encoding import HashGrid
    from .hash_sdf import HashSDFField

    box = cfg.resolve().aabb_box()
    f = HashSDFField(
        box, HashGrid(**cfg._grid_kwargs()), cfg.hidden, view_dependence=cfg.view_dependence,
        beta=cfg.beta, beta_min=cfg.beta_min, learn_beta=cfg.learn_beta,
        level_every=cfg.c2f_every, density=cfg.sdf_density, beta_final=cfg.beta_final,
        anneal_steps=cfg.beta_anneal_steps, color_direction=cfg.color_direction,
    )  # fmt: skip
    return _on_grid(cfg, f, box)
