"""mip-NeRF 360's distortion loss on packed samples: forward and hand-written backward (pure Warp).

One thread per ray walks its samples ``[start, start + count)`` in order. With weights w_i,
interval midpoints m_i and lengths d_i (in whatever normalised ray coordinate s the caller
chose), the loss of a ray is

    L = sum_i sum_j w_i w_j |m_i - m_j|  +  1/3 sum_i w_i^2 d_i

(Barron et al. 2022, eq. 15): it is small when a ray's weight sits in one short stretch, large
when it is spread along the ray (floaters, fog). For samples in increasing order the double sum
is ``2 sum_i w_i (m_i W_i - S_i)`` with the exclusive prefix sums ``W_i = sum_{j<i} w_j`` and
``S_i = sum_{j<i} w_j m_j``, so one pass costs O(n). Its derivative, with ``W``/``S`` the ray's
totals:

    dL/dw_k = 2 (m_k (2 W_k - W) + S - 2 S_k) + 2/3 w_k d_k

(the first term is d/dw_k of the pairs (k, j<k) and (i>k, k) together; the w_k m_k terms of the
suffix sums cancel). Only the weights get a gradient: the sample positions are not learned here.
A NaN or infinite input makes its ray's loss (and gradients) NaN/Inf, never a plausible number.
"""

from __future__ import annotations

from typing import Any

import warp as wp


@wp.func
def interval(s_starts: wp.array(dtype=Any), s_ends: wp.array(dtype=Any), i: int):
    """(midpoint m_i, length d_i) of sample i's interval."""
    return s_starts.dtype(0.5) * (s_starts[i] + s_ends[i]), s_ends[i] - s_starts[i]


@wp.kernel(enable_backward=False)
def distortion_fwd(
    packed_info: wp.array2d(dtype=wp.int32),  # [n_rays, 2] (start, count)
    s_starts: wp.array(dtype=Any),  # [n] interval starts, increasing along each ray
    s_ends: wp.array(dtype=Any),  # [n]
    weights: wp.array(dtype=Any),  # [n]
    out: wp.array(dtype=Any),  # [n_rays] the ray's loss
):
    r = wp.tid()
    start = int(packed_info[r, 0])
    count = int(packed_info[r, 1])
    zero = s_starts.dtype(0.0)
    two = s_starts.dtype(2.0)
    third = s_starts.dtype(1.0) / s_starts.dtype(3.0)  # (a literal 1/3 would be float32's)
    w_sum = zero  # W_i: weights before sample i
    wm_sum = zero  # S_i: weighted midpoints before sample i
    loss = zero
    for k in range(count):
        i = start + k
        w = weights[i]
        m, d = interval(s_starts, s_ends, i)
        loss += two * w * (m * w_sum - wm_sum) + third * w * w * d
        w_sum += w
        wm_sum += w * m
    out[r] = loss


@wp.kernel(enable_backward=False)
def distortion_bwd(
    packed_info: wp.array2d(dtype=wp.int32),  # [n_rays, 2]
    s_starts: wp.array(dtype=Any),  # [n]
    s_ends: wp.array(dtype=Any),  # [n]
    weights: wp.array(dtype=Any),  # [n]
    v_loss: wp.array(dtype=Any),  # [n_rays] upstream gradient
    v_weights: wp.array(dtype=Any),  # [n] output
):
    r = wp.tid()
    start = int(packed_info[r, 0])
    count = int(packed_info[r, 1])
    zero = s_starts.dtype(0.0)
    two = s_starts.dtype(2.0)
    two_thirds = two / s_starts.dtype(3.0)
    w_tot = zero  # the ray's totals W and S first
    wm_tot = zero
    for k in range(count):
        i = start + k
        m, d = interval(s_starts, s_ends, i)
        w_tot += weights[i]
        wm_tot += weights[i] * m
    g = v_loss[r]
    w_sum = zero
    wm_sum = zero
    for k in range(count):
        i = start + k
        w = weights[i]
        m, d = interval(s_starts, s_ends, i)
        dw = two * (m * (two * w_sum - w_tot) + wm_tot - two * wm_sum) + two_thirds * w * d
        v_weights[i] = g * dw
        w_sum += w
        wm_sum += w * m
