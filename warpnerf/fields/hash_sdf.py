"""A fast surface field: a hash-grid SDF rendered with VolSDF's Laplace density (``--field
hash_sdf``), for the occupancy-grid fast path of the NeRF pipeline.

Geometry: the scene box's unit coordinates c in [-1, 1]^3 and the Warp hash encoding of the box
coordinates feed a small MLP (two Softplus hidden layers) -> a residual and ``n_features``
geometry features; the signed distance (world units) is that residual plus a sphere of radius
``radius`` (box units) around the box centre, |c| - radius, bounded below by the box's own SDF
(so no surface lies outside the box). The MLP's last layer starts near zero (and the hash
inputs' weights at zero), so training starts from the exact sphere SDF, the
role of SAL's geometric initialisation (Atzmon & Lipman 2020), which a 64-wide network only
approximates.

Density (``density=``): "laplace", VolSDF's sigma = Psi_beta(-d) / beta with the Laplace CDF
Psi_beta (Yariv et al. 2021); or "logistic", NeuS's opaque density seen along the normal, sigma =
s * Phi_s(-d) with the logistic CDF Phi_s(x) = 1 / (1 + exp(-s x)) and s = 1 / beta (Wang et al.
2021: rho = -(dPhi_s(d(t))/dt) / Phi_s(d(t)) = s (1 - Phi_s(d)) (-cos theta), here with cos theta =
-1, so that the density is a function of position alone and the occupancy grid and the packed
compositing kernels serve it unchanged). Both are the same family sigma = Psi(-d / beta) / beta with
a CDF Psi of unit scale; the logistic one has lighter (exponential, like Laplace) tails but is
smooth at the surface. beta = beta_min + |b| learned (shrinks as the surface sharpens), fixed, or
annealed: ``beta_final`` > 0 makes beta follow beta * (beta_final / beta)^(step / anneal_steps)
(geometric, then constant; :meth:`set_step`), the NeuS-style schedule of the inverse standard
deviation s = 1 / beta without learning it. The current beta is a buffer, so a checkpoint renders
with the beta it was trained to.

Normals and the eikonal term: the hash encoding gives no position gradient, so the SDF's gradient
is a central finite difference (6 evaluations, second-order accurate; the 4-point tetrahedral
scheme is cheaper but only first order, tests/test_hash_sdf.py):
grad_i d(x) ~ (d(x + h e_i) - d(x - h e_i)) / (2 h);
or (``gradient="forward"``, the config's default for this field since 2026-12-03: on an H200
0.74x the step and +0.19 dB on lego, the same materials mesh) a forward difference from the
sample's own value, which the density computed anyway: grad_i d(x) ~ (d(x + h e_i) - d(x)) / h,
3 evaluations, first order (an error of h/2 times the SDF's second derivative: about h / (2 r)
of the normal on a sphere of radius r).
The step h follows the coarse-to-fine schedule (Neuralangelo, Li et al. 2023): the hash levels
open one by one (:meth:`set_step`: ``levels_start`` levels at step 0, one more every
``level_every`` steps) and h is the cell size of the finest open level, so early normals are
smooth and later ones resolve detail. Colour: an MLP on (normal, geometry features, spherical
harmonics of the view direction; with ``color_direction="reflect"`` the view direction
reflected about the normal, w_r = d - 2 (d . n) n, and n . v instead, Ref-NeRF's
parameterisation: a mirror-like highlight is then a function of w_r the head can learn once for
the whole surface rather than something it explains by bending the geometry, and its gradient
reaches the normal, so the geometry is pulled to where the reflections agree; measured on lego
and materials: not yet). The colour head gets the sample positions in the features it
receives from :meth:`density`, so the culling pass (densities only) costs one SDF evaluation and
only coloured samples pay for the 6-point gradient.

The occupancy grid of an SDF field is built from :meth:`grid_density`: the largest density a cell
can hold given the SDF at a point of it (d - r with r the cell's half-diagonal; the SDF is
1-Lipschitz), so cells in a band of width ~r + a few beta around the surface, and inside it,
stay occupied and the band narrows as beta shrinks.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from ..ops.activations import Softplus
from ..ops.encoding import HashGrid, centred_input
from .encoding import HashEncoding, SphericalHarmonics
from .hash_nerf import hash_grid_of, with_occupancy_grid
from .model import FieldTraits, RadianceModel, register_field
from .sdf_volume import laplace_cdf, sdf_box
from .settings import HashConfig, SDFDensityConfig

__all__ = [
    "HashSDFField",
    "DENSITIES",
    "COLOR_DIRECTIONS",
    "GRADIENTS",
    "logistic_density",
    "neus_density",
    "sdf_density",
    "reflect",
]

DENSITIES = ("laplace", "logistic", "neus")
COLOR_DIRECTIONS = ("view", "reflect")
GRADIENTS = ("central", "forward")


def reflect(directions: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """The viewing directions [n, 3] (unit, camera to point) mirrored about the unit normals
    [n, 3]: w_r = d - 2 (d . n) n, the direction a mirror at the point reflects the view into
    (Ref-NeRF, Verbin et al. 2022: 2 (w_o . n) n - w_o with w_o = -d). Unit length."""
    return directions - 2.0 * (directions * normals).sum(-1, keepdim=True) * normals


def logistic_density(d: torch.Tensor, beta) -> torch.Tensor:
    """NeuS's density along the normal: s * sigmoid(-s d) with s = 1 / beta; finite with finite
    gradients for any finite d and beta > 0 (sigmoid never overflows)."""
    return torch.sigmoid(-d / beta) / beta


def neus_density(d: torch.Tensor, grad: torch.Tensor, directions: torch.Tensor, beta):
    """NeuS's unbiased density (Wang et al. 2021, eq. 13): rho = max(-dPhi_s(d)/dt, 0) /
    Phi_s(d) along the ray, which for d's directional derivative c = grad . v is
    max(-c, 0) * s * sigmoid(-s d), s = 1 / beta: the logistic density scaled by how fast the
    ray approaches the surface, and zero where it leaves it. A ray that passes a surface at
    distance m keeps transmittance sigmoid(s m) (its outline is the zero level's), where the
    density "along the normal" renders it ~3 beta too wide (experiments/surfaces/
    silhouette_bias.py). ``directions`` [n, 3] need not be unit (normalised here)."""
    v = torch.nn.functional.normalize(directions.to(grad.dtype), dim=-1)
    approach = torch.relu(-(grad * v).sum(-1)).to(d.dtype)
    return approach * logistic_density(d, beta)


def sdf_density(kind: str, d: torch.Tensor, beta) -> torch.Tensor:
    """sigma(d) of the conversion ``kind`` (:data:`DENSITIES`) with scale ``beta``; for
    ``neus``, which also needs the gradient and the direction (:func:`neus_density`), its bound
    for a 1-Lipschitz SDF: the logistic density."""
    if kind in ("logistic", "neus"):
        return logistic_density(d, beta)
    return laplace_cdf(-d, beta) / beta


_AXES = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
_AXES_ON: dict = {}  # (device, dtype) -> _AXES as a tensor (made once: a host-to-device copy
# synchronises, and is not allowed inside a captured CUDA graph)


def _axes(device, dtype) -> torch.Tensor:
    key = (str(device), dtype)
    if key not in _AXES_ON:
        _AXES_ON[key] = torch.tensor(_AXES, dtype=dtype).to(device)
    return _AXES_ON[key]


class HashSDFField(nn.Module):
    """``forward(positions [n, 3], directions [n, 3]) -> (sigmas [n], rgbs [n, 3])``; the field
    protocol's ``kind = "sdf"``, ``density``, ``color``, ``sdf``, ``aux_losses``."""

    kind = "sdf"

    def __init__(self, aabb, grid: HashGrid | None = None, hidden: int = 64,
                 n_features: int = 15, view_dependence: bool = True, beta: float = 0.1,
                 beta_min: float = 1e-4, learn_beta: bool = True, radius: float = 0.5,
                 levels_start: int = 4, level_every: int = 0, density: str = "laplace",
                 beta_final: float = 0.0, anneal_steps: int = 1,
                 color_direction: str = "view", gradient: str = "central"):  # fmt: skip
        super().__init__()
        if gradient not in GRADIENTS:
            raise ValueError(f"gradient must be one of {GRADIENTS}, got {gradient!r}")
        # forward differences: the colour head's features carry the sample's SDF value
        self.forward_differences = gradient == "forward"
        if color_direction not in COLOR_DIRECTIONS:
            raise ValueError(f"color_direction must be one of {COLOR_DIRECTIONS}, got "
                             f"{color_direction!r}")  # fmt: skip
        self.reflect = color_direction == "reflect"
        if self.reflect and not view_dependence:
            raise ValueError("color_direction 'reflect' needs view_dependence")
        if density not in DENSITIES:
            raise ValueError(f"density must be one of {DENSITIES}, got {density!r}")
        if beta_final > 0 and not (beta_min <= beta_final <= beta and anneal_steps >= 1):
            raise ValueError("an annealed beta needs beta_min <= beta_final <= beta and "
                             "anneal_steps >= 1")  # fmt: skip
        self.density_kind = density
        # NeuS's density depends on the ray's direction: the renderers pass each sample's
        # (warpnerf.field_protocol.density), and the features carry the gradient to color()
        self.density_needs_directions = density == "neus"
        self.beta_start, self.beta_final = float(beta), float(beta_final)
        self.anneal_steps = int(anneal_steps)
        learn_beta = learn_beta and beta_final <= 0  # a schedule replaces learning
        box = torch.as_tensor(aabb, dtype=torch.float32).reshape(-1)
        if box.shape != (6,) or not bool((box[3:] > box[:3]).all()):
            raise ValueError("aabb must be [xmin, ymin, zmin, xmax, ymax, zmax] with min < max")
        self.register_buffer("aabb", box)
        self.half = float((box[3:] - box[:3]).max()) / 2  # world units of one box unit
        self.encoding = HashEncoding(grid)
        self.grid_spec = self.encoding.grid
        self.resolutions = [int(r) for r, _, _ in self.grid_spec.levels]
        self.n_levels = self.grid_spec.n_levels
        self.per_level = self.encoding.out_dim // self.n_levels
        self.levels_start = max(1, min(int(levels_start), self.n_levels))
        self.level_every = int(level_every)
        self.register_buffer("level_mask", torch.ones(self.encoding.out_dim))
        self.open_levels = self.n_levels
        self.beta_min, self.view_dependence = float(beta_min), view_dependence
        b = torch.tensor(max(beta - beta_min, 1e-8))
        self.beta_param = nn.Parameter(b) if learn_beta else None
        if not learn_beta:
            self.register_buffer("beta_fixed", b)
        self.set_step(0)
        e = self.encoding.out_dim
        self.sdf_mlp = nn.Sequential(
            nn.Linear(3 + e, hidden), Softplus(beta=100), nn.Linear(hidden, hidden),
            Softplus(beta=100), nn.Linear(hidden, 1 + n_features),
        )  # fmt: skip
        self._geometric_init(radius, e)
        self.sh = SphericalHarmonics(4) if view_dependence else None
        d_col = 3 + n_features + (self.sh.out_dim if view_dependence else 0) + int(self.reflect)
        self.color_mlp = nn.Sequential(
            nn.Linear(d_col, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
            nn.Linear(hidden, 3),
        )  # fmt: skip
        self._aux = {}

    def _geometric_init(self, radius: float, n_enc: int) -> None:
        layers = [m for m in self.sdf_mlp if isinstance(m, nn.Linear)]
        with torch.no_grad():
            for lin in layers[:-1]:
                nn.init.normal_(lin.weight, 0.0, math.sqrt(2.0) / math.sqrt(lin.out_features))
                nn.init.zeros_(lin.bias)
            layers[0].weight[:, 3:] = 0.0  # hash features join as training opens them
            nn.init.normal_(layers[-1].weight, 0.0, 1e-4)
            nn.init.zeros_(layers[-1].bias)
        self.radius = float(radius)

    # ---------------------------------------------------------------- coarse-to-fine schedule

    def set_step(self, step: int) -> None:
        """Opens the hash levels of training step ``step`` (all of them when level_every = 0) and
        sets an annealed beta to its value at that step."""
        if self.beta_final > 0:
            f = min(max(int(step), 0) / self.anneal_steps, 1.0)
            b = self.beta_start * (self.beta_final / self.beta_start) ** f
            self.beta_fixed.fill_(max(b - self.beta_min, 1e-8))
        n = self.n_levels
        if self.level_every > 0:
            n = min(self.n_levels, self.levels_start + int(step) // self.level_every)
        if n != getattr(self, "_mask_levels", None):
            mask = torch.zeros(self.n_levels, self.per_level)
            mask[:n] = 1.0
            self.level_mask.copy_(mask.reshape(-1))
            self._mask_levels = n
        self.open_levels = n

    @property
    def fd_step(self) -> float:
        """The finite-difference step (world units): the cell of the finest open level."""
        return 2.0 * self.half / self.resolutions[self.open_levels - 1]

    # ---------------------------------------------------------------------------- geometry

    @property
    def beta(self) -> torch.Tensor:
        b = self.beta_param if self.beta_param is not None else self.beta_fixed
        return self.beta_min + b.abs()

    def _geometry(self, positions: torch.Tensor):
        """(sdf [n] world units, features [n, F]) at positions [n, 3] (world)."""
        lo, hi = self.aabb[:3].to(positions.dtype), self.aabb[3:].to(positions.dtype)
        u = ((positions.detach() - lo) / (hi - lo)).clamp(0.0, 1.0)
        if self.level_every == 0 and centred_input():  # [c, enc] from the encoding's kernel
            x = self.encoding(u, centred=True)
            c = x[:, :3]
        else:
            c = 2.0 * u - 1.0
            enc = self.encoding(u)
            if self.level_every > 0:  # (coarse to fine; otherwise the mask is all ones, and
                # x * 1 = x: skipping it saves an elementwise pass over [n, L * F] and its
                # backward)
                enc = enc * self.level_mask.to(u.dtype)
            x = torch.cat([c, enc.to(c.dtype)], -1)
        h = self.sdf_mlp(x)
        d = (c.norm(dim=-1) - self.radius + h[:, 0]) * self.half
        # bounded: at least the distance to the scene box, so that no surface lies outside it
        # (inside the box the zero set is the network's own; outside, where the encoding sees
        # only the clamped border, the SDF is the box's)
        box = sdf_box(positions.detach().to(d.dtype), (lo + hi) * 0.5, hi - lo)
        return torch.maximum(d, box), h[:, 1:]

    def sdf(self, positions: torch.Tensor) -> torch.Tensor:
        """World-unit signed distance at positions [n, 3]."""
        return self._geometry(positions)[0]

    def gradient(self, positions: torch.Tensor) -> torch.Tensor:
        """The SDF's gradient [n, 3] by central finite differences of step :attr:`fd_step`
        (differentiable in the parameters when gradients are enabled); float32 even under
        autocast, float64 for float64 positions."""
        h = self.fd_step
        x = positions.detach()
        x = x if x.dtype == torch.float64 else x.float()
        e = _axes(x.device, x.dtype) * h  # [3, 3]
        v = torch.cat([e, -e]).unsqueeze(1)  # [6, 1, 3]
        with torch.autocast(x.device.type, enabled=False):
            d = self.sdf((x.unsqueeze(0) + v).reshape(-1, 3)).to(x.dtype).reshape(6, -1)
        return ((d[:3] - d[3:]) / (2.0 * h)).T

    def forward_gradient(self, positions: torch.Tensor, d: torch.Tensor | None = None):
        """The SDF's gradient [n, 3] by forward differences of step :attr:`fd_step`,
        (d(x + h e_i) - d(x)) / h, from the SDF values ``d`` [n] at ``positions`` (computed here
        when None or below float32: they must be this precision's values at exactly these
        points); first order, 3 evaluations (4 without ``d``); differentiable in the
        parameters, through ``d`` too. float32, or float64 for float64 positions."""
        h = self.fd_step
        x = positions.detach()
        x = x if x.dtype == torch.float64 else x.float()
        e = _axes(x.device, x.dtype) * h  # [3, 3]
        with torch.autocast(x.device.type, enabled=False):
            if d is None or d.dtype not in (torch.float32, torch.float64):
                d = self.sdf(x)
            dp = self.sdf((x.unsqueeze(0) + e.unsqueeze(1)).reshape(-1, 3)).to(x.dtype)
        return ((dp.reshape(3, -1) - d.to(x.dtype).unsqueeze(0)) / h).T

    def eikonal(self, positions: torch.Tensor) -> torch.Tensor:
        """Mean (|grad d| - 1)^2 at positions [n, 3] (differentiable)."""
        return ((self.gradient(positions).norm(dim=-1) - 1.0) ** 2).mean()

    def normals(self, positions: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return torch.nn.functional.normalize(self.gradient(positions), dim=-1)

    # ------------------------------------------------------------------------- rendering

    def density(self, positions: torch.Tensor, directions: torch.Tensor | None = None):
        """sigmas [n] and the colour head's input [n, 3 + F] (positions, features); with the
        ``neus`` density the samples' ``directions`` [n, 3] are needed and the input is
        [n, 6 + F] (positions, the SDF's gradient, features): the gradient the density used is
        the one the colour head and the eikonal term get."""
        d, feat = self._geometry(positions)
        beta = self.beta.to(d.dtype)
        x = positions.detach().to(feat.dtype)
        if not self.density_needs_directions:
            sigma = sdf_density(self.density_kind, d, beta)
            if self.forward_differences:  # (the value the colour head's differences start from)
                return sigma, torch.cat([x, d.unsqueeze(-1).to(feat.dtype), feat], -1)
            return sigma, torch.cat([x, feat], -1)
        if directions is None:
            raise ValueError("the neus density needs each sample's direction: "
                             "density(positions, directions)")  # fmt: skip
        g = self.forward_gradient(positions, d) if self.forward_differences else (
            self.gradient(positions))  # fmt: skip
        sigma = neus_density(d, g, directions, beta)
        return sigma, torch.cat([x, g.to(feat.dtype), feat], -1)

    def grid_density(self, positions: torch.Tensor, radius: float) -> torch.Tensor:
        """The largest density within ``radius`` of each position (the SDF is 1-Lipschitz):
        the occupancy grid's value of a cell of half-diagonal ``radius``."""
        d = self.sdf(positions)
        return sdf_density(self.density_kind, d - radius, self.beta.to(d.dtype))

    def color(self, h: torch.Tensor, directions: torch.Tensor | None = None, valid=None):
        """rgbs [n, 3] from :meth:`density`'s features (positions + geometry features); records
        the eikonal term of these samples when gradients are enabled. ``valid`` [n] bool: only
        those rows are samples (a fixed-capacity buffer's unused slots are not): the term is
        their mean, and recorded with ``aux_count`` (a device tensor) instead of a host count."""
        if self.density_needs_directions:  # (density() computed it: [positions, grad, feat])
            g, feat = h[:, 3:6], h[:, 6:]
        elif self.forward_differences:  # [positions, sdf, feat]
            g, feat = self.forward_gradient(h[:, :3], h[:, 3]), h[:, 4:]
        else:
            g, feat = self.gradient(h[:, :3]), h[:, 3:]
        if torch.is_grad_enabled() and valid is not None:
            w = valid.to(g.dtype)
            count = w.sum()
            e = ((g.norm(dim=-1) - 1.0) ** 2 * w).sum() / count.clamp_min(1.0)
            self._aux, self._aux_n = {"eikonal": e}, {"eikonal": count}
        elif torch.is_grad_enabled():  # (no samples: no term, not the NaN of an empty mean)
            self._aux = {"eikonal": ((g.norm(dim=-1) - 1.0) ** 2).mean()} if len(g) else {}
            self._aux_n = {"eikonal": int(g.shape[0])}  # (its sample count: data parallelism)
        n = torch.nn.functional.normalize(g, dim=-1).to(h.dtype)
        parts = [n, feat]
        if self.view_dependence:
            if directions is None:
                raise ValueError("a view-dependent field needs directions")
            d = directions.to(h.dtype)
            if self.reflect:  # the reflected direction (gradients reach the normal) and n . v
                d = torch.nn.functional.normalize(d, dim=-1)
                parts += [self.sh(reflect(d, n)), -(d * n).sum(-1, keepdim=True)]
            else:
                parts.append(self.sh(d))
        return torch.sigmoid(self.color_mlp(torch.cat(parts, -1)))

    def aux_losses(self) -> dict:
        """{"eikonal": ...} of the last coloured samples with gradients, once."""
        aux, self._aux = self._aux, {}
        return aux

    def forward(self, positions: torch.Tensor, directions: torch.Tensor | None = None):
        sigma, h = self.density(positions, directions)  # (directions: used by neus only)
        return sigma, self.color(h, directions)

    def n_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())


# the built-in field `hash_sdf`, registered as an added field is (docs/ARCHITECTURE.md)

# The CPU work a sample against the plain hash estimate: 2.3 with central differences
# (measured); forward ones take 0.58x the time (50.8 s against 87.2 s of training on the
# built-in scene, 2 cores, 2026-12-03, docs/design/training.md "Issue 47, fifth round")
CENTRAL_DIFFERENCES_COST, FORWARD_DIFFERENCES_COST = 2.3, 0.58
# the field's finite differences unless --sdf-gradient says otherwise (docs/design/surfaces.md,
# "Issue 49, twelfth round")
DEFAULT_GRADIENT = "forward"
# its colour loss unless --photometric-loss says otherwise (docs/design/nerf.md, "Issue 44,
# eleventh round": lego +1.31 dB after 300 s, the materials mesh 0.0208 -> 0.0194)
DEFAULT_PHOTOMETRIC = "huber"


def _cpu_cost(cfg) -> float:
    forward = (getattr(cfg, "sdf_gradient", None) or DEFAULT_GRADIENT) == "forward"
    return CENTRAL_DIFFERENCES_COST * (FORWARD_DIFFERENCES_COST if forward else 1.0)


@register_field("hash_sdf", FieldTraits(
    geometry="sdf", in_box=True, hash=True, grid=True, beta_schedule=True, lr=1e-2, lr_decay=20.0,
    eikonal_weight=0.01, sdf_gradient=DEFAULT_GRADIENT, photometric_loss=DEFAULT_PHOTOMETRIC,
    cpu_cost=_cpu_cost,
    config=(HashConfig, SDFDensityConfig),
))  # fmt: skip
def _hash_sdf(cfg) -> RadianceModel:
    """A hash-grid SDF with VolSDF's density on the occupancy-grid fast path (hash_sdf.py)."""
    box = cfg.aabb_box()
    f = HashSDFField(
        box, hash_grid_of(cfg), cfg.hidden, view_dependence=cfg.view_dependence,
        beta=cfg.beta, beta_min=cfg.beta_min, learn_beta=cfg.learn_beta,
        level_every=cfg.c2f_every, density=cfg.sdf_density, beta_final=cfg.beta_final,
        anneal_steps=cfg.beta_anneal_steps, color_direction=cfg.color_direction,
        gradient=cfg.sdf_gradient,
    )  # fmt: skip
    return with_occupancy_grid(cfg, f, box)
