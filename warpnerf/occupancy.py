"""Occupancy grid: which cells of the scene box can hold visible density (instant-ngp / nerfacc
style), so rays march only through those cells.

State lives in buffers (saved with the model): ``density`` [res^3] (an EMA of the field's density
in each cell), ``bits`` [res^3 / 8] uint8 (cells above threshold) and the number of updates.
Every update evaluates the field at one jittered point per chosen cell: all cells during the
warm-up (the first ``warmup`` updates), then a random quarter of all cells plus a random
quarter's worth of the occupied ones; ``density = max(decay * density, new)`` and the threshold
is ``min(-log(1 - occ_threshold) / dt, mean density)`` (a cell is kept when one step of length dt
through it would have opacity >= occ_threshold, or when the whole field is still dim).

Unbounded scenes (``contract=a``): the grid covers the contracted cube [-2a, 2a]^3 (see
:func:`warpnerf.ops.occupancy.contract_points`: the inner cube [-a, a]^3 as it is, all of space
beyond it squeezed into the shell around it); a cell's points are mapped back to world space
before the field sees them, and rays march with steps that grow as ``cone`` x distance
(:func:`warpnerf.ops.occupancy.march_rays_contracted`).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from .ops import occupancy as ops
from .ops._bridge import check_int

__all__ = ["OccupancyGrid"]


class OccupancyGrid(nn.Module):
    """Args:
    aabb: scene box [6] (xmin, ymin, zmin, xmax, ymax, zmax).
    resolution: cells per axis (even).
    dt: the marching step the threshold refers to (world units along unit directions).
    occ_threshold: opacity of one step below which a cell counts as empty.
    decay: EMA decay of the cell densities per update.
    warmup: updates that evaluate every cell before random subsets take over.
    contract: 0 (a bounded box), or the inner cube's half-size a of an unbounded scene (then
        aabb must be the contracted cube [-2a, 2a]^3).
    cone: with ``contract``: marching steps are dt up to distance dt / cone, cone x distance
        beyond (0: dt everywhere).
    """

    def __init__(self, aabb, resolution=128, *, dt, occ_threshold=0.01, decay=0.95, warmup=16,
                 contract=0.0, cone=0.0):  # fmt: skip
        super().__init__()
        box = ops._box(aabb)
        contract, cone = float(contract), float(cone)
        if not (0 <= contract < math.inf and 0 <= cone < math.inf):
            raise ValueError("need finite contract >= 0 and cone >= 0")
        if contract and not ops.is_contracted_box(box, contract):
            raise ValueError("a contracted grid's aabb must be the cube [-2a, 2a]^3, a = contract")
        self.contract, self.cone = contract, cone
        ops._check_res(resolution)
        if not (0 < dt < math.inf and 0 < occ_threshold < 1 and 0 <= decay <= 1):
            raise ValueError("need finite dt > 0, 0 < occ_threshold < 1 and 0 <= decay <= 1")
        warmup = check_int("warmup", warmup)
        self.res, self.dt = int(resolution), float(dt)
        self.occ_threshold, self.decay, self.warmup = float(occ_threshold), float(decay), warmup
        n = self.res**3
        self.box = box.tolist()  # host copy: marching needs it without a device sync
        self.register_buffer("aabb", box)
        self.register_buffer("density", torch.zeros(n))
        # Everything counts as occupied until the first update.
        self.register_buffer("bits", torch.full((n // 8,), 255, dtype=torch.uint8))
        self.register_buffer("n_updates", torch.zeros((), dtype=torch.long))

    @property
    def n_cells(self) -> int:
        return self.res**3

    def threshold(self) -> float:
        return min(-math.log1p(-self.occ_threshold) / self.dt, float(self.density.mean()))

    def occupancy(self) -> float:
        """Fraction of cells marked occupied."""
        return float(ops.unpack_bits(self.bits).float().mean())

    def _cells(self, generator):
        n, dev = self.n_cells, self.density.device
        if int(self.n_updates) < self.warmup:
            return torch.arange(n, device=dev, dtype=torch.int32)
        uniform = torch.randint(n, (n // 4,), device=dev, generator=generator)
        occupied = torch.nonzero(ops.unpack_bits(self.bits)).squeeze(1)
        if occupied.numel():
            pick = torch.randint(occupied.numel(), (n // 4,), device=dev, generator=generator)
            uniform = torch.cat([uniform, occupied[pick]])
        return uniform.to(torch.int32)

    @torch.no_grad()
    def update(self, density_fn, generator: torch.Generator | None = None, chunk: int = 1 << 20):
        """Evaluates ``density_fn(points [m, 3]) -> sigmas [m]`` at jittered cell points and
        refreshes the densities and the bitfield (``generator`` on the grid's device)."""
        chunk = check_int("chunk", chunk, lo=1)
        cells = self._cells(generator)
        jitter = torch.rand(cells.shape[0], 3, device=cells.device, generator=generator)
        # the cells are the grid's own (no range check, no host sync)
        points = ops.grid_cell_points(cells, jitter, self.res, self.box, check=False)
        if self.contract:  # the cells tile contracted space: the field sees world points
            points = ops.uncontract_points(points, self.contract)
        values = torch.cat(
            [density_fn(points[s : s + chunk]).float() for s in range(0, points.shape[0], chunk)]
        )
        ops.grid_ema_update(self.density, cells, values, self.decay)
        self.bits.copy_(ops.grid_pack_bits(self.density, self.threshold()))
        self.n_updates += 1

    def march(self, origins, directions, near, far, *, jitter=None, k_begin=None, max_samples=1024,
              capacity=None):  # fmt: skip
        """Packed samples in occupied cells (see :func:`warpnerf.ops.occupancy.march_rays`, and
        ``march_rays_contracted`` for an unbounded scene; ``capacity``: static shapes, no host
        sync, and a third output, the marching's counts)."""
        if self.contract:
            return ops.march_rays_contracted(
                origins, directions, near, far, self.bits, self.res, self.contract, self.dt,
                self.cone, jitter=jitter, k_begin=k_begin, max_samples=max_samples,
                capacity=capacity,
            )  # fmt: skip
        return ops.march_rays(
            origins,
            directions,
            near,
            far,
            self.bits,
            self.res,
            self.box,
            self.dt,
            jitter=jitter,
            k_begin=k_begin,
            max_samples=max_samples,
            capacity=capacity,
        )
