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

View culling (``--view-cull``, issue 44; instant-ngp's ``mark_untrained_density_grid`` in
``src/testbed_nerf.cu``): cells that no training camera sees are empty from the start and stay
empty (the ``seen`` buffer, saved with the grid; every update zeroes the density of unseen
cells, so their bit stays off, and they count as 0 in the mean density, as instant-ngp's -1 cells
count as 0 in its mean). instant-ngp keeps a cell when one of its 8 corners lies in front of some
training camera (``dot(dir, forward) >= 1e-4``) and projects strictly inside its image, no
margin; a cell that a frustum crosses without holding a corner (near a camera, or a cell larger
than the frustum there) is dropped. The rule here is conservative instead (:func:`seen_cells`):
a cell is culled only when, for every training camera, one of the camera's five half-spaces (the
four planes through its centre and the edges [0, W] x [0, H] of its image, and the plane
through its centre facing along its view axis: depth 0, not the near plane) leaves every point of
a convex set holding the cell's world region strictly outside. That set is the cell itself (a
bounded grid, and the inner cube of a contracted one), the cell mapped back from NDC (the map is
projective: the hull of its corners' images, those on the NDC face z = 1 points at infinity),
or for a cell of a contracted grid's shell ``conv{t d_j : t = r_min, R}`` with ``d_j`` its
corners' directions (``|d_j|_inf`` = 1), ``r_min`` the world max-norm of its nearest point and
``R`` that of its farthest over ``min_j e . d_j`` (``e`` the axis its centre leans along); for
the outermost layer ``R`` is infinite (the cell reaches infinity along those directions). No
point of a culled cell lies in any training frustum; a kept cell may lie just outside every one
(near a frustum's edges, within the hull's slack).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from .ops import occupancy as ops
from .ops.bridge import check_int

__all__ = ["OccupancyGrid", "seen_cells", "pinhole_bounds"]


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
        # --view-cull: the cells some training camera sees (all of them unless cull() ran)
        self.register_buffer("seen", torch.ones(n, dtype=torch.bool))
        # the occupied cells' index box, kept with the bits (marching cuts rays to it); derived,
        # so not saved: recomputed wherever the bits change
        self.register_buffer("occupied", ops.occupied_cells(self.bits, self.res), persistent=False)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # a grid saved before view culling existed has no mask: every cell counts as seen
        if prefix + "bits" in state_dict and prefix + "seen" not in state_dict:
            state_dict[prefix + "seen"] = torch.ones_like(self.seen)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
        self._bits_changed()

    def _bits_changed(self) -> None:
        """Refreshes what is derived from the bits (in place: a captured step reads the same
        buffer; no host sync)."""
        self.occupied.copy_(ops.occupied_cells(self.bits, self.res))

    @property
    def n_cells(self) -> int:
        return self.res**3

    def threshold(self) -> float:
        return min(-math.log1p(-self.occ_threshold) / self.dt, float(self.density.mean()))

    def occupancy(self) -> float:
        """Fraction of cells marked occupied."""
        return float(ops.unpack_bits(self.bits).float().mean())

    @torch.no_grad()
    def cull(self, c2w, intrinsics, width: int, height: int, *, bounds=None, ndc=None,
             chunk: int = 1 << 24) -> float:  # fmt: skip
        """View culling: marks the cells no camera sees (:func:`seen_cells`; the cameras
        ``c2w`` [N, 3|4, 4] OpenGL, ``intrinsics`` [N, 4] fx, fy, cx, cy in pixels of W x H
        images, ``bounds`` [N, 4] their image tangents where lens distortion widens them
        (:func:`warpnerf.data.cameras.frustum_bounds`; None: :func:`pinhole_bounds`), ``ndc``
        the NDC camera (fx, fy, W, H) of a
        forward-facing run whose grid covers NDC space) as unseen, empties them now and keeps
        them empty through every update (in place: a captured step reads the same buffers).
        Returns the fraction of cells culled."""
        if bounds is None:
            bounds = pinhole_bounds(intrinsics, width, height)
        dev = self.seen.device
        seen = seen_cells(self.res, self.box, c2w.to(dev), bounds.to(dev), contract=self.contract,
                          ndc=ndc, chunk=chunk)  # fmt: skip
        self.seen &= seen
        self.density.mul_(self.seen)
        self.bits &= ops.grid_pack_bits(self.seen.float(), 0.5)
        self._bits_changed()
        return 1.0 - float(self.seen.float().mean())

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
        self.density.mul_(self.seen)  # culled cells stay empty (in place: no host sync)
        self.bits.copy_(ops.grid_pack_bits(self.density, self.threshold()))
        self._bits_changed()
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
            occupied=self.occupied,
        )


# ---- view culling (see the module's docstring for the rule) ----

NDC_NEAR = 1.0  # the near plane of the NDC map (warpnerf.data.cameras.ndc_rays' default)


def pinhole_bounds(intrinsics, width: int, height: int) -> torch.Tensor:
    """[N, 4] float64 (x_lo, x_hi, y_lo, y_hi): each pinhole camera's image [0, W] x [0, H]
    (pixel edges) as the tangents ``x / d``, ``y / d`` of its rays in camera space (y up, d the
    depth along -z). Lens distortion widens them: :func:`warpnerf.data.cameras.frustum_bounds`."""
    k = torch.as_tensor(intrinsics).reshape(-1, 4).double()
    fx, fy, cx, cy = k.unbind(-1)
    w, h = float(width), float(height)
    return torch.stack([-cx / fx, (w - cx) / fx, -(h - cy) / fy, cy / fy], -1)


def _frustum_planes(c2w, bounds) -> tuple:
    """Each camera's five half-spaces ``n . x + off >= 0`` in world space (x_lo, x_hi, y_lo,
    y_hi, front): normals [N * 5, 3] and offsets [N * 5], float64; in camera space (d = -z)
    they are ``x - x_lo d``, ``x_hi d - x``, ``y - y_lo d``, ``y_hi d - y`` and ``d``."""
    c2w = c2w.double()
    lo_x, hi_x, lo_y, hi_y = bounds.double().unbind(-1)
    one, zero = torch.ones_like(lo_x), torch.zeros_like(lo_x)
    n_cam = torch.stack([
        torch.stack([one, zero, lo_x], -1), torch.stack([-one, zero, -hi_x], -1),
        torch.stack([zero, one, lo_y], -1), torch.stack([zero, -one, -hi_y], -1),
        torch.stack([zero, zero, -one], -1),
    ], 1)  # [N, 5, 3]  # fmt: skip
    normals = n_cam @ c2w[:, :3, :3].transpose(1, 2)  # R n (the rotation is orthonormal)
    offsets = -(normals * c2w[:, None, :3, 3]).sum(-1)
    return normals.reshape(-1, 3), offsets.reshape(-1)


def _cell_boxes(cells, res: int, box):
    """lo, hi [m, 3] (float64) of cells given by index (the last ones end exactly at the box)."""
    ijk = torch.stack([cells // (res * res), (cells // res) % res, cells % res], -1).double()
    b0, b1 = box[:3], box[3:]
    lo = b0 + (b1 - b0) * (ijk / res)
    return lo, torch.where(ijk + 1 == res, b1, b0 + (b1 - b0) * ((ijk + 1) / res))


def _hulls(cells, res: int, box, contract: float, ndc) -> dict:
    """What the plane tests need of each cell's world hull (the module's docstring): ``c``,
    ``h`` [m, 3] centre and half-size of a box, with ``w`` [m, k] its homogeneous weights (a
    bounded cell: one level, 1; NDC: the world box's two z-levels, (x, y) spanning c +- h at
    z = -2 n with weight 1 - Z, 0 at Z = 1); a contracted grid adds ``inner`` [m] (the cell is
    its own world box), the shell's corner directions ``d`` [m, 8, 3] (|d|_inf = 1), ``r_min``,
    ``r_max`` [m] and ``outer`` [m] (``r_max`` infinite); ``keep`` [m]: cells whose region
    cannot be bounded (kept)."""
    lo, hi = _cell_boxes(cells, res, box)
    m = cells.shape[0]
    hull = {"c": 0.5 * (lo + hi), "h": 0.5 * (hi - lo), "w": torch.ones_like(lo[:, :1]),
            "keep": torch.zeros(m, dtype=torch.bool, device=cells.device)}  # fmt: skip
    if ndc is not None:  # NDC -> world is projective: NDC (X, Y, Z) is the world point
        fx, fy, w, h = (float(v) for v in ndc)  # (n X W / fx, n Y H / fy, -2 n) / (1 - Z)
        scale = torch.tensor([NDC_NEAR * w / fx, NDC_NEAR * h / fy, 0.0], dtype=lo.dtype,
                             device=lo.device)  # fmt: skip
        hull["c"] = hull["c"] * scale + torch.tensor([0.0, 0.0, -2 * NDC_NEAR], device=lo.device)
        hull["h"] = hull["h"] * scale
        hull["w"] = torch.stack([1 - lo[:, 2], 1 - hi[:, 2]], -1)
        return hull
    if not contract:
        return hull
    a = contract
    pick = torch.tensor([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], device=cells.device)
    c = torch.where(pick.bool(), hi[:, None], lo[:, None])  # [m, 8, 3] the corners
    s = c.abs().amax(-1)  # [m, 8] the corners' contracted max-norms
    s_max = s.amax(-1)
    s_min = torch.maximum(lo, -hi).clamp_min(0).amax(-1)  # the box's nearest point to 0

    def world(s):  # the world max-norm of contracted max-norm s < 2a
        return torch.where(s <= a, s, a * a / (2 * a - s).clamp_min(1e-300))

    d = c / s.clamp_min(1e-300)[..., None]
    axis = hull["c"].abs().argmax(-1, keepdim=True)  # the axis the centre leans along
    sign = hull["c"].gather(-1, axis).sign()
    beta = (d.gather(-1, axis[:, None].expand(-1, 8, 1)).squeeze(-1) * sign).amin(-1)
    ijk = torch.stack([cells // (res * res), (cells // res) % res, cells % res], -1)
    outer = ((ijk == 0) | (ijk == res - 1)).any(-1)  # the layer that reaches infinity
    inner = s_max <= a
    r_min = world(s_min)
    r_max = torch.where(outer, r_min, world(s_max) / beta.clamp_min(1e-300))  # (outer: unused)
    keep = ~inner & ((s_min <= 0) | (beta <= 0))
    hull.update(d=d, r_min=r_min, r_max=r_max, outer=outer, inner=inner, keep=keep)
    return hull


def _outside(hull: dict, idx, normals, offsets):
    """Bool [len(idx), planes]: the plane leaves the whole hull of cell ``idx`` outside (every
    point strictly below it, no direction above it)."""
    c, h, w = hull["c"][idx], hull["h"][idx], hull["w"][idx]
    top = c @ normals.T + h @ normals.abs().T  # the box's farthest corner along each normal
    out = None
    for k in range(w.shape[1]):  # every z-level of the box outside
        wk = w[:, k : k + 1]
        val = top + wk * offsets
        level = torch.where(wk > 0, val < 0, val <= 0)
        out = level if out is None else out & level
    if "d" not in hull:
        return out
    # the shell's hull conv{t d_j : t = r_min, r_max}: a plane's largest value on it is
    # max(r_min q, r_max q) + off with q = max_j n . d_j (q > 0 and r_max infinite: +inf)
    q = (hull["d"][idx] @ normals.T).amax(1)
    r_min, r_max = hull["r_min"][idx, None], hull["r_max"][idx, None]
    shell = torch.where(
        hull["outer"][idx, None],
        (q <= 0) & (r_min * q + offsets < 0),
        torch.maximum(r_min * q, r_max * q) + offsets < 0,
    )
    return torch.where(hull["inner"][idx, None], out, shell)


CAMERA_GROUP = 16  # cameras tested at once; a cell one of them sees skips the others


def seen_cells(res: int, aabb, c2w, bounds, *, contract: float = 0.0, ndc=None,
               chunk: int = 1 << 24) -> torch.Tensor:  # fmt: skip
    """Bool [res^3]: the grid's cells that some camera sees (the view-culling rule of the
    module's docstring). ``aabb`` the grid's box [6]; ``c2w`` [N, 3|4, 4] OpenGL cameras;
    ``bounds`` [N, 4] their image tangents (:func:`pinhole_bounds`, or
    :func:`warpnerf.data.cameras.frustum_bounds` with lens distortion); ``contract`` the inner
    half-size a of a contracted grid (0: bounded); ``ndc`` (fx, fy, W, H): the grid covers the
    NDC space of that camera (near plane 1).

    In float64 on ``c2w``'s device, in chunks of cells of about ``chunk`` (cell, plane) values;
    each plane is tested at the hull's farthest point along its normal in closed form (a box:
    ``n . centre + |n| . half``; a shell cell: its corner directions' largest ``n . d``), and
    cameras go in groups of :data:`CAMERA_GROUP`: the cells a group sees leave the test. The
    readable twin, vertex by vertex: :func:`warpnerf.reference.view_cull.seen_cells`."""
    ops._check_res(res)
    dev = c2w.device
    box = ops._box(aabb).double().to(dev)
    normals, offsets = _frustum_planes(c2w.to(dev), bounds.to(dev))
    n_cells, n_planes = res**3, normals.shape[0]
    seen = torch.zeros(n_cells, dtype=torch.bool, device=dev)
    group = 5 * CAMERA_GROUP
    step = max(1, chunk // (group * (8 if contract else 1)))
    for s in range(0, n_cells, step):
        cells = torch.arange(s, min(s + step, n_cells), device=dev)
        hull = _hulls(cells, res, box, contract, ndc)
        seen[cells] = hull["keep"]
        todo = torch.nonzero(~hull["keep"]).squeeze(1)
        for p in range(0, n_planes, group):
            if todo.numel() == 0:
                break
            out = _outside(hull, todo, normals[p : p + group], offsets[p : p + group])
            sees = ~out.reshape(todo.shape[0], -1, 5).any(-1).all(-1)  # a camera sees it
            seen[cells[todo[sees]]] = True
            todo = todo[~sees]
    return seen
