"""The config sections of the built-in fields, declared once and registered with the fields that
read them (:class:`~warpnerf.fields.model.FieldTraits` ``config``): the MLP network, the hash-grid
encoding and the SDF fields' density. A run's config (``NeRFConfig``) derives from them; each
section's flags are shown under its TITLE, and each checks its own values (``check_section``)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..options import check_at_least, option

__all__ = ["MLPConfig", "HashConfig", "SDFDensityConfig", "VOLSDF"]

VOLSDF = ("volsdf",)  # flag group: shown by `train volsdf` only


@dataclass
class MLPConfig:
    """NeRF's MLP (and VolSDF's): layers, width, skip, the encodings' frequencies."""

    TITLE = "MLP network"

    n_layers: int = option(8, "MLP layers", flag="--layers", check="positive")
    width: int = option(256, "MLP width", check="positive")
    skip: int = option(4, flag=None)
    pos_freqs: int = option(10, "positional-encoding frequencies", check="nonnegative")
    dir_freqs: int = option(4, "direction-encoding frequencies", check="nonnegative")
    density_activation: str = option("softplus", flag=None)

    def check_section(self, fail) -> None:
        check_at_least(self, fail, 1, "n_layers", "width")
        check_at_least(self, fail, 0, "pos_freqs", "dir_freqs", "skip")
        for name in ("pos_freqs", "dir_freqs"):  # 2^64 * coordinates stays finite in float32
            if getattr(self, name) > 64:
                raise fail(name, f"must be at most 64, got {getattr(self, name)}")
        if self.density_activation not in ("relu", "softplus"):
            raise fail("density_activation", "must be one of relu, softplus, got "
                       f"{self.density_activation!r}")  # fmt: skip


@dataclass
class HashConfig:
    """The multiresolution hash-grid encoding and its small MLPs."""

    TITLE = "hash-grid encoding"

    hash_levels: int = option(16, "hash field: grid levels", check="positive")
    hash_log2_size: int = option(19, "hash field: log2 of the rows per level", check="positive")
    hash_base_res: int = option(16, flag=None)
    hash_max_res: int | None = option(
        None, "hash field: finest grid resolution (default 1024 for --field hash on a "
        "COLMAP/LLFF capture: measured +0.4 dB on beer and +0.1 dB on fern against 2048, "
        "docs/design/data.md; else 2048)", check="positive",
    )  # fmt: skip
    hidden: int = option(64, "hash field MLP width", check="positive")

    def grid_kwargs(self) -> dict:
        """The :class:`~warpnerf.ops.encoding.HashGrid` arguments."""
        return dict(n_levels=self.hash_levels, log2_size=self.hash_log2_size,
                    base_res=self.hash_base_res, max_res=self.hash_max_res)  # fmt: skip

    def check_section(self, fail) -> None:
        from ..ops.encoding import HashGrid

        check_at_least(self, fail, 1, "hash_levels", "hash_log2_size", "hash_base_res", "hidden")
        if self.hash_max_res is not None:  # (None: resolved from the data, checked then)
            try:
                HashGrid(**self.grid_kwargs())
            except ValueError as e:
                raise fail("hash_max_res", f"makes no hash grid with the other hash settings: {e}"
                           ) from None  # fmt: skip


@dataclass
class SDFDensityConfig:
    """An SDF field rendered as a density (VolSDF's Laplace or NeuS' logistic): its scale beta,
    the beta schedule, the eikonal term, the colour head's direction."""

    TITLE = "SDF density"

    # volsdf: the Laplace scale (world units), its floor, learned or fixed; the eikonal weight
    beta: float = option(0.1, "initial Laplace scale", check="positive", groups=VOLSDF)
    beta_min: float = option(1e-4, "its floor", check="positive", groups=VOLSDF)
    learn_beta: bool = option(True, "keep beta at --beta", negate="--fixed-beta", groups=VOLSDF)
    beta_final: float = option(
        0.0, "hash_sdf: anneal beta geometrically from --beta to this over --beta-anneal-steps "
        "(then constant; replaces learning it); 0: off", check="nonnegative", groups=VOLSDF,
    )  # fmt: skip
    beta_anneal_steps: int = option(
        5000, "hash_sdf: steps of the --beta-final schedule", check="positive", groups=VOLSDF
    )
    sdf_density: str = option(
        "laplace", "hash_sdf: SDF-to-density conversion, laplace (VolSDF), logistic (NeuS's "
        "density along the normal, s = 1/beta) or neus (NeuS's unbiased density: the logistic "
        "one times how fast the ray approaches the surface, zero where it leaves; outlines at "
        "the zero level, where the other two render a sphere of radius 0.32 about 0.024 / 0.030 "
        "wider at beta 0.01; the samples' gradients in both passes: slower)", groups=VOLSDF,
    )  # fmt: skip
    color_direction: str = option(
        "view", "hash_sdf: the colour head's direction input, view (the viewing direction) or "
        "reflect (it reflected about the SDF normal, plus n.v: Ref-NeRF's input for glossy "
        "surfaces; measured on materials: +1.4 dB renders, a coarser mesh)", groups=VOLSDF,
    )  # fmt: skip
    sdf_gradient: str | None = option(
        None, "hash_sdf: the finite differences of the SDF's gradient (the colour head's "
        "normal, the eikonal term, neus' density): central (second order: 7 SDF evaluations a "
        "coloured training sample) or forward (first order, with the sample's own value: 4; "
        "hash_sdf's default: on an H200 0.72x the step, lego +0.19 dB at 300 s, the same "
        "materials mesh, docs/design/surfaces.md)", groups=VOLSDF,
    )  # fmt: skip
    eikonal_weight: float | None = option(
        None, "weight of (|grad d| - 1)^2 (samples + random points); default 0.1 (volsdf), "
        "0.01 (hash_sdf: measured +0.7 dB on lego, docs/design/surfaces.md)", check="finite",
        groups=VOLSDF,
    )  # fmt: skip
    c2f_every: int = option(
        0, "hash_sdf: steps between opening one more hash level (coarse to fine, from 4 "
        "levels; 0: all levels at once, measured better on lego)", check="nonnegative",
        groups=VOLSDF,
    )  # fmt: skip

    def check_section(self, fail) -> None:
        if not (self.beta > 0 and 0 < self.beta_min <= self.beta):
            raise fail("beta_min", f"must be in (0, beta]: got beta-min {self.beta_min}, "
                       f"beta {self.beta}")  # fmt: skip
        if self.beta_final > 0 and not self.beta_min <= self.beta_final <= self.beta:
            raise fail("beta_final", f"must be in [beta_min, beta] = [{self.beta_min}, "
                       f"{self.beta}] (or 0: off), got {self.beta_final}")  # fmt: skip
        check_at_least(self, fail, 1, "beta_anneal_steps")
        for name, allowed in (("sdf_density", ("laplace", "logistic", "neus")),
                              ("color_direction", ("view", "reflect")),
                              ("sdf_gradient", ("central", "forward", None))):  # fmt: skip
            if (v := getattr(self, name)) not in allowed:
                raise fail(name, f"must be one of {', '.join(filter(None, allowed))}, got {v!r}")
        ew = self.eikonal_weight
        if ew is not None and not (math.isfinite(ew) and ew >= 0):
            raise fail("eikonal_weight", f"must be finite and >= 0, got {ew}")
        check_at_least(self, fail, 0, "c2f_every")
