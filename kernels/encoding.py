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
    res: wp.array(dtype=wp.int32),  # [L] cells per side
    offsets: wp.array(dtype=wp.int32),  # [L] first row of each level
    sizes: wp.array(dtype=wp.int32),  # [L] rows of each level
    dense_levels: wp.array(dtype=wp.int32),  # [L] 1: (res + 1)^3 <= rows, indexed densely
    n_levels: int,
    out: wp.array2d(dtype=Any),  # [n, L * F]
):
    tid = wp.tid()
    i = tid // n_levels
    lvl = tid - i * n_levels
    r = int(res[lvl])
    size = int(sizes[lvl])
    off = int(offsets[lvl])
    dense = int(dense_levels[lvl])  # decided on the host: (res + 1)^3 overflows int32
    n_feat = table.shape[1]
    if not finite3(x, i):
        # NaN/Inf positions give NaN features (never a plausible value, never an index)
        for q in range(n_feat):
            out[i, lvl * n_feat + q] = x.dtype(wp.nan)
        return
    cx, fx = cell_coord(x[i, 0], r)
    cy, fy = cell_coord(x[i, 1], r)
    cz, fz = cell_coord(x[i, 2], r)
    for q in range(n_feat):  # accumulate in a register, write each feature once
        acc = x.dtype(0.0)
        for v in range(8):
            row, w = corner(v, cx, cy, cz, fx, fy, fz, r, size, dense)
            acc = acc + w * table[off + row, q]
        out[i, lvl * n_feat + q] = acc


@wp.kernel(enable_backward=False)
def hash_encode_bwd(
    x: wp.array2d(dtype=Any),  # [n, 3]
    v_out: wp.array2d(dtype=Any),  # [n, L * F]
    res: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int32),
    sizes: wp.array(dtype=wp.int32),
    dense_levels: wp.array(dtype=wp.int32),
    n_levels: int,
    v_table: wp.array2d(dtype=Any),  # [total_rows, F] accumulated (zeroed by the caller)
):
    tid = wp.tid()
    i = tid // n_levels
    lvl = tid - i * n_levels
    r = int(res[lvl])
    if not finite3(x, i):
        return
    cx, fx = cell_coord(x[i, 0], r)
    cy, fy = cell_coord(x[i, 1], r)
    cz, fz = cell_coord(x[i, 2], r)
    n_feat = v_table.shape[1]
    for v in range(8):
        row, w = corner(v, cx, cy, cz, fx, fy, fz, r, int(sizes[lvl]), int(dense_levels[lvl]))
        for q in range(n_feat):
            g = v_out[i, lvl * n_feat + q]
            if g != x.dtype(0.0):
                wp.atomic_add(v_table, int(offsets[lvl]) + row, q, w * g)


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
    v_out: wp.array2d(dtype=Any),  # [n, L * F]
    res: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int32),
    sizes: wp.array(dtype=wp.int32),
    dense_levels: wp.array(dtype=wp.int32),
    n_levels: int,
    v_x: wp.array2d(dtype=Any),  # [n, 3] written
):
    i = wp.tid()
    zero = x.dtype(0.0)
    if not finite3(x, i):
        v_x[i, 0] = zero
        v_x[i, 1] = zero
        v_x[i, 2] = zero
        return
    n_feat = table.shape[1]
    gx = zero
    gy = zero
    gz = zero
    for lvl in range(n_levels):
        r = int(res[lvl])
        size = int(sizes[lvl])
        off = int(offsets[lvl])
        dense = int(dense_levels[lvl])
        cx, fx = cell_coord(x[i, 0], r)
        cy, fy = cell_coord(x[i, 1], r)
        cz, fz = cell_coord(x[i, 2], r)
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
                s = s + v_out[i, lvl * n_feat + q] * table[off + row, q]
            lx = lx + s * dx * wy * wz
            ly = ly + s * wx * dy * wz
            lz = lz + s * wx * wy * dz
        rr = x.dtype(r)
        gx = gx + lx * rr
        gy = gy + ly * rr
        gz = gz + lz * rr
    v_x[i, 0] = gx * inside01(x[i, 0])
    v_x[i, 1] = gy * inside01(x[i, 1])
    v_x[i, 2] = gz * inside01(x[i, 2])


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


@wp.kernel(enable_backward=False)
def hash_encode_bwd_pairs(
    x: wp.array2d(dtype=wp.float32),  # [n, 3]
    v_out: wp.array2d(dtype=wp.float32),  # [n, L * F], F even
    res: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int32),
    sizes: wp.array(dtype=wp.int32),
    dense_levels: wp.array(dtype=wp.int32),
    n_levels: int,
    v_table: wp.array2d(dtype=wp.float32),  # [total_rows, F] accumulated (zeroed by the caller)
):
    """``hash_encode_bwd`` for float32 tables with an even number of features (rows of 8-byte
    aligned pairs): each pair of features goes into the table in one atomic on sm_90."""
    tid = wp.tid()
    i = tid // n_levels
    lvl = tid - i * n_levels
    r = int(res[lvl])
    if not finite3(x, i):
        return
    cx, fx = cell_coord(x[i, 0], r)
    cy, fy = cell_coord(x[i, 1], r)
    cz, fz = cell_coord(x[i, 2], r)
    n_feat = v_table.shape[1]
    off = int(offsets[lvl])
    for v in range(8):
        row, w = corner(v, cx, cy, cz, fx, fy, fz, r, int(sizes[lvl]), int(dense_levels[lvl]))
        for p in range(n_feat // 2):
            q = 2 * p
            g0 = v_out[i, lvl * n_feat + q]
            g1 = v_out[i, lvl * n_feat + q + 1]
            if g0 != 0.0 or g1 != 0.0:
                atomic_add_pair(v_table, off + row, q, w * g0, w * g1)


def _overloads(dtype):
    a2 = wp.array2d(dtype=dtype)
    ai = wp.array(dtype=wp.int32)
    wp.overload(hash_encode_fwd, [a2, a2, ai, ai, ai, ai, int, a2])
    wp.overload(hash_encode_bwd, [a2, a2, ai, ai, ai, ai, int, a2])
    wp.overload(hash_encode_bwd_x, [a2, a2, a2, ai, ai, ai, ai, int, a2])


for _dt in (wp.float32, wp.float64):
    _overloads(_dt)
