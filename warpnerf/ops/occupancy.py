"""Torch bridge for the occupancy grid and packed ray marching (kernels/occupancy.py).

No gradients flow through these ops (they place samples and keep state); the samples they emit
are composited by :func:`warpnerf.ops.render_packed`, whose backward is exact. The readable twins
are in ``warpnerf.reference.occupancy``.
"""

from __future__ import annotations

import torch

from . import bridge
from .rays import ray_aabb_intersect
from .sampling import Samples

__all__ = [
    "march_rays",
    "march_rays_contracted",
    "contract_points",
    "uncontract_points",
    "grid_cell_points",
    "grid_ema_update",
    "grid_pack_bits",
    "occupied_cells",
    "live_samples",
    "live_samples_fixed",
    "sample_points",
    "unpack_bits",
]


# Most lattice steps a ray's interval may span: k stays far from int32 overflow, and float32
# lattice positions t_lo + k * dt stay distinct.
MAX_STEPS = 1 << 24


def _empty_f(dev):
    return torch.empty(0, device=dev, dtype=torch.float32)


def _empty_i(dev):
    return torch.empty(0, device=dev, dtype=torch.int32)


def _box(aabb):
    box = torch.as_tensor(aabb, dtype=torch.float32).reshape(-1).cpu()
    if box.shape != (6,) or not bool(torch.isfinite(box).all() & (box[3:] > box[:3]).all()):
        raise ValueError("aabb must be 6 finite numbers [xmin, ymin, zmin, xmax, ymax, zmax]")
    return box


def _cell_geometry(aabb, res: int):
    from warpnerf.kernels import occupancy as K  # noqa: F401  (registers the module)

    wp = bridge.load_warp()
    box = _box(aabb)
    size = (box[3:] - box[:3]) / res
    return wp.vec3(*box[:3].tolist()), wp.vec3(*size.tolist())


def march_grid(bits: torch.Tensor, res: int, box, dt: float, contract=0.0, cone=0.0,
               occupied: torch.Tensor | None = None):  # fmt: skip
    """The marching kernels' ``MarchGrid`` of a grid's ``bits`` [res^3 / 8] uint8: the bounded
    box ``box`` [6] float32, or with ``contract`` > 0 the contracted cube of that inner
    half-size (``box`` then unread, the steps growing by ``cone``). ``occupied``: the bounded
    grid's :func:`occupied_cells` of these bits (rays are cut to them), or None."""
    from warpnerf.kernels import occupancy as K

    wp = bridge.load_warp()
    g = K.MarchGrid()
    g.bits = wp.from_torch(bits)
    g.res, g.dt, g.contracted = int(res), float(dt), int(bool(contract))
    g.a, g.cone = float(contract), float(cone)
    if not contract:
        g.lo, g.cell_size = _cell_geometry(box, res)
    if occupied is None or contract:
        g.occ = wp.from_torch(_empty_i(bits.device))
    else:
        if occupied.shape != (6,) or occupied.dtype != torch.int32:
            raise ValueError("occupied must be occupied_cells(bits, res): [6] int32")
        g.occ = wp.from_torch(occupied.to(bits.device))
    return g


def occupied_cells(bits: torch.Tensor, res: int) -> torch.Tensor:
    """The index box [lo_x, lo_y, lo_z, hi_x, hi_y, hi_z) (int32 [6], on the bits' device, no
    host sync) of a res^3 grid's occupied cells (``bits`` [res^3 / 8] uint8, cell (ix * res +
    iy) * res + iz); lo >= hi on every axis when none is. Marching reads it to cut each ray to
    that box (:func:`march_rays`'s ``occupied``)."""
    _check_res(res, bits.numel() * 8)
    occ = unpack_bits(bits).reshape(res, res, res)
    ar = torch.arange(res, device=bits.device, dtype=torch.int32)
    lo, hi = [], []
    for axes in ((1, 2), (0, 2), (0, 1)):
        line = occ.any(dim=axes[1]).any(dim=axes[0])  # [res] bool along the remaining axis
        lo.append(torch.where(line, ar, res).amin())
        hi.append(torch.where(line, ar + 1, 0).amax())
    return torch.stack(lo + hi).to(torch.int32)


def _check_rays_and_bits(origins, directions, res, bits) -> tuple:
    """(n_rays, device) of a march's rays (float32 [n, 3] on one device) after checking them and
    the grid's packed ``bits`` (uint8 [res^3 / 8] on the same device); ValueError otherwise."""
    bridge.check_float("origins", origins, (None, 3), torch.float32)
    n_rays, dev = origins.shape[0], origins.device
    bridge.check_float("directions", directions, (n_rays, 3), torch.float32, dev)
    _check_res(res)
    if bits.dtype != torch.uint8 or bits.shape != (res**3 // 8,) or bits.device != dev:
        raise ValueError(f"bits must be a uint8 tensor [{res**3 // 8}] on {dev}")
    return n_rays, dev


def _check_res(res: int, n_cells: int | None = None):
    if isinstance(res, bool) or not isinstance(res, int) or res < 2 or res % 2 or res > 1024:
        raise ValueError(f"grid resolution must be an even int in [2, 1024], got {res!r}")
    if n_cells is not None and n_cells != res**3:
        raise ValueError(f"grid has {n_cells} cells, expected res^3 = {res**3}")


def _check_cells(cells: torch.Tensor, n_cells: int, more=()) -> list:
    """Raises ValueError unless every cell index lies in [0, n_cells); ``more`` flags ride on the
    same host sync (their values are returned)."""
    flags = list(more)
    if cells.numel():
        lo, hi = torch.aminmax(cells)
        flags.append((lo >= 0) & (hi < n_cells))
    got = bridge.host_flags(*flags)
    if cells.numel() and not got[-1]:
        raise ValueError(f"cells must lie in [0, {n_cells}) (the grid's res^3 cells)")
    return got[: len(more)]


def grid_cell_points(
    cells: torch.Tensor,  # [m] int32/int64 cell indices in [0, res^3)
    jitter: torch.Tensor,  # [m, 3] float32 in [0, 1)
    res: int,
    aabb,
    *,
    check: bool = True,
) -> torch.Tensor:
    """Points ``lo + (cell + jitter) * cell_size`` [m, 3] (one per listed cell).

    Cells outside [0, res^3) raise ValueError (one reduction and one host sync on CUDA;
    ``check=False`` skips it for cells the caller drew itself, as :class:`OccupancyGrid` does).
    """
    from warpnerf.kernels import occupancy as K

    _check_res(res)
    bridge.check_index("cells", cells, (None,))
    m, dev = cells.shape[0], cells.device
    bridge.check_float("jitter", jitter, (m, 3), torch.float32, dev)
    if check:
        _check_cells(cells, res**3)
    lo, size = _cell_geometry(aabb, res)
    points = torch.empty(m, 3, device=dev, dtype=torch.float32)
    wp = bridge.load_warp()
    inputs = [bridge.arr(cells.to(torch.int32)), bridge.arr(jitter), res, lo, size]
    bridge.launch(K.cell_points, m, inputs + [bridge.arr(points, wp.vec3)], dev)
    return points


def grid_ema_update(
    density: torch.Tensor,  # [res^3] float32, updated in place
    cells: torch.Tensor,  # [m] int32
    values: torch.Tensor,  # [m] float32 densities at the cells' points
    decay: float,
) -> torch.Tensor:
    """``density[c] = max(decay * density[c], max of values at c)`` for every listed cell c
    (duplicates allowed: the maximum wins). NaN values, and cells outside [0, len(density)),
    raise ValueError (checked together: one host sync on CUDA)."""
    from warpnerf.kernels import occupancy as K

    dev = density.device
    bridge.check_float("density", density, (None,), torch.float32)
    bridge.check_index("cells", cells, (None,), dev)
    bridge.check_float("values", values, (cells.shape[0],), torch.float32, dev)
    if not 0.0 <= decay <= 1.0:
        raise ValueError(f"decay must be in [0, 1], got {decay}")
    if values.numel():
        (has_nan,) = _check_cells(cells, density.shape[0], [torch.isnan(values).any()])
        if has_nan:
            raise ValueError(
                "the field returned NaN densities; the occupancy grid cannot be updated"
            )
    newmax = torch.full_like(density, -1.0)
    a = bridge.arr
    cells = cells.to(torch.int32)
    bridge.launch(K.scatter_max, cells.shape[0], [a(cells), a(values), a(newmax)], dev)
    bridge.launch(K.ema, density.shape[0], [a(newmax), float(decay), a(density)], dev)
    return density


def grid_pack_bits(density: torch.Tensor, threshold: float) -> torch.Tensor:
    """Bitfield [n_cells / 8] uint8 of ``density > threshold`` (bit c & 7 of byte c >> 3)."""
    from warpnerf.kernels import occupancy as K

    bridge.check_float("density", density, (None,), torch.float32)
    n = density.shape[0]
    if n % 8:
        raise ValueError(f"the number of cells must be a multiple of 8, got {n}")
    bits = torch.empty(n // 8, device=density.device, dtype=torch.uint8)
    a = bridge.arr
    bridge.launch(K.pack_bits, n // 8, [a(density), float(threshold), a(bits)], density.device)
    return bits


def unpack_bits(bits: torch.Tensor) -> torch.Tensor:
    """Bool [n_cells] from a bitfield [n_cells / 8] uint8."""
    shifts = torch.arange(8, device=bits.device, dtype=torch.uint8)
    return ((bits.unsqueeze(-1) >> shifts) & 1).bool().reshape(-1)


def march_rays(
    origins: torch.Tensor,  # [n_rays, 3] float32
    directions: torch.Tensor,  # [n_rays, 3] float32
    near,  # float or [n_rays]
    far,  # float or [n_rays]
    bits: torch.Tensor,  # [res^3 / 8] uint8
    res: int,
    aabb,  # [6]
    dt: float,
    *,
    jitter: torch.Tensor | None = None,  # [n_rays] in [0, 1): lattice shift (training)
    k_begin: torch.Tensor | None = None,  # [n_rays] int32: resume each ray at this index
    max_samples: int = 1024,
    capacity: int | None = None,
    occupied: torch.Tensor | None = None,  # [6] int32: occupied_cells(bits, res)
):
    """Packed samples in the occupied cells along each ray (see kernels/occupancy.py).
    ``occupied`` (:func:`occupied_cells` of these bits; a grid keeps it with its bits) cuts
    each ray to the occupied cells' box first: the same samples, less marching through the
    empty space before and after them.

    A ray's lattice of step ``dt`` starts at ``t_lo = max(near, box entry)`` (shifted by
    ``jitter * dt``) and ends at ``t_hi = min(far, box exit)``; an interval is kept when the grid
    cell of its midpoint is occupied. At most ``max_samples`` per ray per call.

    Returns:
        (Samples with t_starts, t_ends [n] float32, ray_indices [n] int32, packed_info
        [n_rays, 2] int32, and k_next [n_rays] int32: the lattice index to continue from, -1 when
        the ray has no more samples).
    Raises ValueError for non-finite origins/directions, zero directions, NaN near/far, bad
    shapes, dt <= 0, a ray whose interval spans more than ``MAX_STEPS`` lattice steps, ``jitter``
    outside [0, 1) or ``k_begin`` outside [-1, 2^31); IndexDtypeError (a TypeError and
    ValueError) for a float ``k_begin``. These value checks cost no extra host sync: offending
    rays are given no samples before the kernel runs (it could otherwise loop for ~2^31 steps)
    and the error is raised at the sync that reads the sample total, which marching needs anyway.

    ``capacity`` (static shapes: a training step captured in a CUDA graph): the outputs have
    exactly ``capacity`` slots and nothing is read back to the host. Rays keep their samples in
    ray order until the buffer is full; later rays lose theirs (deterministically: by ray
    order), and packed_info says what each ray kept. Slots past the samples hold t = 0 and
    ray 0 (finite, referenced by no ray). Refused rays get no samples and no error. Returns
    ``(Samples, k_next, stats)`` with ``stats`` an int64 device tensor [3]: (samples marched,
    samples dropped for want of capacity, rays refused).
    """
    from warpnerf.kernels import occupancy as K

    wp = bridge.load_warp()
    n_rays, dev = _check_rays_and_bits(origins, directions, res, bits)
    if isinstance(dt, torch.Tensor) or not (dt > 0 and dt < float("inf")):
        raise ValueError(f"need dt > 0 (a finite float), got {dt}")
    max_samples = bridge.check_int("max_samples", max_samples, lo=1)
    if n_rays > bridge.INT32_MAX:
        raise ValueError(f"{n_rays} rays exceed int32 indices: march fewer at once")
    box = _box(aabb)
    t_lo, t_hi, bad, near, far = lattice_bounds(origins, directions, near, far, box, dt)
    jit, kb, bad = _lattice_inputs(jitter, k_begin, n_rays, dev, bad)
    jitter = None if jitter is None else jit  # (a refusal's message checks what the kernel saw)
    t_lo, t_hi = t_lo.contiguous(), torch.where(bad, t_lo, t_hi).contiguous()
    a = bridge.arr
    head = [a(origins, wp.vec3), a(directions, wp.vec3), a(t_lo), a(t_hi), a(jit), a(kb),
            march_grid(bits, res, box, dt, occupied=occupied), int(max_samples)]  # fmt: skip

    def refuse():
        raise_bad_rays(origins, directions, near, far, dt, jitter, k_begin)

    return _march_passes(K.march, head, n_rays, bad, capacity, dev, refuse)


def lattice_bounds(origins, directions, near, far, aabb, dt: float) -> tuple:
    """A bounded march's per-ray lattice: ``(t_lo, t_hi, bad, near, far)`` [n_rays] float32
    (``t_lo = max(near, box entry)``, ``t_hi = min(far, box exit)``, ``t_lo`` for a miss) and
    ``bad`` [n_rays] bool, the rays a marching kernel must not see (refused: give them no
    samples, then :func:`raise_bad_rays` after the caller's host sync). ``near``/``far`` are
    returned expanded to [n_rays]."""
    n_rays, dev = origins.shape[0], origins.device
    near = bridge.constant(near, dev, torch.float32).expand(n_rays)
    far = bridge.constant(far, dev, torch.float32).expand(n_rays)
    t_in, t_out, hit = ray_aabb_intersect(origins, directions, aabb)
    t_lo = torch.maximum(t_in, near)
    t_hi = torch.where(hit, torch.minimum(t_out, far), t_lo)
    # Rays the kernel must not see, in one fused test per ray (few launches: rendering marches
    # in many rounds): a NaN/Inf origin, direction or near, or a zero direction (1 / max |d| is
    # inf) make x non-finite; a NaN far or an interval of more than MAX_STEPS lattice steps
    # (k would outgrow int32 and float32 steps) fail the span test. Such rays get no samples;
    # which check failed is worked out after the caller's one host sync, only when one did.
    x = origins.sum(-1) + directions.sum(-1) + near + directions.abs().amax(-1).reciprocal()
    bad = ~(torch.isfinite(x) & ((t_hi - t_lo) < MAX_STEPS * float(dt)))
    return t_lo, t_hi, bad, near, far


def _march_passes(kernel, head: list, n_rays: int, bad, capacity, dev, refuse) -> tuple:
    """A marcher's launches of ``kernel`` on its inputs ``head``: the count pass, then with
    ``capacity`` the fill into static slots (:func:`_fill_fixed`), else the one host sync (the
    sample total and whether any ray was refused: then ``refuse()`` raises) and the packed fill.
    Returns ``march_rays``'s result."""
    a = bridge.arr
    counts = torch.empty(n_rays, device=dev, dtype=torch.int32)
    k_next = torch.empty(n_rays, device=dev, dtype=torch.int32)
    no_f, no_i = a(_empty_f(dev)), a(_empty_i(dev))
    bridge.launch(kernel, n_rays, head + [0, no_i, a(counts), a(k_next), no_f, no_f, no_i], dev)
    if capacity is not None:
        return _fill_fixed(kernel, head, counts, k_next, bad, capacity, dev)
    csum = torch.cumsum(counts, 0, dtype=torch.int64)
    total = csum[-1:] if n_rays else torch.zeros(1, device=dev, dtype=torch.int64)
    # the one host sync: the sample total and whether any ray was refused
    total, refused = torch.cat([total, bad.any().reshape(1).to(torch.int64)]).tolist()
    if refused:
        refuse()
    offsets, t_starts, t_ends, ray_indices = _packed_outputs(total, csum, counts, dev)
    if total:
        fill = [1, a(offsets), a(counts), a(k_next), a(t_starts), a(t_ends), a(ray_indices)]
        bridge.launch(kernel, n_rays, head + fill, dev)
    packed_info = torch.stack([offsets, counts], -1)
    return Samples(t_starts, t_ends, ray_indices, packed_info), k_next


def _fill_fixed(kernel, head: list, counts, k_next, bad, capacity: int, dev) -> tuple:
    """The fill pass into ``capacity`` slots, with no host sync (see ``march_rays``'s
    ``capacity``): each ray keeps ``clamp(capacity - offset, 0, count)`` of its samples."""
    capacity = bridge.check_int("capacity", capacity, lo=1)
    csum = torch.cumsum(counts, 0, dtype=torch.int64)
    offsets64 = csum - counts
    kept = torch.minimum((capacity - offsets64).clamp_min(0), counts.to(torch.int64))
    offsets, kept = offsets64.clamp_max(capacity).to(torch.int32), kept.to(torch.int32)
    # slots no ray writes stay finite: t = 0 on ray 0 (positions are the ray's origin)
    t_starts = torch.zeros(capacity, device=dev, dtype=torch.float32)
    t_ends = torch.zeros(capacity, device=dev, dtype=torch.float32)
    ray_indices = torch.zeros(capacity, device=dev, dtype=torch.int32)
    a = bridge.arr
    fill = [1, a(offsets), a(kept), a(k_next), a(t_starts), a(t_ends), a(ray_indices)]
    bridge.launch(kernel, counts.shape[0], head + fill, dev)
    total = csum[-1] if counts.numel() else torch.zeros((), device=dev, dtype=torch.int64)
    stats = torch.stack([total, (total - capacity).clamp_min(0), bad.sum()])
    packed_info = torch.stack([offsets, kept], -1)
    return Samples(t_starts, t_ends, ray_indices, packed_info), k_next, stats


def _packed_outputs(total: int, csum, counts, dev) -> tuple:
    """The marchers' fill-pass outputs for ``total`` samples: (first slot per ray int32, t_starts,
    t_ends, ray_indices); ValueError past int32 offsets."""
    if total >= 2**31:
        raise ValueError(f"{total} samples exceed int32 offsets: march fewer rays at once")
    offsets = (csum - counts).to(torch.int32)
    t_starts = torch.empty(total, device=dev, dtype=torch.float32)
    t_ends = torch.empty(total, device=dev, dtype=torch.float32)
    return offsets, t_starts, t_ends, torch.empty(total, device=dev, dtype=torch.int32)


def _lattice_inputs(jitter, k_begin, n_rays: int, dev, bad):
    """The marchers' optional per-ray lattice inputs, checked and in the kernels' dtypes: (jitter
    float32 or an empty array, k_begin int32 or an empty array, ``bad`` with the rays whose
    values are out of range: jitter outside [0, 1) or NaN, k_begin below -1 or beyond int32)."""
    jit, kb = _empty_f(dev), _empty_i(dev)
    if jitter is not None:
        bridge.check_float("jitter", jitter, (n_rays,), device=dev)
        jit = jitter.to(torch.float32).contiguous()  # checked as the kernel sees it
        bad = bad | ~((jit >= 0) & (jit < 1))  # NaN included
    if k_begin is not None:
        bridge.check_index("k_begin", k_begin, (n_rays,), dev)
        if k_begin.dtype == torch.int32:
            bad = bad | (k_begin < -1)
            kb = k_begin.contiguous()
        else:
            bad = bad | (k_begin < -1) | (k_begin > bridge.INT32_MAX)
            kb = k_begin.clamp(-1, bridge.INT32_MAX).to(torch.int32).contiguous()
    return jit, kb, bad


def contract_points(points: torch.Tensor, a: float) -> torch.Tensor:
    """mip-NeRF 360's contraction with the max norm (nerfstudio's for grids), pure torch
    (shared by the field, the grid and the kernels' twin): ``p`` inside the cube [-a, a]^3 stays,
    beyond it ``a (2 - 1/m) u / m`` with ``u = p / a``, ``m = |u|_inf``; all of space lands in
    [-2a, 2a]^3. points [..., 3] -> [..., 3]."""
    m = points.abs().amax(-1, keepdim=True) / a
    scale = torch.where(m <= 1, torch.ones_like(m), (2 - 1 / m.clamp_min(1)) / m.clamp_min(1))
    return points * scale


def is_contracted_box(box: torch.Tensor, a: float) -> bool:
    """Whether a float32 box [6] is the contracted cube [-2a, 2a]^3."""
    return torch.equal(box.cpu(), torch.tensor([-2.0 * a] * 3 + [2.0 * a] * 3))


# the inverse's largest contracted max-norm, in units of a: points that close to the cube's
# surface map to 1e4 a (the outermost cells stand for everything beyond)
UNCONTRACT_LIMIT = 2.0 - 1e-4


def uncontract_points(c: torch.Tensor, a: float) -> torch.Tensor:
    """The inverse of :func:`contract_points` on [-2a, 2a]^3: ``c / (m (2 - m))`` for
    ``m = |c / a|_inf`` > 1 (clamped at ``UNCONTRACT_LIMIT``), so points stay finite."""
    m = (c.abs().amax(-1, keepdim=True) / a).clamp(max=UNCONTRACT_LIMIT)
    mc = m.clamp_min(1)
    return c * torch.where(m <= 1, torch.ones_like(m), 1 / (mc * (2 - mc)))


def lattice_s(t: torch.Tensor, dt: float, cone: float) -> torch.Tensor:
    """The lattice coordinate of distance ``t`` >= 0 (inverse of the kernels' ``lattice_t``):
    ``t / dt`` up to ``dt / cone``, then ``1 / cone + log(t cone / dt) / cone``."""
    if cone <= 0:
        return t / dt
    return torch.where(
        t * cone <= dt, t / dt, 1 / cone + torch.log((t * cone / dt).clamp_min(1)) / cone
    )


def march_rays_contracted(
    origins: torch.Tensor,  # [n_rays, 3] float32
    directions: torch.Tensor,  # [n_rays, 3] float32
    near,  # float or [n_rays]
    far,  # float or [n_rays]
    bits: torch.Tensor,  # [res^3 / 8] uint8, cells of the contracted cube [-2a, 2a]^3
    res: int,
    a: float,
    dt: float,
    cone: float,
    *,
    jitter: torch.Tensor | None = None,  # [n_rays] in [0, 1)
    k_begin: torch.Tensor | None = None,  # [n_rays] int32
    max_samples: int = 1024,
    capacity: int | None = None,
):
    """Packed samples of an unbounded scene (see kernels/occupancy.py, "the contracted grid"):
    lattice intervals from ``near`` to ``far`` whose steps are ``dt`` up to distance
    ``dt / cone`` and grow as ``cone * t`` beyond, kept where the cell of the contracted
    midpoint (:func:`contract_points` with inner half-size ``a``) is occupied. Returns and
    errors as :func:`march_rays` (the span test counts lattice steps, so a far plane of
    thousands of ``a`` costs only a few thousand steps with a cone)."""
    from warpnerf.kernels import occupancy as K

    wp = bridge.load_warp()
    n_rays, dev = _check_rays_and_bits(origins, directions, res, bits)
    for name, v, ok in (("a", a, a > 0), ("dt", dt, dt > 0), ("cone", cone, cone >= 0)):
        if isinstance(v, torch.Tensor) or not (ok and v < float("inf")):
            raise ValueError(f"need a finite float {name} ({'>= 0' if name == 'cone' else '> 0'})"
                             f", got {v}")  # fmt: skip
    max_samples = bridge.check_int("max_samples", max_samples, lo=1)
    if n_rays > bridge.INT32_MAX:
        raise ValueError(f"{n_rays} rays exceed int32 indices: march fewer at once")
    s_lo, far, bad, near = lattice_bounds_contracted(origins, directions, near, far, dt, cone)
    jit, kb, bad = _lattice_inputs(jitter, k_begin, n_rays, dev, bad)
    jitter = None if jitter is None else jit  # (a refusal's message checks what the kernel saw)
    t_hi = torch.where(bad, torch.zeros_like(far), far).contiguous()  # refused: no samples
    s_lo = torch.where(bad, torch.zeros_like(s_lo), s_lo).contiguous()
    a_ = bridge.arr
    head = [a_(origins, wp.vec3), a_(directions, wp.vec3), a_(s_lo), a_(t_hi), a_(jit), a_(kb),
            march_grid(bits, res, None, dt, contract=a, cone=cone), int(max_samples)]  # fmt: skip

    def refuse():
        raise_bad_rays(origins, directions, near, far, dt, jitter, k_begin, contracted=True)

    return _march_passes(K.march, head, n_rays, bad, capacity, dev, refuse)


def lattice_bounds_contracted(origins, directions, near, far, dt: float, cone: float) -> tuple:
    """A contracted march's per-ray lattice: ``(s_lo, far, bad, near)`` [n_rays] (``s_lo`` the
    lattice coordinate of near, far and near expanded to [n_rays]; ``bad`` as in
    :func:`lattice_bounds`, plus a negative near)."""
    n_rays, dev = origins.shape[0], origins.device
    near = bridge.constant(near, dev, torch.float32).expand(n_rays)
    far = bridge.constant(far, dev, torch.float32).expand(n_rays)
    s_lo = lattice_s(near.clamp_min(0), float(dt), float(cone))
    s_hi = lattice_s(far.clamp_min(0), float(dt), float(cone))
    # as in march_rays: refused rays get no samples, the error comes at the one host sync
    x = origins.sum(-1) + directions.sum(-1) + near + directions.abs().amax(-1).reciprocal()
    bad = ~(torch.isfinite(x) & (near >= 0) & ((s_hi - s_lo) < MAX_STEPS))
    return s_lo, far, bad, near


def raise_bad_rays(origins, directions, near, far, dt, jitter=None, k_begin=None, *,
                   contracted=False):  # fmt: skip
    """The ValueError for rays a marcher refused (:func:`lattice_bounds`'s ``bad``; the slow
    path: only after a refusal), naming the wrong input. ``contracted``: a negative near too."""
    if contracted and not bool((near >= 0).all()):
        raise ValueError("near must be >= 0 for contracted marching")
    finite = torch.isfinite(origins).all() & torch.isfinite(directions).all()
    finite &= torch.isfinite(near).all() & ~torch.isnan(far).any()
    if not bool(finite & (directions.abs().amax(-1) > 0).all()):
        raise ValueError(
            "origins, directions and near must be finite, far not NaN, directions non-zero"
        )
    if jitter is not None and not bool(((jitter >= 0) & (jitter < 1)).all()):
        raise ValueError("jitter must lie in [0, 1)")
    if k_begin is not None and not bool(((k_begin >= -1) & (k_begin <= bridge.INT32_MAX)).all()):
        raise ValueError("k_begin must be -1 (done) or a lattice index in [0, 2^31)")
    raise ValueError(
        f"a ray spans more than {MAX_STEPS} lattice steps of dt={dt} (directions too short, "
        "dt too small for the box, or a value overflowed)"
    )


# the live-sample compaction after marching (ops/live.py), re-exported here
from .live import live_samples, live_samples_fixed, sample_points  # noqa: E402
