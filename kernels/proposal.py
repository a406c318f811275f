"""Proposal sampling (nerfacto, mip-NeRF 360): inverse-CDF resampling of a per-ray histogram and
the interlevel ("proposal") loss, forward and hand-written backward (pure Warp). Dense layouts:
every ray has the same number of bins, edges ``[n_rays, n + 1]`` increasing along each ray, in
the normalised ray coordinate s of the sampler.

Resampling (``resample_fwd``, no gradient). A ray's bins [e_i, e_{i+1}] (i < n) carry weights
w_i >= 0. nerfacto's annealing and padding give each bin the mass

    m_i = w_i^a + pad          (a in [0, 1]: the anneal exponent, 0^0 = 1; pad: 0.01 in nerfacto)

(all-zero masses: one per bin). With C_i = sum_{k<i} m_k and M = C_n, the n_out = n_new + 1 new
edges are the inverse CDF at the sorted u_j = (j + U_j) / n_out: U_j = 1/2 (deterministic
midpoints), one U per ray (nerfacto's single jitter) or one per edge, U in [0, 1). With
v = u M, bin i is the last with C_i <= v (i <= n - 1; bins of zero mass are never chosen while
a later one has mass) and

    s = min(e_i + clamp((v - C_i) / m_i, 0, 1) (e_{i+1} - e_i), e_{i+1})      (e_i when m_i = 0)

so the edges come out sorted inside [e_0, e_n]. One thread per ray sums M, then walks the CDF
once while the u_j increase. A non-finite weight or edge makes the whole ray's new edges NaN.

Interlevel loss (``interlevel_fwd`` / ``interlevel_bwd``, mip-NeRF 360 eq. 13, nerfstudio's
``lossfun_outer``). For each fine interval [t0_i, t1_i] with (detached) weight w_i, the outer
measure of the proposal histogram (edges p_j, weights q_j) over it is the sum of q_j over the
proposal intervals from lo_i = (number of p_j <= t0_i) - 1 to hi_i = number of ends p_{j+1} <=
t1_i (both clamped to [0, n_p - 1]: nerfstudio's two searchsorted calls), and

    L = sum_i max(0, w_i - outer_i)^2 / (w_i + eps),

    dL/dq_j = sum_{i: lo_i <= j <= hi_i} -2 max(0, w_i - outer_i) / (w_i + eps).

lo_i and hi_i never decrease along a ray, so two pointers walk both edge lists once; the outer
measure is summed directly over its (few) intervals rather than as a difference of prefix sums
(no cancellation in float32), which costs O(n_f + n_p) per ray because the fine intervals
partition the ray. The backward recomputes the walk and adds each g_i to its intervals (one
thread owns a ray's row: no atomics). A NaN input makes its ray's loss NaN.
"""

from __future__ import annotations

from typing import Any

import warp as wp


@wp.func
def bin_mass(weights: wp.array2d(dtype=Any), r: int, i: int, a: Any, pad: Any, uniform: int):
    """m_i = w^a + pad (0^0 = 1); 1 when every mass of the ray is zero (``uniform``)."""
    one = weights.dtype(1.0)
    if uniform != 0:
        return one
    w = weights[r, i]
    p = weights.dtype(0.0)
    if w == p:
        if a == p:
            p = one
    else:
        p = wp.pow(w, a)  # (a negative w gives NaN: loud)
    return p + pad


@wp.kernel(enable_backward=False)
def resample_fwd(
    edges: wp.array2d(dtype=Any),  # [n_rays, n + 1] increasing
    weights: wp.array2d(dtype=Any),  # [n_rays, n] >= 0
    anneal: wp.array(dtype=Any),  # [1] the exponent a
    pad: Any,  # added to every bin's mass
    jitter: wp.array2d(dtype=Any),  # [n_rays, 1 | n_out] in [0, 1), or [1, 1] unused (mode 0)
    mode: int,  # 0: midpoints, 1: one U per ray, 2: one U per new edge
    out: wp.array2d(dtype=Any),  # [n_rays, n_out] the new edges
):
    r = wp.tid()
    n = weights.shape[1]
    n_out = out.shape[1]
    zero = weights.dtype(0.0)
    a = anneal[0]
    total = zero
    finite = int(1)
    for i in range(n):
        total += bin_mass(weights, r, i, a, pad, 0)
        if not wp.isfinite(edges[r, i]):
            finite = 0
    if not wp.isfinite(edges[r, n]) or not wp.isfinite(total):
        finite = 0
    if finite == 0:
        for j in range(n_out):
            out[r, j] = zero / zero  # NaN
        return
    uniform = int(0)
    if not total > zero:
        uniform = 1
        total = weights.dtype(float(n))
    i = int(0)
    c = zero  # C_i
    m = bin_mass(weights, r, 0, a, pad, uniform)
    half = weights.dtype(0.5)
    for j in range(n_out):
        u = half
        if mode == 1:
            u = jitter[r, 0]
        elif mode == 2:
            u = jitter[r, j]
        v = (weights.dtype(float(j)) + u) / weights.dtype(float(n_out)) * total
        while i < n - 1 and c + m <= v:
            c += m
            i += 1
            m = bin_mass(weights, r, i, a, pad, uniform)
        e0 = edges[r, i]
        e1 = edges[r, i + 1]
        f = zero
        if m > zero:
            f = wp.clamp((v - c) / m, zero, weights.dtype(1.0))
        out[r, j] = wp.min(e0 + f * (e1 - e0), e1)


@wp.func
def advance(p: wp.array2d(dtype=Any), r: int, k: int, n_p: int, s: Any):
    """The pointer k moved on while the proposal edge p[r, k + 1] <= s (k <= n_p - 1)."""
    while k < n_p - 1 and p[r, k + 1] <= s:
        k += 1
    return k


@wp.func
def outer_measure(w_prop: wp.array2d(dtype=Any), r: int, lo: int, hi: int):
    """The proposal weight of intervals lo..hi (summed directly: no prefix-sum cancellation)."""
    outer = w_prop.dtype(0.0)
    for j in range(lo, hi + 1):
        outer += w_prop[r, j]
    return outer


@wp.kernel(enable_backward=False)
def interlevel_fwd(
    s_fine: wp.array2d(dtype=Any),  # [n_rays, n_f + 1]
    w_fine: wp.array2d(dtype=Any),  # [n_rays, n_f]
    s_prop: wp.array2d(dtype=Any),  # [n_rays, n_p + 1]
    w_prop: wp.array2d(dtype=Any),  # [n_rays, n_p]
    eps: Any,
    out: wp.array(dtype=Any),  # [n_rays]
):
    r = wp.tid()
    n_f = w_fine.shape[1]
    n_p = w_prop.shape[1]
    zero = w_fine.dtype(0.0)
    lo = int(0)
    hi = int(0)
    loss = zero
    for i in range(n_f):
        lo = advance(s_prop, r, lo, n_p, s_fine[r, i])
        hi = advance(s_prop, r, hi, n_p, s_fine[r, i + 1])
        outer = outer_measure(w_prop, r, lo, hi)
        w = w_fine[r, i]
        d = wp.max(w - outer, zero)
        if wp.isnan(w - outer):
            d = w - outer
        loss += d * d / (w + eps)
    out[r] = loss


@wp.kernel(enable_backward=False)
def interlevel_bwd(
    s_fine: wp.array2d(dtype=Any),  # [n_rays, n_f + 1]
    w_fine: wp.array2d(dtype=Any),  # [n_rays, n_f]
    s_prop: wp.array2d(dtype=Any),  # [n_rays, n_p + 1]
    w_prop: wp.array2d(dtype=Any),  # [n_rays, n_p]
    eps: Any,
    v_loss: wp.array(dtype=Any),  # [n_rays] upstream gradient
    v_w_prop: wp.array2d(dtype=Any),  # [n_rays, n_p] output, zeroed by the caller
):
    r = wp.tid()
    n_f = w_fine.shape[1]
    n_p = w_prop.shape[1]
    zero = w_fine.dtype(0.0)
    two = w_fine.dtype(2.0)
    lo = int(0)
    hi = int(0)
    g_ray = v_loss[r]
    for i in range(n_f):
        lo = advance(s_prop, r, lo, n_p, s_fine[r, i])
        hi = advance(s_prop, r, hi, n_p, s_fine[r, i + 1])
        outer = outer_measure(w_prop, r, lo, hi)
        w = w_fine[r, i]
        d = w - outer
        if d > zero or wp.isnan(d):
            g = -two * d / (w + eps) * g_ray
            for j in range(lo, hi + 1):
                v_w_prop[r, j] = v_w_prop[r, j] + g
