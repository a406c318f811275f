"""Emission-absorption compositing: forward and hand-written backward (pure Warp).

This module: the maths, the helpers every compositing kernel shares and the one-thread-per-ray
kernels (``composite_fwd`` / ``composite_bwd``: float32 and float64, densities or opacities).
``composite_tiled.py``: the cooperative float32 kernels for densities, one block per ray (the
default path). A ray's samples are the contiguous range ``[start, start + count)`` of the flat
sample arrays: ``packed_info[ray] = (start, count)`` in the packed layout, ``start = ray * n_dense,
count = n_dense`` in the dense layout. The backward kernels write the gradient of every sample,
zero included (``zero_uncovered``), so the bridge allocates them without zeroing them first.

Forward (sample i of a ray, delta_i = t_end_i - t_start_i, t_i = (t_start_i + t_end_i) / 2):

    tau_i   = sigma_i * delta_i              (density input)   or  -log(1 - a_i)  (opacity input)
    alpha_i = 1 - exp(-tau_i)                (computed as -expm1(-tau_i))          or  a_i
    T_i     = exp(-sum_{j<i} tau_j)          transmittance, accumulated in log space
    w_i     = T_i * alpha_i
    rgb     = sum_i w_i c_i + T_m * background,  depth = sum_i w_i t_i,  opacity = sum_i w_i

Early termination: a ray stops at the first sample m whose transmittance T_m < t_threshold
(t_threshold = 0 never stops). Samples from m on get weight 0 and gradient 0; the forward stores m
(``n_eff``) and the per-sample transmittance T_i, so the backward sees exactly the same samples
(the tiled kernels store neither per sample: they recompute T_i bit for bit, composite_tiled.py).

Backward. Write every upstream gradient as one scalar per sample,
``e_i = v_rgb . c_i + v_depth * t_i + v_opacity + v_weights_i`` and ``e_bg = v_rgb . background``;
then L = sum_{i<m} w_i e_i + T_m e_bg. With S_i the value seen from just behind sample i,

    S_{m-1} = e_bg,      S_{i-1} = alpha_i e_i + (1 - alpha_i) S_i      (a reverse running sum)

the exact derivatives are

    dL/dalpha_i = T_i (e_i - S_i)
    dL/dsigma_i = delta_i T_{i+1} (e_i - S_i)     (T_{i+1} = T_i exp(-tau_i))
    dL/dc_i     = w_i v_rgb.

This equals the textbook delta_i (T_{i+1} c_i - sum_{j>i} w_j c_j - T_m bg) but never subtracts two
large sums and never divides by 1 - alpha_i, so it stays exact for alpha_i -> 1, sigma * delta up to
1e8 or inf, and 10^4 samples per ray. NaN inputs propagate (no clamping hides them), and so
does an invalid sample: an interval whose length t_end - t_start is not finite and >= 0, a
negative density or an opacity outside [0, 1] gives tau = alpha = NaN (``optical_depth``), so its
ray's outputs and gradients are NaN instead of a plausible-looking value (T_i > 1, negative
weights), at the cost of a few comparisons per sample and no host-side check.
"""

from typing import Any

import warp as wp


@wp.func
def expm1_(x: Any):
    """exp(x) - 1 without cancellation for small |x| (Kahan's trick)."""
    one = type(x)(1.0)
    u = wp.exp(x)
    if u == one:
        return x
    um1 = u - one
    if um1 == -one:
        return -one
    if wp.isinf(u):
        return u
    return um1 * x / wp.log(u)


@wp.func
def log1p_(x: Any):
    """log(1 + x) without cancellation for small |x| (Kahan's trick)."""
    one = type(x)(1.0)
    u = one + x
    if u == one:
        return x
    if u == type(x)(0.0):
        return wp.log(u)
    return wp.log(u) * x / (u - one)


@wp.func
def optical_depth(use_alpha: int, value: Any, delta: Any):
    """Returns (tau, alpha, 1 - alpha) of one sample from its density or its opacity; all three
    NaN for an invalid sample (delta not finite and >= 0, density < 0, opacity outside [0, 1])."""
    one = type(value)(1.0)
    ok = wp.isfinite(delta) and delta >= type(value)(0.0) and value >= type(value)(0.0)
    if use_alpha != 0:
        ok = ok and value <= one
    if not ok:
        nan = type(value)(wp.nan)
        return nan, nan, nan
    if use_alpha != 0:
        return -log1p_(-value), value, one - value
    tau = value * delta
    keep = wp.exp(-tau)
    return tau, -expm1_(-tau), keep


@wp.func
def upstream_value(
    g0: Any,
    g1: Any,
    g2: Any,
    gd: Any,
    ga: Any,
    c0: Any,
    c1: Any,
    c2: Any,
    t_mid: Any,
    v_weights: wp.array(dtype=Any),
    i: int,
):
    """All upstream gradients of sample i (colour c, midpoint t_mid) as one scalar:
    e_i = v_rgb . c_i + v_depth * t_i + v_opacity + v_weights_i (v_weights may be empty)."""
    e = g0 * c0 + g1 * c1 + g2 * c2
    e += gd * t_mid + ga
    if v_weights.shape[0] > 0:
        e += v_weights[i]
    return e


@wp.func
def upstream_scalar(
    g0: Any,
    g1: Any,
    g2: Any,
    gd: Any,
    ga: Any,
    rgbs: wp.array2d(dtype=Any),
    t_starts: wp.array(dtype=Any),
    t_ends: wp.array(dtype=Any),
    v_weights: wp.array(dtype=Any),
    i: int,
):
    """``upstream_value`` of sample i, its colour and midpoint read from the arrays."""
    t_mid = type(gd)(0.5) * (t_starts[i] + t_ends[i])
    c0 = rgbs[i, 0]
    c1 = rgbs[i, 1]
    c2 = rgbs[i, 2]
    return upstream_value(g0, g1, g2, gd, ga, c0, c1, c2, t_mid, v_weights, i)


@wp.func
def store_ray(
    r: int,
    c0: Any,
    c1: Any,
    c2: Any,
    depth: Any,
    opacity: Any,
    t_end: Any,
    m: int,
    background: wp.array2d(dtype=Any),
    out_rgb: wp.array2d(dtype=Any),
    out_depth: wp.array(dtype=Any),
    out_opacity: wp.array(dtype=Any),
    out_t_final: wp.array(dtype=Any),
    n_eff: wp.array(dtype=wp.int32),
):
    """Writes one ray's outputs; the background (shared [1, 3] or per ray) gets weight T_m."""
    b = 0
    if background.shape[0] > 1:
        b = r
    out_rgb[r, 0] = c0 + t_end * background[b, 0]
    out_rgb[r, 1] = c1 + t_end * background[b, 1]
    out_rgb[r, 2] = c2 + t_end * background[b, 2]
    out_depth[r] = depth
    out_opacity[r] = opacity
    out_t_final[r] = t_end
    n_eff[r] = m


@wp.func
def ray_upstream(
    r: int,
    background: wp.array2d(dtype=Any),  # [n_rays or 1, 3]
    v_rgb: wp.array2d(dtype=Any),  # [n_rays, 3]
    v_depth: wp.array(dtype=Any),  # [n_rays]
    v_opacity: wp.array(dtype=Any),  # [n_rays]
):
    """Ray ``r``'s upstream gradients (colour g0..g2, depth, opacity) and the background term
    of the suffix, g . C_bg (its background row: ``r``, or the one shared row)."""
    b = 0
    if background.shape[0] > 1:
        b = r
    g0 = v_rgb[r, 0]
    g1 = v_rgb[r, 1]
    g2 = v_rgb[r, 2]
    s = g0 * background[b, 0] + g1 * background[b, 1] + g2 * background[b, 2]
    return g0, g1, g2, v_depth[r], v_opacity[r], s


@wp.func
def ray_range(r: int, n_dense: int, packed_info: wp.array2d(dtype=wp.int32)):
    if n_dense > 0:
        return r * n_dense, n_dense
    return int(packed_info[r, 0]), int(packed_info[r, 1])


@wp.func
def zero_sample(i: int, v_values: wp.array(dtype=Any), v_rgbs: wp.array2d(dtype=Any)):
    zero = v_values.dtype(0.0)
    v_values[i] = zero
    v_rgbs[i, 0] = zero
    v_rgbs[i, 1] = zero
    v_rgbs[i, 2] = zero


@wp.func
def zero_uncovered(
    r: int,
    lane: int,
    bd: int,
    n_dense: int,
    packed_info: wp.array2d(dtype=wp.int32),
    v_values: wp.array(dtype=Any),
    v_rgbs: wp.array2d(dtype=Any),
):
    """Zero gradients for the samples no ray covers (a fixed-capacity buffer's unused slots), by
    lane ``lane`` of ``bd`` in ray ``r``'s block: the gap before ray 0 (ray 0), the gap between
    ray r and ray r + 1 (ray r), and the slots after the last ray, spread over all blocks.

    Exact for segments in ray order (non-decreasing starts, no overlap), which is what
    ``packed_info_from_ray_indices``, the samplers and the marchers make and what the bridge's
    ``check_packed_info`` enforces; the dense layout covers every sample.
    """
    n_rays = packed_info.shape[0]
    if n_dense > 0 or n_rays == 0:
        return
    start = int(packed_info[r, 0])
    if r == 0:
        for i in range(lane, start, bd):
            zero_sample(i, v_values, v_rgbs)
    if r + 1 < n_rays:
        end = start + int(packed_info[r, 1])
        for i in range(end + lane, int(packed_info[r + 1, 0]), bd):
            zero_sample(i, v_values, v_rgbs)
    tail = int(packed_info[n_rays - 1, 0]) + int(packed_info[n_rays - 1, 1])
    n_tail = v_values.shape[0] - tail
    n_blocks = n_tail // bd
    if n_tail % bd != 0:
        n_blocks += 1
    for blk in range(r, n_blocks, n_rays):
        off = blk * bd + lane
        if off < n_tail:
            zero_sample(tail + off, v_values, v_rgbs)


@wp.kernel(enable_backward=False)
def composite_fwd(
    packed_info: wp.array2d(dtype=wp.int32),  # [n_rays, 2] (start, count); unused when n_dense > 0
    n_dense: int,  # samples per ray in the dense layout, 0 for packed
    t_starts: wp.array(dtype=Any),  # [n]
    t_ends: wp.array(dtype=Any),  # [n]
    values: wp.array(dtype=Any),  # [n] sigmas, or alphas when use_alpha
    use_alpha: int,
    rgbs: wp.array2d(dtype=Any),  # [n, 3]
    background: wp.array2d(dtype=Any),  # [n_rays or 1, 3]
    t_threshold: Any,
    want_weights: int,
    # outputs
    out_rgb: wp.array2d(dtype=Any),  # [n_rays, 3]
    out_depth: wp.array(dtype=Any),  # [n_rays]
    out_opacity: wp.array(dtype=Any),  # [n_rays]
    out_t_final: wp.array(dtype=Any),  # [n_rays] T_m, the background's weight
    trans: wp.array(dtype=Any),  # [n] T_i, 0 after termination
    weights: wp.array(dtype=Any),  # [n] or [0]
    n_eff: wp.array(dtype=wp.int32),  # [n_rays] samples actually composited
):
    r = wp.tid()
    start, count = ray_range(r, n_dense, packed_info)
    zero = t_starts.dtype(0.0)
    half = t_starts.dtype(0.5)
    log_t = zero
    c0 = zero
    c1 = zero
    c2 = zero
    depth = zero
    acc = zero
    m = count
    for k in range(count):
        i = start + k
        t = wp.exp(log_t)
        if t < t_threshold:
            m = k
            break
        tau, alpha, keep = optical_depth(use_alpha, values[i], t_ends[i] - t_starts[i])
        w = t * alpha
        trans[i] = t
        if want_weights != 0:
            weights[i] = w
        c0 += w * rgbs[i, 0]
        c1 += w * rgbs[i, 1]
        c2 += w * rgbs[i, 2]
        depth += w * half * (t_starts[i] + t_ends[i])
        acc += w
        log_t -= tau
    for k in range(m, count):
        trans[start + k] = zero
        if want_weights != 0:
            weights[start + k] = zero
    store_ray(
        r,
        c0,
        c1,
        c2,
        depth,
        acc,
        wp.exp(log_t),
        m,
        background,
        out_rgb,
        out_depth,
        out_opacity,
        out_t_final,
        n_eff,
    )


@wp.kernel(enable_backward=False)
def composite_bwd(
    packed_info: wp.array2d(dtype=wp.int32),  # [n_rays, 2]
    n_dense: int,
    t_starts: wp.array(dtype=Any),  # [n]
    t_ends: wp.array(dtype=Any),  # [n]
    values: wp.array(dtype=Any),  # [n]
    use_alpha: int,
    rgbs: wp.array2d(dtype=Any),  # [n, 3]
    background: wp.array2d(dtype=Any),  # [n_rays or 1, 3]
    trans: wp.array(dtype=Any),  # [n] from the forward
    n_eff: wp.array(dtype=wp.int32),  # [n_rays] from the forward
    v_rgb: wp.array2d(dtype=Any),  # [n_rays, 3]
    v_depth: wp.array(dtype=Any),  # [n_rays]
    v_opacity: wp.array(dtype=Any),  # [n_rays]
    v_weights: wp.array(dtype=Any),  # [n] or [0]
    # outputs
    v_values: wp.array(dtype=Any),  # [n]
    v_rgbs: wp.array2d(dtype=Any),  # [n, 3]
):
    r = wp.tid()
    start, count = ray_range(r, n_dense, packed_info)
    m = int(n_eff[r])
    for k in range(m, count):
        zero_sample(start + k, v_values, v_rgbs)
    zero_uncovered(r, 0, 1, n_dense, packed_info, v_values, v_rgbs)
    g0, g1, g2, gd, ga, s = ray_upstream(r, background, v_rgb, v_depth, v_opacity)
    for kk in range(m):
        i = start + m - 1 - kk
        delta = t_ends[i] - t_starts[i]
        tau, alpha, keep = optical_depth(use_alpha, values[i], delta)
        t = trans[i]
        w = t * alpha
        e = upstream_scalar(g0, g1, g2, gd, ga, rgbs, t_starts, t_ends, v_weights, i)
        diff = e - s
        if use_alpha != 0:
            v_values[i] = t * diff
            if wp.isnan(alpha):  # an invalid opacity: T_i (e_i - S_i) alone would look fine
                v_values[i] = alpha
        else:
            v_values[i] = delta * (t * keep) * diff
        v_rgbs[i, 0] = w * g0
        v_rgbs[i, 1] = w * g1
        v_rgbs[i, 2] = w * g2
        s = alpha * e + keep * s


def _overloads(dtype):
    a1 = wp.array(dtype=dtype)
    a2 = wp.array2d(dtype=dtype)
    common = {"t_starts": a1, "t_ends": a1, "values": a1, "rgbs": a2, "background": a2}
    fwd = dict(common, t_threshold=dtype, out_rgb=a2, out_depth=a1, out_opacity=a1, trans=a1)
    fwd["out_t_final"] = a1
    fwd["weights"] = a1
    bwd = dict(common, trans=a1, v_rgb=a2, v_depth=a1, v_opacity=a1, v_weights=a1)
    bwd.update(v_values=a1, v_rgbs=a2)
    wp.overload(composite_fwd, fwd)
    wp.overload(composite_bwd, bwd)


for _dt in (wp.float32, wp.float64):
    _overloads(_dt)
