"""The issue-5 cooperative float32 compositing kernels, kept only as the baseline of issue 47's A/B
in ``warpnerf bench composite`` (variant ``composite_packed_v1``): delete once the H200 figures
of docs/design/kernels.md ("Issue 47 item 4") are in.

They store the per-sample transmittance for the backward (4 B written + 4 B read per sample) and
rely on the bridge zeroing the gradient buffers first (16 B written per sample); the kernels of
``composite_tiled.py`` do neither. Semantics and results are the same (tests/test_composite_tiled.py
runs both).
"""

import warp as wp

from .composite import optical_depth, ray_range, store_ray, upstream_scalar

# Cooperative float32 kernels for densities: one block per ray (launch_tiled), lane l of a block
# handles samples base + l, so a block's loads are contiguous (coalesced on a GPU). Transmittance
# prefix sums come from a block-wide scan of tau; the backward walks the ray's live samples in
# chunks from the back, lane l taking sample hi - 1 - l, and forms
#     suffix_i = sum_{j>i, j<m} w_j e_j + T_m e_bg
# with a block scan (a direct sum of the terms behind i, never a total minus a prefix), then
#     dL/dsigma_i = delta_i (T_{i+1} e_i - suffix_i),
# the same quantity as delta_i T_{i+1} (e_i - S_i) above. Semantics (early termination, NaN
# propagation, outputs) are those of composite_fwd / composite_bwd; on the CPU a block has one lane
# and the same code walks the ray one sample at a time.


@wp.func
def block_sum(x: float):
    return wp.tile_extract(wp.tile_sum(wp.tile(x)), 0)


@wp.kernel(enable_backward=False)
def composite_fwd_tiled(
    packed_info: wp.array2d(dtype=wp.int32),  # [n_rays, 2]
    n_dense: int,
    t_starts: wp.array(dtype=float),  # [n]
    t_ends: wp.array(dtype=float),  # [n]
    sigmas: wp.array(dtype=float),  # [n]
    rgbs: wp.array2d(dtype=float),  # [n, 3]
    background: wp.array2d(dtype=float),  # [n_rays or 1, 3]
    t_threshold: float,
    want_weights: int,
    out_rgb: wp.array2d(dtype=float),  # [n_rays, 3]
    out_depth: wp.array(dtype=float),  # [n_rays]
    out_opacity: wp.array(dtype=float),  # [n_rays]
    out_t_final: wp.array(dtype=float),  # [n_rays]
    trans: wp.array(dtype=float),  # [n]
    weights: wp.array(dtype=float),  # [n] or [0]
    n_eff: wp.array(dtype=wp.int32),  # [n_rays]
):
    r, lane = wp.tid()
    bd = wp.block_dim()
    start, count = ray_range(r, n_dense, packed_info)
    acc = float(0.0)  # optical depth of the live samples so far (same value in every lane)
    c0 = float(0.0)
    c1 = float(0.0)
    c2 = float(0.0)
    depth = float(0.0)
    op = float(0.0)
    live_count = int(0)
    n_chunks = (count + bd - 1) // bd
    for q in range(n_chunks):
        k = q * bd + lane
        i = start + k
        tau = float(0.0)
        alpha = float(0.0)
        if k < count:
            tau, alpha, keep = optical_depth(0, sigmas[i], t_ends[i] - t_starts[i])
        # An exclusive scan sums each lane's predecessors: exact, whereas inclusive - tau loses
        # the small sum in front of a huge tau (and gives inf - inf).
        excl = wp.untile(wp.tile_scan_exclusive(wp.tile(tau)))
        t = wp.exp(-(acc + excl))
        live_tau = float(0.0)
        if k < count:
            if t < t_threshold:
                if want_weights != 0:
                    weights[i] = 0.0
            else:
                w = t * alpha
                trans[i] = t
                if want_weights != 0:
                    weights[i] = w
                c0 += w * rgbs[i, 0]
                c1 += w * rgbs[i, 1]
                c2 += w * rgbs[i, 2]
                depth += w * 0.5 * (t_starts[i] + t_ends[i])
                op += w
                live_count += 1
                live_tau = tau
        acc += block_sum(live_tau)
        if wp.exp(-acc) < t_threshold:
            # every later sample is dead: zero its weight (uniform exit for the whole block)
            if want_weights != 0:
                for kk in range((q + 1) * bd + lane, count, bd):
                    weights[start + kk] = 0.0
            break
    c0 = block_sum(c0)
    c1 = block_sum(c1)
    c2 = block_sum(c2)
    depth = block_sum(depth)
    op = block_sum(op)
    m = wp.tile_extract(wp.tile_sum(wp.tile(live_count)), 0)
    if lane == 0:
        store_ray(
            r,
            c0,
            c1,
            c2,
            depth,
            op,
            wp.exp(-acc),
            m,
            background,
            out_rgb,
            out_depth,
            out_opacity,
            out_t_final,
            n_eff,
        )


@wp.kernel(enable_backward=False)
def composite_bwd_tiled(
    packed_info: wp.array2d(dtype=wp.int32),  # [n_rays, 2]
    n_dense: int,
    t_starts: wp.array(dtype=float),  # [n]
    t_ends: wp.array(dtype=float),  # [n]
    sigmas: wp.array(dtype=float),  # [n]
    rgbs: wp.array2d(dtype=float),  # [n, 3]
    background: wp.array2d(dtype=float),  # [n_rays or 1, 3]
    trans: wp.array(dtype=float),  # [n]
    n_eff: wp.array(dtype=wp.int32),  # [n_rays]
    t_final: wp.array(dtype=float),  # [n_rays]
    v_rgb: wp.array2d(dtype=float),  # [n_rays, 3]
    v_depth: wp.array(dtype=float),  # [n_rays]
    v_opacity: wp.array(dtype=float),  # [n_rays]
    v_weights: wp.array(dtype=float),  # [n] or [0]
    v_sigmas: wp.array(dtype=float),  # [n] out
    v_rgbs: wp.array2d(dtype=float),  # [n, 3] out
):
    r, lane = wp.tid()
    bd = wp.block_dim()
    start, count = ray_range(r, n_dense, packed_info)
    m = int(n_eff[r])
    for k in range(m + lane, count, bd):
        v_sigmas[start + k] = 0.0
        v_rgbs[start + k, 0] = 0.0
        v_rgbs[start + k, 1] = 0.0
        v_rgbs[start + k, 2] = 0.0
    b = 0
    if background.shape[0] > 1:
        b = r
    g0 = v_rgb[r, 0]
    g1 = v_rgb[r, 1]
    g2 = v_rgb[r, 2]
    gd = v_depth[r]
    ga = v_opacity[r]
    carry = t_final[r] * (g0 * background[b, 0] + g1 * background[b, 1] + g2 * background[b, 2])
    n_chunks = (m + bd - 1) // bd
    for q in range(n_chunks):
        k = m - 1 - q * bd - lane
        i = start + k
        term = float(0.0)
        e = float(0.0)
        w = float(0.0)
        tk = float(0.0)  # T_{i+1}
        delta = float(0.0)
        if k >= 0:
            delta = t_ends[i] - t_starts[i]
            tau, alpha, keep = optical_depth(0, sigmas[i], delta)
            t = trans[i]
            w = t * alpha
            tk = t * keep
            e = upstream_scalar(g0, g1, g2, gd, ga, rgbs, t_starts, t_ends, v_weights, i)
            term = w * e
        # Terms are bounded by |e| (w <= 1), so inclusive - term has only rounding-level error.
        behind = wp.untile(wp.tile_scan_inclusive(wp.tile(term))) - term
        if k >= 0:
            v_sigmas[i] = delta * (tk * e - (carry + behind))
            v_rgbs[i, 0] = w * g0
            v_rgbs[i, 1] = w * g1
            v_rgbs[i, 2] = w * g2
        carry += block_sum(term)
