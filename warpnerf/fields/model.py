"""The model of a NeRF or VolSDF run (:class:`RadianceModel`) and the registry of radiance
fields that builds it from a config (:data:`FIELDS`, :func:`register_field`, :func:`build_model`).

A field is an ``nn.Module`` with a declared ``kind`` ("density": ``density(x) -> (sigma,
features)``; "sdf": a signed distance turned into a density by the field itself, e.g. VolSDF's
Laplace CDF, with ``sdf(x)``, ``gradient(x)``, ``normals(x)`` and the density's scale ``beta``
for the mesh and geometry tools), ``color(x, d, features)``, ``forward(x, d) -> (sigma, rgb)``
and ``aux_losses()`` (the regularisers of its last forward pass with gradients). The model holds
the field of the coarse pass, the fine pass's field (None, or the same module when one network
serves both) and the occupancy grid (None without one); it is what a run checkpoints
(:meth:`parts`) and what the renderers of train/nerf.py take.

Adding a field: write the module (one new file in ``warpnerf/fields/``), then one builder::

    @register_field("myfield", FieldTraits(in_box=True, lr=1e-3, config=(MLPConfig,)))
    def _my_field(cfg):
        return RadianceModel(MyField(cfg.width).to(cfg.device))

and ``--field myfield`` trains it (the config's choices come from this registry). The built-in
fields register so in their own modules; an outside package names its module in the
``warpnerf.fields`` entry points (:mod:`warpnerf.plugins`). The field's
:class:`FieldTraits` are what the rest of the library knows of it: whether it is a density or an
SDF, whether it lives in the scene box, takes the hash flags or the occupancy grid, its
learning-rate defaults, the built-in config sections it reads (``config``: ``--width`` is
MLPConfig's; the command line refuses a section's flags for a field that does not read it).
Code asks the traits (``field_traits(name)``, ``cfg.traits``), never the field's name.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import nn

from ..plugins import Registry, add_entry

__all__ = [
    "RadianceModel", "FIELDS", "FieldTraits", "register_field", "field_traits", "fields_with",
    "build_model",
]  # fmt: skip


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
        self.proposal = None  # --sampler proposal: a ProposalSampler (fields/proposal.py)

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
        """{"coarse", "fine", "grid"[, "poses"][, "proposal"]}: each module once (None for a
        fine pass that shares the coarse network, or that is absent; "poses" only with pose
        refinement, "proposal" only with proposal sampling): the layout of a checkpoint's
        ``fields``."""
        parts = {"coarse": self.coarse, "fine": self.fine_field, "grid": self.grid}
        if self.poses is not None:
            parts["poses"] = self.poses
        if self.proposal is not None:
            parts["proposal"] = self.proposal
        return parts

    def load_parts(self, saved, path) -> None:
        """Loads a checkpoint's ``fields`` (the layout of :meth:`parts`): every part this model
        has must be there with each of its parameters and buffers of their shapes (a strict
        load), and no part the model lacks may be; a :class:`~warpnerf.errors.UserError` naming
        checkpoint ``path`` and the part or key otherwise (nothing is left freshly initialised).
        """
        from ..errors import UserError
        from ..outputs import load_weights

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


@dataclass(frozen=True)
class FieldTraits:
    """What the library needs to know of a registered field, declared with it.

    ``geometry``: "density" (a NeRF field: `train nerf`, depth supervision, pose refinement) or
    "sdf" (VolSDF's family: `train volsdf`, beta and the eikonal term, meshes, sphere tracing).
    ``in_box``: the field lives in the scene box [-aabb, aabb]^3 (an aabb is resolved for it).
    ``hash``: on the hash encoding (Adam with instant-ngp's eps 1e-15 for the sparse table
    updates; its flags are ``config``'s HashConfig). ``grid``: can march an occupancy
    grid, on by default (``--grid-res`` 128). ``captures``: the capture features (contraction of
    unbounded scenes, appearance codes, the distortion loss; on a COLMAP/LLFF capture the finest
    hash level defaults to 1024). ``beta_schedule``: takes ``--beta-final``, ``--sdf-density``
    and ``--color-direction``. ``lr``, ``lr_decay``: the default learning rate and its final
    value's divisor. ``eikonal_weight``: the default eikonal weight (SDF fields);
    ``sdf_gradient``: the default finite differences of a ``beta_schedule`` field's gradient
    (central or forward; ``--sdf-gradient``). ``photometric_loss``: the default colour loss
    (mse or huber; ``--photometric-loss``). ``cpu_cost``:
    the work per sample relative to the plain MLP or hash estimate (``--preset`` hints on a
    CPU): a number, or a function of the config where its options change it.
    ``check(cfg, fail)``: the field's own checks of a config (``fail(name, rule)`` builds the
    error to raise), or None. ``options``: the field's own settings, a dataclass declared
    with :func:`~warpnerf.options.option`: their flags are on `train nerf|volsdf` (for this
    field only), the run saves them in its config's ``field_options`` and the builder reads them
    as ``cfg.field_settings()``. ``config``: the built-in config sections its builder reads
    (fields/settings.py: MLPConfig, HashConfig, SDFDensityConfig): their checks apply to a run
    with this field, and ``--help`` names the fields that read each section."""

    geometry: str = "density"
    in_box: bool = False
    hash: bool = False
    grid: bool = False
    captures: bool = False
    beta_schedule: bool = False
    lr: float = 5e-4
    lr_decay: float = 10.0
    eikonal_weight: float = 0.1
    sdf_gradient: str = "central"
    photometric_loss: str = "mse"
    cpu_cost: float | Callable = 1.0
    check: Callable | None = None
    options: type | None = None
    config: tuple = ()

    def __post_init__(self):
        if self.geometry not in ("density", "sdf"):
            raise ValueError(f"geometry must be 'density' or 'sdf', got {self.geometry!r}")
        if self.captures and not self.grid:
            raise ValueError("the capture features need the occupancy grid (grid=True)")


# name -> builder(cfg) -> RadianceModel; cfg is a NeRFConfig (resolved by the builder if needed).
# The built-in fields register in their own modules (nerf.py: mlp, hash_nerf.py: hash, volsdf.py,
# hash_sdf.py; imported by the package in that order), an outside package's through the
# "warpnerf.fields" entry points (warpnerf/plugins.py), loaded when the registry is first read.
FIELDS: dict[str, Callable] = Registry("warpnerf.fields")
FIELD_TRAITS: dict[str, FieldTraits] = Registry("warpnerf.fields")
_NO_TRAITS = FieldTraits()


def register_field(name: str, traits: FieldTraits | None = None):
    """Decorator: registers ``builder(cfg) -> RadianceModel`` under ``name`` (``--field name``)
    with its :class:`FieldTraits` (default: a density field outside any box)."""

    def add(builder):
        if not add_entry(FIELDS, name, builder):
            raise ValueError(f"field {name!r} is registered already")
        FIELD_TRAITS[name] = traits or _NO_TRAITS
        return builder

    return add


def field_traits(name: str) -> FieldTraits:
    """The traits of field ``name``; an unregistered name has the defaults (its config's
    validation reports it)."""
    return FIELD_TRAITS.get(name, _NO_TRAITS) if isinstance(name, str) else _NO_TRAITS


def fields_with(**traits) -> tuple:
    """The registered fields whose traits have these values, e.g. ``fields_with(geometry="sdf")``
    (for messages and choices)."""
    return tuple(n for n, t in FIELD_TRAITS.items()
                 if all(getattr(t, k) == v for k, v in traits.items()))  # fmt: skip


def build_model(cfg) -> RadianceModel:
    """The model of config ``cfg`` (its ``field`` names a registered builder), initialised from
    ``cfg.seed``, on ``cfg.device``. The builders read a resolved config: a run's (frozen), or
    here a resolved copy of one not resolved yet."""
    if cfg.field not in FIELDS:
        raise ValueError(f"unknown field {cfg.field!r}; registered: {', '.join(FIELDS)}")
    if not getattr(cfg, "frozen", True):  # (a config no run has resolved: a test's, a tool's)
        cfg = cfg.resolve()
    torch.manual_seed(cfg.seed)
    model = FIELDS[cfg.field](cfg)
    if getattr(cfg, "pose_refine", False):
        from ..errors import UserError
        from .poses import CameraCorrection

        if cfg.pose_images < 1:  # (a run's config without the count)
            raise UserError("pose_refine needs pose_images >= 1 (the training images)")
        model.poses = CameraCorrection(cfg.pose_images)
    return model.to(cfg.device)
