"""Multiresolution hash-grid encoding (instant-ngp's, Mueller et al. 2022), forward and backward.

Level ``l`` is a grid of ``res[l]`` cells per side over the unit cube, i.e. ``(res + 1)^3``
vertices, each holding ``F`` features in rows ``offsets[l] .. offsets[l] + sizes[l]`` of one
table ``[total_rows, F]``. A vertex (i, j, k) maps to its row densely, ``i + (res+1)(j +
(res+1) k)``, when the level fits (``(res+1)^3 <= sizes[l]``), otherwise by the spatial hash
``(i * 1 ^ j * 2654435761 ^ k * 805459861) mod sizes[l]`` in uint32 arithmetic (hashed levels
have power-of-two sizes, so the modulo is a mask).

Forward, for a point x in [0, 1]^3 (clamped) and level l: ``p = x * res``, corner ``c = floor(p)``
(clamped to ``res - 1`` so x = 1 uses the last cell), fraction ``f = p - c``;
``out[n, l*F + q] = sum_{corner v} w_v(f) table[row(v), q]`` with trilinear weights
``w_v = prod_axis (f if v_axis else 1 - f)``.

Backward (hand-written; the table is the only input with a gradient): the forward is linear in
the table, so ``v_table[row(v), q] += w_v * v_out[n, l*F + q]`` for every point and corner,
scattered with atomic adds (on CUDA the summation order, hence the last bits, vary run to run).
Positions, when asked for (pose refinement: the samples' positions depend on the cameras), get
theirs from ``hash_encode_bwd_x``: ``v_x[n, a] = sum_l sum_v sum_q v_out[n, l*F + q]
table[row(v), q] * dw_v/dx_a`` with ``dw_v/dx_a = res_l * (+-1 for the corner's side on axis
a) * (the other two axes' weight factors)``, the derivative inside the cell the forward used
(one-sided on cell faces, as the twin's autograd gives), zero along an axis where x was clamped
(outside [0, 1]) and zero for non-finite points. One thread per point walks the levels, so
there are no atomics and the sum's order is fixed.

One thread per (point, level); threads of one point are adjacent, so its output row is written
by neighbouring threads.
"""

from typing import Any

import warp as wp

PRIME_Y = wp.constant(wp.uint32(2654435761))
PRIME_Z = wp.constant(wp.uint32(805459861))


@wp.struct
class Levels:
    """The grid's L levels, each array [L] int32: cells per side, first row of the level in the
    table, its rows, and 1 where it is indexed densely ((res + 1)^3 <= rows: decided on the host,
    where (res + 1)^3 cannot overflow int32)."""

    res: wp.array(dtype=wp.int32)
    offsets: wp.array(dtype=wp.int32)
    sizes: wp.array(dtype=wp.int32)
    dense: wp.array(dtype=wp.int32)


@wp.func
def level(levels: Levels, lvl: int):
    """(cells per side, first row, rows, dense) of level lvl."""
    return (int(levels.res[lvl]), int(levels.offsets[lvl]), int(levels.sizes[lvl]),
            int(levels.dense[lvl]))  # fmt: skip


@wp.func
def vertex_row(ix: int, iy: int, iz: int, res: int, size: int, dense: int):
    if dense != 0:
        return ix + (res + 1) * (iy + (res + 1) * iz)
    h = wp.uint32(ix) ^ (wp.uint32(iy) * PRIME_Y) ^ (wp.uint32(iz) * PRIME_Z)
    return int(h & wp.uint32(size - 1))


@wp.func
def finite3(x: wp.array2d(dtype=Any), i: int):
    return wp.isfinite(x[i, 0]) and wp.isfinite(x[i, 1]) and wp.isfinite(x[i, 2])


@wp.func
def cell_coord(x: Any, res: int):
    """Clamped corner index and fraction of coordinate x in [0, 1] on a grid of res cells."""
    xc = wp.clamp(x, x.dtype(0.0), x.dtype(1.0))
    p = xc * x.dtype(res)
    c = wp.min(int(wp.floor(p)), res - 1)
    return c, p - x.dtype(c)


@wp.func
def cell(x: wp.array2d(dtype=Any), i: int, res: int):
    """(cx, cy, cz, fx, fy, fz): corner and fractions of point i's cell on a grid of res cells."""
    cx, fx = cell_coord(x[i, 0], res)
    cy, fy = cell_coord(x[i, 1], res)
    cz, fz = cell_coord(x[i, 2], res)
    return cx, cy, cz, fx, fy, fz


@wp.func
def corner(
    v: int, cx: int, cy: int, cz: int, fx: Any, fy: Any, fz: Any, r: int, size: int, dense: int
):
    """Table row (within the level) and trilinear weight of cell corner v (bits: x, y, z)."""
    bx = v & 1
    by = (v >> 1) & 1
    bz = (v >> 2) & 1
    one = fx.dtype(1.0)
    w = wp.where(bx == 1, fx, one - fx)
    w = w * wp.where(by == 1, fy, one - fy)
    w = w * wp.where(bz == 1, fz, one - fz)
    return vertex_row(cx + bx, cy + by, cz + bz, r, size, dense), w


@wp.kernel(enable_backward=False)
def hash_encode_fwd(
    x: wp.array2d(dtype=Any),  # [n, 3] in [0, 1]
    table: wp.array2d(dtype=Any),  # [total_rows, F]
    levels: Levels,
    col0: int,  # 0, or 3: the first three columns are 2 x - 1 (the level-0 thread writes them)
    out: wp.array2d(dtype=Any),  # [n, col0 + L * F]
):
    tid = wp.tid()
    i = tid // levels.res.shape[0]
    lvl = tid - i * levels.res.shape[0]
    r, off, size, dense = level(levels, lvl)
    n_feat = table.shape[1]
    if col0 == 3 and lvl == 0:  # (NaN/Inf positions: NaN or Inf there too)
        for k in range(3):
            out[i, k] = x.dtype(2.0) * x[i, k] - x.dtype(1.0)
    base = col0 + lvl * n_feat
    if not finite3(x, i):
        # NaN/Inf positions give NaN features (never a plausible value, never an index)
        for q in range(n_feat):
            out[i, base + q] = x.dtype(wp.nan)
        return
    cx, cy, cz, fx, fy, fz = cell(x, i, r)
    for q in range(n_feat):  # accumulate in a register, write each feature once
        acc = x.dtype(0.0)
        for v in range(8):
            row, w = corner(v, cx, cy, cz, fx, fy, fz, r, size, dense)
            acc = acc + w * table[off + row, q]
        out[i, base + q] = acc


# sm_90 adds two float32 values to adjacent, 8-byte aligned addresses in one atomic (CUDA's
# float2 atomicAdd): half the atomics of the table's backward, whose throughput bounds it. Other
# devices and the CPU add the two values one by one (the same sums).
_ADD2 = """
#if defined(__CUDA_ARCH__) && (__CUDA_ARCH__ >= 900)
    atomicAdd(reinterpret_cast<float2*>(&wp::index(v_table, row, q)), make_float2(a, b));
#else
    wp::atomic_add(&wp::index(v_table, row, q), a);
    wp::atomic_add(&wp::index(v_table, row, q + 1), b);
#endif
"""


@wp.func_native(_ADD2)
def atomic_add_pair(
    v_table: wp.array2d(dtype=wp.float32), row: int, q: int, a: float, b: float
): ...


@wp.func
def atomic_add_pair(  # noqa: F811  (Warp overloads a function by its argument types)
    v_table: wp.array2d(dtype=wp.float64), row: int, q: int, a: wp.float64, b: wp.float64
):
    """float64 tables: the two values one by one."""
    wp.atomic_add(v_table, row, q, a)
    wp.atomic_add(v_table, row, q + 1, b)


@wp.func
def add_corner(
    v_table: wp.array2d(dtype=Any),
    row: int,
    v_out: wp.array2d(dtype=Any),
    i: int,
    col: int,
    w: Any,
    pairs: int,
):
    """One corner's share of the table gradient, ``v_table[row, q] += w * v_out[i, col + q]``
    for every feature q (zero gradients skipped): one atomic per feature, or with ``pairs`` (an
    even number of features: rows of 8-byte aligned pairs) one per pair of features."""
    zero = w.dtype(0.0)
    if pairs != 0:
        for p in range(v_table.shape[1] // 2):
            q = 2 * p
            g0 = v_out[i, col + q]
            g1 = v_out[i, col + q + 1]
            if g0 != zero or g1 != zero:
                atomic_add_pair(v_table, row, q, w * g0, w * g1)
    else:
        for q in range(v_table.shape[1]):
            g = v_out[i, col + q]
            if g != zero:
                wp.atomic_add(v_table, row, q, w * g)


@wp.kernel(enable_backward=False)
def hash_encode_bwd(
    x: wp.array2d(dtype=Any),  # [n, 3]
    v_out: wp.array2d(dtype=Any),  # [n, col0 + L * F]
    levels: Levels,
    col0: int,  # the features' first column in v_out (3 after the centred positions)
    pairs: int,  # float32 tables of an even F: two features per atomic (add_corner)
    v_table: wp.array2d(dtype=Any),  # [total_rows, F] accumulated (zeroed by the caller)
):
    tid = wp.tid()
    i = tid // levels.res.shape[0]
    lvl = tid - i * levels.res.shape[0]
    if not finite3(x, i):
        return
    r, off, size, dense = level(levels, lvl)
    cx, cy, cz, fx, fy, fz = cell(x, i, r)
    col = col0 + lvl * v_table.shape[1]
    for v in range(8):
        row, w = corner(v, cx, cy, cz, fx, fy, fz, r, size, dense)
        add_corner(v_table, off + row, v_out, i, col, w, pairs)


@wp.func
def axis_factor(b: int, f: Any):
    """(weight factor, its derivative in f) of one axis for corner bit b."""
    one = f.dtype(1.0)
    return wp.where(b == 1, f, one - f), wp.where(b == 1, one, -one)


@wp.func
def inside01(x: Any):
    """1 where x is in [0, 1] (the clamp passes the gradient), else 0."""
    return wp.where(x >= x.dtype(0.0) and x <= x.dtype(1.0), x.dtype(1.0), x.dtype(0.0))


@wp.kernel(enable_backward=False)
def hash_encode_bwd_x(
    x: wp.array2d(dtype=Any),  # [n, 3]
    table: wp.array2d(dtype=Any),  # [total_rows, F]
    v_out: wp.array2d(dtype=Any),  # [n, col0 + L * F]
    levels: Levels,
    col0: int,  # 0, or 3: the centred positions 2 x - 1 (gradient 2) before the features
    v_x: wp.array2d(dtype=Any),  # [n, 3] written
):
    i = wp.tid()
    zero = x.dtype(0.0)
    if not finite3(x, i):  # (no feature gradient; the centred columns' 2 v_out stays)
        for k in range(3):
            v_x[i, k] = zero
            if col0 == 3:
                v_x[i, k] = x.dtype(2.0) * v_out[i, k]
        return
    n_feat = table.shape[1]
    gx = zero
    gy = zero
    gz = zero
    for lvl in range(levels.res.shape[0]):
        r, off, size, dense = level(levels, lvl)
        cx, cy, cz, fx, fy, fz = cell(x, i, r)
        lx = zero
        ly = zero
        lz = zero
        for v in range(8):
            bx = v & 1
            by = (v >> 1) & 1
            bz = (v >> 2) & 1
            wx, dx = axis_factor(bx, fx)
            wy, dy = axis_factor(by, fy)
            wz, dz = axis_factor(bz, fz)
            row = vertex_row(cx + bx, cy + by, cz + bz, r, size, dense)
            s = zero  # d loss / d (this corner's weight)
            for q in range(n_feat):
                s = s + v_out[i, col0 + lvl * n_feat + q] * table[off + row, q]
            lx = lx + s * dx * wy * wz
            ly = ly + s * wx * dy * wz
            lz = lz + s * wx * wy * dz
        rr = x.dtype(r)
        gx = gx + lx * rr
        gy = gy + ly * rr
        gz = gz + lz * rr
    cx2 = zero  # the centred columns' gradient, 2 v_out (no clamp: 2 x - 1 of x as given)
    cy2 = zero
    cz2 = zero
    if col0 == 3:
        cx2 = x.dtype(2.0) * v_out[i, 0]
        cy2 = x.dtype(2.0) * v_out[i, 1]
        cz2 = x.dtype(2.0) * v_out[i, 2]
    v_x[i, 0] = gx * inside01(x[i, 0]) + cx2
    v_x[i, 1] = gy * inside01(x[i, 1]) + cy2
    v_x[i, 2] = gz * inside01(x[i, 2]) + cz2


def _overloads(dtype):
    a2 = wp.array2d(dtype=dtype)
    wp.overload(hash_encode_fwd, [a2, a2, Levels, int, a2])
    wp.overload(hash_encode_bwd, [a2, a2, Levels, int, int, a2])
    wp.overload(hash_encode_bwd_x, [a2, a2, a2, Levels, int, a2])


for _dt in (wp.float32, wp.float64):
    _overloads(_dt)
