"""Stratified and hierarchical (importance) sampling along rays (pure Warp).

Stratified (``stratified_fwd``). [near, far] is cut into n equal bins of width D = (far - near) / n.
In evaluation the sample intervals are the bins themselves. In training each interior bin edge is
moved by a uniform offset in [-D/2, D/2) (Warp's counter-based RNG, keyed by seed and ray), so the
intervals still partition [near, far] exactly, stay ordered, and their midpoints (where fields are
evaluated) are jittered. A ray with far <= near (a miss) gets no samples in the packed layout and
zero-length intervals at near in the dense layout.

Importance (``importance_fwd``, coarse-to-fine). A ray's n_c coarse intervals have edges
e_0 = near <= e_1 <= ... <= e_nc = far (they partition [near, far]: t_end_i == t_start_{i+1}) and
weights w_i >= 0 (the coarse pass's compositing weights). With L = far - near, len_i = e_{i+1} - e_i
and eps = PDF_PADDING (1e-5), every interval gets the mass

    m_i = w_i + eps * n_c * len_i / L,        p_i = m_i / M,  M = sum_i m_i,

a piecewise-constant PDF over [near, far] (uniform density inside each interval). The padding is a
constant density, so it adds exactly eps per interval on equal bins (NeRF's ``weights + 1e-5``), it
never leaves a positive-length interval at probability 0, and all-zero weights give p_i = len_i / L:
samples uniform over [near, far] by length, whatever the coarse bins' jitter. Weights are absolute
(compositing weights, sum <= 1): on a nearly transparent ray (sum w ~ eps * n_c) the padding takes
a fair share of the samples, which is what we want where there is nothing to focus on.

n_f new positions by the inverse CDF at sorted u_j: u_j = (j + 1/2) / n_f in evaluation,
u_j = (j + U_j) / n_f in training (U_j uniform in [0, 1) from wp.rand_init(seed, ray); the bridge
salts the seed so that the same seed as ``stratified_fwd`` gives an unrelated stream). With the
running sums C_i = sum_{k<i} m_k and v = u * M, interval i is the last one with C_i <= v
(i <= n_c - 1) and

    t = min(e_i + clamp((v - C_i) / m_i, 0, 1) * len_i, e_{i+1})      (t = e_i when m_i = 0)

so t stays inside its interval and the positions come out sorted. One thread per ray sums M, then
walks the CDF once while merging the n_c + 1 coarse edges with the n_f new positions: the
n_c + n_f + 1 sorted edges give n_c + n_f intervals that partition [near, far] exactly (first start
= near, last end = far, shared edges bit-identical). Positions may repeat (zero-length intervals).
A ray with L = 0 gets n_c + n_f zero-length intervals at near; a packed ray with no coarse interval
gets none. Non-finite weights would poison M; the torch bridge rejects them before launching.
"""

from typing import Any

import warp as wp

from .composite import ray_range


@wp.kernel(enable_backward=False)
def stratified_fwd(
    near: wp.array(dtype=Any),  # [n_rays]
    far: wp.array(dtype=Any),  # [n_rays]
    n_samples: int,
    packed_info: wp.array2d(dtype=wp.int32),  # [n_rays, 2] (start, count); [0, 2] for dense
    perturb: int,
    seed: int,
    ray_offset: int,  # this launch's first ray in a larger batch (the generator's ray key)
    t_starts: wp.array(dtype=Any),  # [n] out
    t_ends: wp.array(dtype=Any),  # [n] out
    ray_indices: wp.array(dtype=wp.int64),  # [n] out, or [0] for dense
):
    r = wp.tid()
    n_dense = n_samples
    if packed_info.shape[0] > 0:
        n_dense = 0
    start, count = ray_range(r, n_dense, packed_info)
    if count == 0:
        return
    lo = near[r]
    hi = wp.max(far[r], lo)
    step = (hi - lo) / near.dtype(float(n_samples))
    half = near.dtype(0.5)
    state = wp.rand_init(seed, r + ray_offset)
    edge = lo
    for k in range(n_samples):
        nxt = hi
        if k < n_samples - 1:
            u = half
            if perturb != 0:
                u = near.dtype(wp.randf(state))
            nxt = lo + (near.dtype(float(k + 1)) + u - half) * step
        i = start + k
        t_starts[i] = edge
        t_ends[i] = nxt
        if ray_indices.shape[0] > 0:
            ray_indices[i] = wp.int64(r)
        edge = nxt


for _dt in (wp.float32, wp.float64):
    _a1 = wp.array(dtype=_dt)
    wp.overload(stratified_fwd, {"near": _a1, "far": _a1, "t_starts": _a1, "t_ends": _a1})


@wp.func
def _interval_mass(w: Any, t0: Any, t1: Any, scale: Any):
    """m_i = w_i + scale * len_i with scale = eps * n_c / L (the padding density)."""
    return w + scale * (t1 - t0)


@wp.func
def _emit(
    out_starts: wp.array(dtype=Any),
    out_ends: wp.array(dtype=Any),
    out_ray_indices: wp.array(dtype=wp.int64),
    o: int,
    a: Any,
    b: Any,
    r: int,
):
    """Writes output interval o = [a, b] of ray r (ray index only in the packed layout)."""
    out_starts[o] = a
    out_ends[o] = b
    if out_ray_indices.shape[0] > 0:
        out_ray_indices[o] = wp.int64(r)


@wp.kernel(enable_backward=False)
def importance_fwd(
    t_starts: wp.array(dtype=Any),  # [n] coarse interval starts
    t_ends: wp.array(dtype=Any),  # [n] coarse interval ends
    weights: wp.array(dtype=Any),  # [n] coarse weights, >= 0 and finite
    n_dense: int,  # coarse intervals per ray in the dense layout, 0 for packed
    packed_info: wp.array2d(dtype=wp.int32),  # [n_rays, 2] coarse (start, count); [0, 2] dense
    n_fine: int,
    pad: Any,  # eps, the padding mass per interval on equal bins
    perturb: int,
    seed: int,
    ray_offset: int,
    out_info: wp.array2d(dtype=wp.int32),  # [n_rays, 2] out (start, count); [0, 2] dense
    out_starts: wp.array(dtype=Any),  # [m] out
    out_ends: wp.array(dtype=Any),  # [m] out
    out_ray_indices: wp.array(dtype=wp.int64),  # [m] out, or [0] for dense
):
    r = wp.tid()
    start, count = ray_range(r, n_dense, packed_info)
    o = r * (n_dense + n_fine)
    if n_dense == 0:
        o = int(out_info[r, 0])
    if count == 0:
        return
    zero = t_starts.dtype(0.0)
    lo = t_starts[start]
    length = t_ends[start + count - 1] - lo
    if length <= zero:  # every edge is at near
        for k in range(count + n_fine):
            _emit(out_starts, out_ends, out_ray_indices, o + k, lo, lo, r)
        return
    scale = pad * t_starts.dtype(float(count)) / length
    total = zero
    for k in range(count):
        i = start + k
        total += _interval_mass(weights[i], t_starts[i], t_ends[i], scale)

    one = t_starts.dtype(1.0)
    half = t_starts.dtype(0.5)
    nf = t_starts.dtype(float(n_fine))
    state = wp.rand_init(seed, r + ray_offset)
    i = int(0)  # current coarse interval (relative to start)
    c = zero  # C_i, the mass before interval i
    m = _interval_mass(weights[start], t_starts[start], t_ends[start], scale)
    nxt = int(1)  # next coarse edge to emit (edge k is t_ends[start + k - 1])
    prev = lo  # last emitted edge
    for j in range(n_fine):
        u = half
        if perturb != 0:
            u = t_starts.dtype(wp.randf(state))
        v = (t_starts.dtype(float(j)) + u) / nf * total
        while i < count - 1 and c + m <= v:
            c += m
            i += 1
            m = _interval_mass(weights[start + i], t_starts[start + i], t_ends[start + i], scale)
        e0 = t_starts[start + i]
        e1 = t_ends[start + i]
        frac = zero
        if m > zero:
            frac = wp.min(wp.max((v - c) / m, zero), one)
        t = wp.min(e0 + frac * (e1 - e0), e1)
        while nxt <= i:  # coarse edges e_1..e_i lie at or before t
            edge = t_ends[start + nxt - 1]
            _emit(out_starts, out_ends, out_ray_indices, o, prev, edge, r)
            o += 1
            prev = edge
            nxt += 1
        _emit(out_starts, out_ends, out_ray_indices, o, prev, t, r)
        o += 1
        prev = t
    while nxt <= count:
        edge = t_ends[start + nxt - 1]
        _emit(out_starts, out_ends, out_ray_indices, o, prev, edge, r)
        o += 1
        prev = edge
        nxt += 1


for _dt in (wp.float32, wp.float64):
    _a1 = wp.array(dtype=_dt)
    wp.overload(
        importance_fwd,
        {
            "t_starts": _a1,
            "t_ends": _a1,
            "weights": _a1,
            "pad": _dt,
            "out_starts": _a1,
            "out_ends": _a1,
        },
    )
