"""Cooperative float32 compositing kernels for densities: one block per ray (``launch_tiled``).

The maths, early termination and NaN rules are those of ``composite.py`` (its docstring derives
the backward); this module only changes who computes what, so that a ray moves the fewest bytes.

Layout. A block of ``bd`` lanes walks its ray in chunks of ``SPL * bd`` samples; lane ``l`` holds
samples ``j * bd + l`` of the chunk (``j < SPL``) in the components of a ``wp.vec4``. Every load
instruction of a block reads consecutive samples (coalesced), and a lane issues all its chunk's
loads before the first block-wide operation (indices are clamped into the ray, so the loads are
unconditional), which keeps ``SPL`` times more bytes in flight than one sample per lane. Since
``wp.tile`` of a vector makes a tile of shape ``(SPL, bd)`` and tile scans run over the
flattened row-major order ``j * bd + l``, one scan gives the exclusive prefix of the optical
depths in sample order for the whole chunk.

Forward, chunk by chunk: ``T_i = exp(-(acc + excl_i))`` with ``acc`` the optical depth of the
live samples before the chunk (the same in every lane) and ``excl_i`` the chunk's exclusive scan;
the lane's contributions (tau, w c, w t, w) are summed over the block in one vector reduction.
It writes the ray's outputs, ``t_final = T_m``, ``n_eff`` (the samples it walked: whole chunks
up to the one after which T < t_threshold) and, for each chunk but the first, ``acc`` at the
chunk's first sample (``tau_ckpt[start + q * SPL * bd]``: one float per chunk, none for rays of
at most ``SPL * bd`` samples). Nothing per sample but the optional weights.

Backward, chunk by chunk from the last walked one: the same loads, the same scan from the same
``acc`` (read back from ``tau_ckpt``) give bit-for-bit the forward's ``T_i`` and its live
samples (the rule ``T_i < t_threshold`` is applied again), so no per-sample transmittance is
stored. With ``term_i = w_i e_i`` (e_i: ``upstream_value``) and the suffix

    suffix_i = sum_{j > i, live} term_j + T_m e_bg,  dL/dsigma_i = delta_i (T_{i+1} e_i - suffix_i),

the suffix inside a chunk is an inclusive scan of the chunk in reverse sample order (each lane
takes the vector of lane ``bd - 1 - l`` reversed, via ``tile_extract``), a direct sum of the terms
behind i rather than a total minus a prefix; a carry adds the later chunks. Each walked sample's
gradient is written (zero for samples the rule skips), the rest of the ray's samples get zeros,
and so do samples no ray covers (``zero_uncovered``): the bridge never zero-fills.

Bytes: forward 24 B per sample read (t_starts, t_ends, sigmas, rgbs), backward the same 24 B read
and 16 B written (v_sigmas, v_rgbs): 64 B per sample, the inputs once per pass and the gradients
once. On the CPU (``wp.config.enable_cpu_blocks``) the same code runs the block's lanes in turn.
"""

import warp as wp

from .composite import (
    optical_depth,
    ray_range,
    ray_upstream,
    store_ray,
    upstream_value,
    zero_sample,
    zero_uncovered,
)

SPL = 4  # samples per lane in a chunk: the components of a wp.vec4

vec6 = wp.types.vector(length=6, dtype=float)


@wp.func
def chunk_index(base: int, j: int, lane: int, bd: int, start: int, count: int):
    """(k, i): sample j of ``lane`` in the chunk at ``base``, its index in the ray and its index
    clamped into the ray's range (a valid address to load from when k >= count)."""
    k = base + j * bd + lane
    return k, start + wp.min(k, count - 1)


@wp.func
def load_chunk(
    base: int,
    lane: int,
    bd: int,
    start: int,
    count: int,
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    sigmas: wp.array(dtype=float),
    rgbs: wp.array2d(dtype=float),
):
    """The lane's samples of the chunk at ``base`` as vec4s: (tau (0 past the ray's end), alpha,
    1 - alpha, delta, midpoint, r, g, b). All loads come first, unconditional (clamped indices)
    and before any branch, so the compiler issues them back to back."""
    sig = wp.vec4(0.0)
    t0 = wp.vec4(0.0)
    t1 = wp.vec4(0.0)
    c0 = wp.vec4(0.0)
    c1 = wp.vec4(0.0)
    c2 = wp.vec4(0.0)
    for j in range(SPL):
        k, i = chunk_index(base, j, lane, bd, start, count)
        sig[j] = sigmas[i]
        t0[j] = t_starts[i]
        t1[j] = t_ends[i]
        c0[j] = rgbs[i, 0]
        c1[j] = rgbs[i, 1]
        c2[j] = rgbs[i, 2]
    tau = wp.vec4(0.0)
    alpha = wp.vec4(0.0)
    keep = wp.vec4(0.0)
    for j in range(SPL):
        ta, al, kp = optical_depth(0, sig[j], t1[j] - t0[j])
        if base + j * bd + lane < count:
            tau[j] = ta
        alpha[j] = al
        keep[j] = kp
    return tau, alpha, keep, t1 - t0, 0.5 * (t0 + t1), c0, c1, c2


@wp.func
def chunk_scan(tau: wp.vec4, acc: float):
    """The chunk's transmittances: ``exp(-(acc + exclusive prefix of tau))`` in sample order."""
    excl = wp.untile(wp.tile_scan_exclusive(wp.tile(tau)))
    return wp.vec4(
        wp.exp(-(acc + excl[0])),
        wp.exp(-(acc + excl[1])),
        wp.exp(-(acc + excl[2])),
        wp.exp(-(acc + excl[3])),
    )


@wp.kernel(enable_backward=False)
def composite_fwd_tiled(
    packed_info: wp.array2d(dtype=wp.int32),  # [n_rays, 2]; unused when n_dense > 0
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
    tau_ckpt: wp.array(dtype=float),  # [n] written at each chunk's first sample but the first
    weights: wp.array(dtype=float),  # [n] or [0]
    n_eff: wp.array(dtype=wp.int32),  # [n_rays] samples walked
):
    r, lane = wp.tid()
    bd = wp.block_dim()
    chunk = SPL * bd
    start, count = ray_range(r, n_dense, packed_info)
    # block-wide totals over the live samples: optical depth, rgb, depth, opacity
    tot = vec6(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    walked = count
    n_chunks = (count + chunk - 1) // chunk
    for q in range(n_chunks):
        base = q * chunk
        acc = tot[0]
        if q > 0 and lane == 0:
            tau_ckpt[start + base] = acc
        tau, alpha, keep, delta, mid, c0, c1, c2 = load_chunk(
            base, lane, bd, start, count, t_starts, t_ends, sigmas, rgbs
        )
        t = chunk_scan(tau, acc)
        part = vec6(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        for j in range(SPL):
            k = base + j * bd + lane
            if k < count:
                w = float(0.0)
                if not (t[j] < t_threshold):  # (a NaN transmittance stays live: NaN out)
                    w = t[j] * alpha[j]
                    part += vec6(tau[j], w * c0[j], w * c1[j], w * c2[j], w * mid[j], w)
                if want_weights != 0:
                    weights[start + k] = w
        tot += wp.tile_extract(wp.tile_sum(wp.tile(part, preserve_type=True)), 0)
        if wp.exp(-tot[0]) < t_threshold:
            # every later sample is dead (uniform exit for the whole block)
            walked = wp.min(count, base + chunk)
            if want_weights != 0:
                for kk in range(walked + lane, count, bd):
                    weights[start + kk] = 0.0
            break
    if lane == 0:
        store_ray(
            r,
            tot[1],
            tot[2],
            tot[3],
            tot[4],
            tot[5],
            wp.exp(-tot[0]),
            walked,
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
    t_threshold: float,
    tau_ckpt: wp.array(dtype=float),  # [n] from the forward
    n_eff: wp.array(dtype=wp.int32),  # [n_rays] from the forward
    t_final: wp.array(dtype=float),  # [n_rays] from the forward
    v_rgb: wp.array2d(dtype=float),  # [n_rays, 3]
    v_depth: wp.array(dtype=float),  # [n_rays]
    v_opacity: wp.array(dtype=float),  # [n_rays]
    v_weights: wp.array(dtype=float),  # [n] or [0]
    v_sigmas: wp.array(dtype=float),  # [n] out
    v_rgbs: wp.array2d(dtype=float),  # [n, 3] out
):
    r, lane = wp.tid()
    bd = wp.block_dim()
    chunk = SPL * bd
    start, count = ray_range(r, n_dense, packed_info)
    walked = int(n_eff[r])
    for k in range(walked + lane, count, bd):
        zero_sample(start + k, v_sigmas, v_rgbs)
    zero_uncovered(r, lane, bd, n_dense, packed_info, v_sigmas, v_rgbs)
    g0, g1, g2, gd, ga, s_bg = ray_upstream(r, background, v_rgb, v_depth, v_opacity)
    # the suffix behind the chunk: T_m e_bg, then the terms of the chunks walked so far
    carry = t_final[r] * s_bg
    n_chunks = (walked + chunk - 1) // chunk
    for qq in range(n_chunks):
        base = (n_chunks - 1 - qq) * chunk
        acc = float(0.0)
        if base > 0:
            acc = tau_ckpt[start + base]
        tau, alpha, keep, delta, mid, c0, c1, c2 = load_chunk(
            base, lane, bd, start, count, t_starts, t_ends, sigmas, rgbs
        )
        e = wp.vec4(0.0)
        for j in range(SPL):
            k, i = chunk_index(base, j, lane, bd, start, count)
            e[j] = upstream_value(g0, g1, g2, gd, ga, c0[j], c1[j], c2[j], mid[j], v_weights, i)
        t = chunk_scan(tau, acc)
        w = wp.vec4(0.0)
        term = wp.vec4(0.0)
        live = wp.vec4(0.0)
        for j in range(SPL):
            k = base + j * bd + lane
            if k < count and not (t[j] < t_threshold):
                live[j] = 1.0
                w[j] = t[j] * alpha[j]
                term[j] = w[j] * e[j]
        # Suffix sums in sample order: an inclusive scan of the chunk reversed (lane l takes
        # lane bd-1-l's terms, last first), read back by the mirrored lane. The terms are
        # bounded by |e| (w <= 1), so suffix - term has only rounding-level error, relative to
        # the chunk's suffix (the carry stays out of the scan: adding it in would make that
        # error relative to the whole suffix, twice the worst relative error in NUMERICS.md).
        mirror = wp.tile_extract(wp.tile(term, preserve_type=True), bd - 1 - lane)
        rev = wp.vec4(mirror[3], mirror[2], mirror[1], mirror[0])
        rsuffix = wp.untile(wp.tile_scan_inclusive(wp.tile(rev)))
        suffix = wp.tile_extract(wp.tile(rsuffix, preserve_type=True), bd - 1 - lane)
        for j in range(SPL):
            k = base + j * bd + lane
            if k < count:
                i = start + k
                if live[j] != 0.0:
                    behind = carry + (suffix[SPL - 1 - j] - term[j])
                    v_sigmas[i] = delta[j] * (t[j] * keep[j] * e[j] - behind)
                    v_rgbs[i, 0] = w[j] * g0
                    v_rgbs[i, 1] = w[j] * g1
                    v_rgbs[i, 2] = w[j] * g2
                else:
                    zero_sample(i, v_sigmas, v_rgbs)
        if qq + 1 < n_chunks:  # (none after the ray's first chunk: most rays have one)
            lane_terms = term[0] + term[1] + term[2] + term[3]
            carry += wp.tile_extract(wp.tile_sum(wp.tile(lane_terms)), 0)
