"""Stratified sampling between per-ray near and far (pure Warp).

[near, far] is cut into n equal bins of width D = (far - near) / n. In evaluation the sample
intervals are the bins themselves. In training each interior bin edge is moved by a uniform offset
in [-D/2, D/2) (Warp's counter-based RNG, keyed by seed and ray), so the intervals still partition
[near, far] exactly, stay ordered, and their midpoints (where fields are evaluated) are jittered.
A ray with far <= near (a miss) gets no samples in the packed layout and zero-length intervals at
near in the dense layout.
"""

from typing import Any

import warp as wp


@wp.kernel(enable_backward=False)
def stratified_fwd(
    near: wp.array(dtype=Any),  # [n_rays]
    far: wp.array(dtype=Any),  # [n_rays]
    n_samples: int,
    packed_info: wp.array2d(dtype=wp.int32),  # [n_rays, 2] (start, count); [0, 2] for dense
    perturb: int,
    seed: int,
    t_starts: wp.array(dtype=Any),  # [n] out
    t_ends: wp.array(dtype=Any),  # [n] out
    ray_indices: wp.array(dtype=wp.int64),  # [n] out, or [0] for dense
):
    r = wp.tid()
    start = r * n_samples
    count = n_samples
    if packed_info.shape[0] > 0:
        start = int(packed_info[r, 0])
        count = int(packed_info[r, 1])
    if count == 0:
        return
    lo = near[r]
    hi = wp.max(far[r], lo)
    step = (hi - lo) / near.dtype(float(n_samples))
    half = near.dtype(0.5)
    state = wp.rand_init(seed, r)
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
