"""nerfacto's proposal networks for contracted scenes (``--sampler proposal``): small hash-grid
density fields that place each ray's samples instead of an occupancy grid.

A ray's samples are placed in the coordinate ``s = t / (t + a)`` (a: the contraction's inner
half-size; the distortion loss's coordinate, :func:`warpnerf.train.nerf_run.distortion_coordinate`):
uniform in s is linear in t inside the inner cube and uniform in disparity beyond it, like
nerfacto's ``UniformLinDispPiecewiseSampler``. The first level's edges are uniform in s between
near and far; each proposal network's densities at its level's interval midpoints give
compositing weights, whose histogram is resampled (:func:`warpnerf.ops.proposal_resample`,
annealed and padded as nerfacto does) into the next level's edges, and the last histogram into
the field's. :func:`warpnerf.ops.interlevel_loss` trains the networks to bound the field's
weights (the field's weights detached); nothing flows through the resampling.

Defaults are nerfacto's: levels of 256 then 96 samples, 48 for the field; the networks' hash
grids of 5 levels of 2 features, 2^17 rows, from 16 to 128 then 256 cells per side, one hidden
layer of 16, density trunc_exp(x), zero outside the contracted cube; the anneal exponent rises
as ``slope f / ((slope - 1) f + 1)``, f = min(step / anneal_steps, 1), slope 10.
"""

from __future__ import annotations

import torch
from torch import nn

from ..ops.encoding import HashGrid
from ..ops.occupancy import contract_points
from .encoding import HashEncoding
from .mlp import run_mlp, trunc_exp

__all__ = [
    "ProposalDensity", "ProposalSampler", "proposal_sampler_of", "parse_levels",
    "PROPOSAL_RES", "MAX_LEVELS", "MAX_SAMPLES",
]  # fmt: skip

PROPOSAL_RES = (128, 256)  # finest resolution of each level's network (later levels: the last)
PROPOSAL_LEVELS = 5  # hash levels of a proposal network
PROPOSAL_LOG2 = 17  # its table's rows: 2^17
PROPOSAL_HIDDEN = 16
ANNEAL_SLOPE = 10.0
MAX_LEVELS = 4  # proposal levels at most
MAX_SAMPLES = 4096  # samples per ray of any level at most


def parse_levels(text: str) -> tuple:
    """'256,96' -> (256, 96): each proposal level's samples per ray; ValueError if malformed."""
    try:
        levels = tuple(int(v) for v in str(text).split(","))
    except ValueError:
        raise ValueError(f"expected integers such as 256,96, got {text!r}") from None
    if not 1 <= len(levels) <= MAX_LEVELS or not all(1 <= v <= MAX_SAMPLES for v in levels):
        raise ValueError(f"expected 1 to {MAX_LEVELS} levels of 1 to {MAX_SAMPLES} samples each, "
                         f"got {text!r}")  # fmt: skip
    return levels


class ProposalDensity(nn.Module):
    """``forward(positions [n, 3]) -> sigmas [n]``: contracted positions (inner half-size
    ``contract``) -> hash encoding of the cube [-2a, 2a]^3 -> Linear, ReLU, Linear -> trunc_exp;
    zero outside the cube (nerfacto's ``HashMLPDensityField``)."""

    def __init__(self, contract: float, grid: HashGrid, hidden: int = PROPOSAL_HIDDEN):
        super().__init__()
        if not contract > 0:
            raise ValueError(f"a proposal network needs a contracted scene (a > 0), got {contract}")
        self.contract = float(contract)
        self.encoding = HashEncoding(grid)
        self.mlp = nn.Sequential(
            nn.Linear(self.encoding.out_dim, hidden), nn.ReLU(), nn.Linear(hidden, 1)
        )

    def forward(self, positions: torch.Tensor) -> torch.Tensor:
        a = self.contract
        x = (contract_points(positions, a) + 2 * a) / (4 * a)
        inside = ((x >= 0) & (x <= 1)).all(-1)
        h = run_mlp(self.mlp, self.encoding(x))
        return trunc_exp(h[:, 0]) * inside.to(h.dtype)


class ProposalSampler(nn.Module):
    """The proposal networks of a run, one per level, and their sampling settings: ``samples``
    per ray of each level, ``final`` samples of the field, the contraction's ``contract`` (a)
    and the anneal exponent (a buffer, saved with the networks: a loaded run samples as it
    trained last). ``n_draws``: the uniform numbers a training ray needs (one per level plus
    one for the field's samples: nerfacto's single jitter)."""

    def __init__(self, contract: float, samples=(256, 96), final: int = 48,
                 anneal_steps: int = 1000):  # fmt: skip
        super().__init__()
        self.samples, self.final = tuple(int(v) for v in samples), int(final)
        self.contract, self.anneal_steps = float(contract), int(anneal_steps)
        self.nets = nn.ModuleList(
            ProposalDensity(
                self.contract,
                HashGrid(
                    n_levels=PROPOSAL_LEVELS,
                    n_features=2,
                    log2_size=PROPOSAL_LOG2,
                    base_res=16,
                    max_res=PROPOSAL_RES[min(i, len(PROPOSAL_RES) - 1)],
                ),
            )  # fmt: skip
            for i in range(len(self.samples))
        )
        self.register_buffer("anneal", torch.ones(1))

    @property
    def n_draws(self) -> int:
        return len(self.samples) + 1

    def set_step(self, step: int) -> None:
        """nerfacto's anneal exponent for training step ``step`` (in place: no host sync)."""
        f = min(max(step / self.anneal_steps, 0.0), 1.0) if self.anneal_steps > 0 else 1.0
        self.anneal.fill_(ANNEAL_SLOPE * f / ((ANNEAL_SLOPE - 1) * f + 1))

    def s_of_t(self, t: torch.Tensor) -> torch.Tensor:
        return t / (t + self.contract)

    def t_of_s(self, s: torch.Tensor) -> torch.Tensor:
        return self.contract * s / (1 - s)


def proposal_sampler_of(cfg) -> ProposalSampler:
    """The proposal sampler of a run's config (``--sampler proposal``, contracted)."""
    return ProposalSampler(float(cfg.aabb), parse_levels(cfg.proposal_samples),
                           cfg.proposal_final, cfg.proposal_anneal)  # fmt: skip
