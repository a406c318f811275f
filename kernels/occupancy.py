"""Occupancy grid and packed ray marching (pure Warp, float32, no gradients).

The grid is a cube of ``res^3`` cells over the scene box ``lo .. hi``; cell ``c = (ix * res + iy)
* res + iz``. It keeps one density value per cell (an EMA of the field's density at points in the
cell) and a bitfield (``uint8``, 8 cells per byte, bit ``c & 7`` of byte ``c >> 3``) of the cells
whose value is above the threshold.

Update (every N training steps, :class:`warpnerf.OccupancyGrid`):
    points  = lo + (cell + jitter) * cell_size           cell_points
    newmax  = max over the update's points in a cell      scatter_max (atomic max: order-free)
    density = max(decay * density, newmax)  for the cells evaluated in this update   ema
    bits    = density > threshold                          pack_bits

Marching. A ray's samples lie on a lattice of fixed step ``dt`` anchored at the start of its
interval ``[t_lo, t_hi]`` (the scene box clipped to near/far, computed by the caller):
    interval k = [t_lo + (k + j) dt, min(t_lo + (k + j + 1) dt, t_hi)],  j = the ray's jitter
is emitted when the cell holding its midpoint is occupied. From an empty cell the ray jumps to
the first lattice interval whose midpoint lies past the cell's exit (DDA over the cells), then
backs off while the previous interval's midpoint is already outside the cell by the occupancy
test's own floor() (rounding can only re-test an interval, never skip one; rays nearly parallel
to a cell face need this: the exit plane and floor() then disagree by ~ulp / |d|). Samples therefore
are exactly the dense lattice intervals whose midpoint cell is occupied (tests compare with that
brute force). One kernel serves both passes: ``fill == 0`` counts a ray's samples (capped at
``max_samples``), ``fill == 1`` writes the first ``counts[r]`` of them at the ray's offset (the
exclusive prefix sum of the counts; fewer than counted where a fixed-capacity buffer is full).
``k_next`` returns where the ray stopped, so rendering can march in rounds (-1: done). The
same kernel marches the contracted grid of unbounded scenes (below): a ``MarchGrid`` says which
lattice a launch walks, and ``next_occupied`` is the one rule per step that the marcher and the
rendering tracer (kernels/tracer.py) share.
"""

import warp as wp

SKIP_MARGIN = 1.0e-3  # in units of dt: how far before a cell's exit the marcher lands


@wp.kernel(enable_backward=False)
def cell_points(
    cells: wp.array(dtype=wp.int32),  # [m] cell indices
    jitter: wp.array2d(dtype=float),  # [m, 3] in [0, 1)
    res: int,
    lo: wp.vec3,
    cell_size: wp.vec3,
    points: wp.array(dtype=wp.vec3),  # [m] out
):
    i = wp.tid()
    c = cells[i]
    ix = c // (res * res)
    iy = (c // res) % res
    iz = c % res
    points[i] = wp.vec3(
        lo[0] + (float(ix) + jitter[i, 0]) * cell_size[0],
        lo[1] + (float(iy) + jitter[i, 1]) * cell_size[1],
        lo[2] + (float(iz) + jitter[i, 2]) * cell_size[2],
    )


@wp.kernel(enable_backward=False)
def scatter_max(
    cells: wp.array(dtype=wp.int32),  # [m]
    values: wp.array(dtype=float),  # [m] densities >= 0 (NaN rejected by the caller)
    newmax: wp.array(dtype=float),  # [res^3] -1 where not evaluated; out
):
    i = wp.tid()
    wp.atomic_max(newmax, cells[i], wp.max(values[i], 0.0))


@wp.kernel(enable_backward=False)
def ema(
    newmax: wp.array(dtype=float),  # [res^3]
    decay: float,
    density: wp.array(dtype=float),  # [res^3] in/out
):
    c = wp.tid()
    v = newmax[c]
    if v >= 0.0:
        density[c] = wp.max(density[c] * decay, v)


@wp.kernel(enable_backward=False)
def pack_bits(
    density: wp.array(dtype=float),  # [res^3]
    threshold: float,
    bits: wp.array(dtype=wp.uint8),  # [res^3 / 8] out
):
    j = wp.tid()
    word = int(0)
    for b in range(8):
        if density[j * 8 + b] > threshold:
            word = word | (1 << b)
    bits[j] = wp.uint8(word)


@wp.func
def occupied(bits: wp.array(dtype=wp.uint8), c: int):
    return (int(bits[c >> 3]) >> (c & 7)) & 1


@wp.func
def cell_coord(x: float, lo: float, inv_size: float, res: int):
    return wp.clamp(int(wp.floor((x - lo) * inv_size)), 0, res - 1)


@wp.func
def axis_exit(o: float, d: float, lo: float, size: float, i: int):
    """t at which the ray leaves cell column i of one axis (inf for d == 0)."""
    if d > 0.0:
        return (lo + float(i + 1) * size - o) / d
    if d < 0.0:
        return (lo + float(i) * size - o) / d
    return float(wp.inf)


@wp.func
def march_next(
    o: wp.vec3,
    d: wp.vec3,
    t0: float,
    t1: float,
    j: float,
    k: int,
    bits: wp.array(dtype=wp.uint8),
    res: int,
    lo: wp.vec3,
    cell_size: wp.vec3,
    inv: wp.vec3,
    dt: float,
):
    """A ray's first lattice interval at index >= k (k >= 0) whose midpoint cell is occupied:
    (its index, or -1 when the ray has none left; its start s and end e). The marching rule of
    the module's docstring (DDA skips over empty cells, backed off to floor()'s rounding)."""
    found = int(-1)
    s = float(0.0)
    e = float(0.0)
    while k >= 0 and found < 0:
        s = t0 + (float(k) + j) * dt
        if s >= t1:
            k = -1
        else:
            e = wp.min(s + dt, t1)
            m = 0.5 * (s + e)
            p = o + d * m
            ix = cell_coord(p[0], lo[0], inv[0], res)
            iy = cell_coord(p[1], lo[1], inv[1], res)
            iz = cell_coord(p[2], lo[2], inv[2], res)
            if occupied(bits, (ix * res + iy) * res + iz) != 0:
                found = k
            else:
                t_exit = wp.min(
                    axis_exit(o[0], d[0], lo[0], cell_size[0], ix),
                    wp.min(
                        axis_exit(o[1], d[1], lo[1], cell_size[1], iy),
                        axis_exit(o[2], d[2], lo[2], cell_size[2], iz),
                    ),
                )
                if not (t_exit < t1):
                    k = -1  # the rest of the ray lies in this empty cell
                else:
                    # first k whose midpoint t0 + (k + j + 1/2) dt is past t_exit, less a
                    # margin ...
                    kn = int(wp.ceil((t_exit - t0) / dt - j - 0.5 - SKIP_MARGIN))
                    # ... then back off while the interval before it still leaves this cell by
                    # the occupancy test's own rounding (for rays nearly parallel to a cell face
                    # the exact exit plane and floor() disagree by ~ulp / |d|, far more than the
                    # margin)
                    while kn - 1 > k:
                        sb = t0 + (float(kn - 1) + j) * dt
                        pb = o + d * (0.5 * (sb + wp.min(sb + dt, t1)))
                        jx = cell_coord(pb[0], lo[0], inv[0], res)
                        jy = cell_coord(pb[1], lo[1], inv[1], res)
                        jz = cell_coord(pb[2], lo[2], inv[2], res)
                        if jx == ix and jy == iy and jz == iz:
                            break
                        kn -= 1
                    k = wp.max(k + 1, kn)
    return found, s, e


# --- Unbounded scenes: the contracted grid ---------------------------------------------------
#
# Contraction (mip-NeRF 360's map, with the max norm as nerfstudio uses it for grids): with
# u = p / a (a: the half-size of the inner cube, which holds the cameras) and m = |u|_inf,
#     contract(p) = p                          for m <= 1
#                 = a (2 - 1/m) u / m          beyond,
# so all of space lands in the cube [-2a, 2a]^3; the grid's res^3 cells cover that cube.
#
# Marching steps grow with distance (instant-ngp's cone): the lattice is uniform in a coordinate
# s along the ray whose step in t (distance from the ray's origin) is dt up to t_sw = dt / cone,
# then cone * t:
#     t(s) = s dt                          for s <= 1 / cone (and always when cone == 0)
#          = (dt / cone) exp(cone s - 1)    beyond,
# interval k = [t(s0 + k + j), min(t(s0 + k + j + 1), t_hi)], s0 = s(t_lo), j the jitter. It is
# kept when the contracted cell of its midpoint is occupied. Cells in contracted space are not
# world-space boxes, so there is no DDA skipping: every lattice interval is tested (a few
# thousand per ray at most: s grows with log t).


@wp.func
def contract(p: wp.vec3, a: float):
    m = wp.max(wp.abs(p[0]), wp.max(wp.abs(p[1]), wp.abs(p[2]))) / a
    if m <= 1.0:
        return p
    return p * ((2.0 - 1.0 / m) / m)


@wp.func
def lattice_t(s: float, dt: float, cone: float):
    if cone <= 0.0 or s * cone <= 1.0:
        return s * dt
    return dt / cone * wp.exp(cone * s - 1.0)


@wp.func
def march_next_contracted(
    o: wp.vec3,
    d: wp.vec3,
    s0: float,
    t1: float,
    j: float,
    k: int,
    bits: wp.array(dtype=wp.uint8),
    res: int,
    a: float,
    dt: float,
    cone: float,
):
    """:func:`march_next` on the contracted grid: every lattice interval from index k on is
    tested (no skipping); (index or -1, start, end)."""
    lo = -2.0 * a
    inv = float(res) / (4.0 * a)
    found = int(-1)
    s = float(0.0)
    e = float(0.0)
    while k >= 0 and found < 0:
        s = lattice_t(s0 + float(k) + j, dt, cone)
        if s >= t1:
            k = -1
        else:
            e = wp.min(lattice_t(s0 + float(k + 1) + j, dt, cone), t1)
            p = contract(o + d * (0.5 * (s + e)), a)
            ix = cell_coord(p[0], lo, inv, res)
            iy = cell_coord(p[1], lo, inv, res)
            iz = cell_coord(p[2], lo, inv, res)
            if occupied(bits, (ix * res + iy) * res + iz) != 0:
                found = k
            else:
                k += 1
    return found, s, e


# --- One marcher for both grids ---------------------------------------------------------------


@wp.struct
class MarchGrid:
    """What a marcher reads of a grid: its bitfield and its lattice, bounded (the box ``lo ..
    lo + res * cell_size``, DDA skipping) or contracted (the cube [-2a, 2a]^3, steps growing by
    ``cone``: "the contracted grid" below)."""

    bits: wp.array(dtype=wp.uint8)  # [res^3 / 8]
    res: int
    lo: wp.vec3  # bounded: the box's lower corner
    cell_size: wp.vec3  # bounded
    dt: float
    contracted: int
    a: float  # contracted: the inner cube's half-size
    cone: float  # contracted: the step's growth
    occ: wp.array(dtype=wp.int32)  # bounded: [6] the occupied cells' index box [lo, hi), or [0]


@wp.func
def clip_to_occupied(grid: MarchGrid, o: wp.vec3, d: wp.vec3, t0: float, t1: float, k: int):
    """(k, t1) of a bounded ray cut to the occupied cells (``grid.occ``, the index box of every
    occupied cell, grown by one cell against rounding): the ray's first lattice index k moves up
    to two intervals before the grown box's entry, its end t1 down to one step past its exit,
    -1 when the ray misses it. Exact: an interval the march emits has its midpoint in an
    occupied cell, so inside the box, hence at index >= the new k and ending before the new t1
    (the interval cut by the new t1 starts past the exit: its midpoint tests empty as before)."""
    occ = grid.occ
    if occ[0] >= occ[3] or occ[1] >= occ[4] or occ[2] >= occ[5]:
        return int(-1), t1  # no occupied cell
    te = float(-wp.inf)
    tx = float(wp.inf)
    for i in range(3):
        lo = grid.lo[i] + float(occ[i] - 1) * grid.cell_size[i]
        hi = grid.lo[i] + float(occ[i + 3] + 1) * grid.cell_size[i]
        if d[i] == 0.0:
            if o[i] < lo or o[i] > hi:
                te = float(wp.inf)
        else:
            ta = (lo - o[i]) / d[i]
            tb = (hi - o[i]) / d[i]
            te = wp.max(te, wp.min(ta, tb))
            tx = wp.min(tx, wp.max(ta, tb))
    t1 = wp.min(t1, tx + grid.dt)
    if not (te < t1) or not (t1 > t0):
        return int(-1), t1
    if te > t0:  # (and te < t1: the index fits the lattice's span, checked by the caller)
        k = wp.max(k, int(wp.floor((te - t0) / grid.dt)) - 2)
    return k, t1


@wp.func
def next_occupied(grid: MarchGrid, o: wp.vec3, d: wp.vec3, t0: float, t1: float, j: float, k: int):
    """:func:`march_next` or :func:`march_next_contracted`, as the grid is: (index or -1, start,
    end) of the ray's first occupied lattice interval at index >= k (t0: the bounded lattice's
    anchor, or the contracted lattice's coordinate of near)."""
    if grid.contracted != 0:
        return march_next_contracted(o, d, t0, t1, j, k, grid.bits, grid.res, grid.a, grid.dt,
                                     grid.cone)  # fmt: skip
    size = grid.cell_size
    inv = wp.vec3(1.0 / size[0], 1.0 / size[1], 1.0 / size[2])
    return march_next(o, d, t0, t1, j, k, grid.bits, grid.res, grid.lo, size, inv, grid.dt)


@wp.kernel(enable_backward=False)
def march(
    origins: wp.array(dtype=wp.vec3),  # [n_rays]
    directions: wp.array(dtype=wp.vec3),  # [n_rays]
    t_lo: wp.array(dtype=float),  # [n_rays] lattice anchor (box entry clipped to near) or s(near)
    t_hi: wp.array(dtype=float),  # [n_rays] end (box exit or far); bounded, <= t_lo: no samples
    jitter: wp.array(dtype=float),  # [n_rays] lattice shift in [0, 1), or [0] for none
    k_begin: wp.array(dtype=wp.int32),  # [n_rays] first lattice index, or [0] for 0
    grid: MarchGrid,
    max_samples: int,
    fill: int,
    offsets: wp.array(dtype=wp.int32),  # [n_rays] first output slot (fill pass)
    counts: wp.array(dtype=wp.int32),  # [n_rays] out (count pass); in (fill pass): samples to write
    k_next: wp.array(dtype=wp.int32),  # [n_rays] out (count pass): next index, -1 = done
    t_starts: wp.array(dtype=float),  # [n] out (fill pass)
    t_ends: wp.array(dtype=float),  # [n] out (fill pass)
    ray_indices: wp.array(dtype=wp.int32),  # [n] out (fill pass)
):
    r = wp.tid()
    o = origins[r]
    d = directions[r]
    t0 = t_lo[r]
    t1 = t_hi[r]
    j = float(0.0)
    if jitter.shape[0] > 0:
        j = jitter[r]
    k = int(0)
    if k_begin.shape[0] > 0:
        k = int(k_begin[r])
    n = int(0)
    base = int(0)
    limit = max_samples
    if fill != 0:
        base = int(offsets[r])
        limit = int(counts[r])  # the count pass's own, or fewer (a fixed-capacity buffer)
    if k < 0 or (grid.contracted == 0 and not (t1 > t0)):
        k = -1
    if k >= 0 and grid.contracted == 0 and grid.occ.shape[0] == 6:
        k, t1 = clip_to_occupied(grid, o, d, t0, t1, k)
    while k >= 0 and n < limit:
        found, s, e = next_occupied(grid, o, d, t0, t1, j, k)
        if found < 0:
            k = -1
            break
        if fill != 0:
            t_starts[base + n] = s
            t_ends[base + n] = e
            ray_indices[base + n] = r
        n += 1
        k = found + 1
    if fill == 0:
        counts[r] = n
        k_next[r] = k


@wp.kernel(enable_backward=False)
def live_counts(
    packed_info: wp.array2d(dtype=wp.int32),  # [n_rays, 2]
    t_starts: wp.array(dtype=float),  # [n]
    t_ends: wp.array(dtype=float),  # [n]
    sigmas: wp.array(dtype=float),  # [n]
    t_threshold: float,
    n_live: wp.array(dtype=wp.int32),  # [n_rays] out
):
    """The compositing kernels' early-termination rule on densities alone: a ray's live samples
    are those before the first one whose transmittance T_i = exp(-sum_{j<i} sigma_j delta_j) is
    below t_threshold."""
    r = wp.tid()
    start = int(packed_info[r, 0])
    count = int(packed_info[r, 1])
    log_t = float(0.0)
    m = count
    for k in range(count):
        i = start + k
        if wp.exp(log_t) < t_threshold:
            m = k
            break
        log_t -= sigmas[i] * (t_ends[i] - t_starts[i])
    n_live[r] = m


# --- The static-shape step's per-sample gathers (warpnerf.render_marched_fixed) -------------
#
# Positions of packed samples, o[r] + d[r] (t_start + t_end) / 2 with r the sample's ray, and
# the compaction of each ray's live samples into a buffer of fixed capacity: kept slot i of the
# ray r with first[r] <= i < first[r] + n_live[r] (first: the exclusive prefix sum of n_live)
# holds sample start[r] + i - first[r]; slots past the live total repeat sample 0. One thread
# per slot (a binary search for its ray), so every slot is written without a fill beforehand.


@wp.kernel(enable_backward=False)
def sample_points(
    origins: wp.array(dtype=wp.vec3),  # [n_rays]
    directions: wp.array(dtype=wp.vec3),  # [n_rays]
    t_starts: wp.array(dtype=float),  # [n]
    t_ends: wp.array(dtype=float),  # [n]
    ray_indices: wp.array(dtype=wp.int32),  # [n]
    positions: wp.array(dtype=wp.vec3),  # [n] out
):
    i = wp.tid()
    r = ray_indices[i]
    m = 0.5 * (t_starts[i] + t_ends[i])
    positions[i] = origins[r] + directions[r] * m


@wp.kernel(enable_backward=False)
def live_compact(
    packed_info: wp.array2d(dtype=wp.int32),  # [n_rays, 2] the marched samples (start, count)
    live_end: wp.array(dtype=wp.int64),  # [n_rays] inclusive prefix sum of each ray's live count
    n_live: wp.array(dtype=wp.int32),  # [n_rays]
    t_starts: wp.array(dtype=float),  # [n]
    t_ends: wp.array(dtype=float),  # [n]
    ray_indices: wp.array(dtype=wp.int32),  # [n]
    positions: wp.array(dtype=wp.vec3),  # [n], or [0]: no positions and directions gathered
    directions: wp.array(dtype=wp.vec3),  # [n_rays] (or [0])
    src: wp.array(dtype=wp.int64),  # [capacity] out: the sample each slot holds
    kept_starts: wp.array(dtype=float),  # [capacity] out
    kept_ends: wp.array(dtype=float),  # [capacity] out
    kept_rays: wp.array(dtype=wp.int32),  # [capacity] out
    kept_positions: wp.array(dtype=wp.vec3),  # [capacity] out (or [0])
    kept_directions: wp.array(dtype=wp.vec3),  # [capacity] out: each slot's ray's direction
):
    i = wp.tid()
    n_rays = live_end.shape[0]
    s = int(0)
    if n_rays > 0:
        if wp.int64(i) < live_end[n_rays - 1]:
            lo = int(0)  # the first ray whose live samples end past slot i
            hi = n_rays - 1
            while lo < hi:
                mid = (lo + hi) // 2
                if live_end[mid] > wp.int64(i):
                    hi = mid
                else:
                    lo = mid + 1
            first = int(live_end[lo] - wp.int64(n_live[lo]))
            s = int(packed_info[lo, 0]) + i - first
    src[i] = wp.int64(s)
    kept_starts[i] = t_starts[s]
    kept_ends[i] = t_ends[s]
    r = ray_indices[s]
    kept_rays[i] = r
    if kept_positions.shape[0] > 0:
        kept_positions[i] = positions[s]
        kept_directions[i] = directions[r]
