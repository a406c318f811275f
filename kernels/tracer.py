"""The rendering tracer (instant-ngp's ``trace``): rays marched and composited in rounds over a
compacted list of live rays, with fixed sample slots per live ray (pure Warp, float32, no
gradients).

State per ray (allocated once per call): ``k`` the next lattice index (the occupancy marchers'
lattice, -1: the ray has no sample left), ``log_t`` the log transmittance, the accumulated
``rgb`` and ``depth``. A live list holds the ray ids still marching; its count lives in a device
counter, so kernels launched over an upper bound read it there.

One round, live ray at list position i marching ``n_steps`` samples:

    trace_march      slots [i * n_steps, i * n_steps + n_i): the ray's next n_i <= n_steps
                     occupied lattice intervals (``march_next``: the marchers' own rule), their
                     midpoint positions, directions, t_starts, t_ends; unused slots hold the ray's
                     origin and a zero interval. Then k is advanced to the ray's next occupied
                     interval (-1 when there is none), so a ray that is done leaves the list now.
    (the field)      densities (and colours) of all slots of the round, in torch
    trace_composite  each live ray's samples in order onto its state (the compositing kernels'
                     rule: T_i = exp(log_t), stop at the first sample with T_i < t_threshold,
                     w_i = T_i (1 - exp(-sigma_i delta_i)), log_t -= sigma_i delta_i), then the
                     ray joins the next live list (an atomic add on its counter) while k >= 0 and
                     T >= t_threshold. Without colours it stores the weights instead and lists the
                     slots whose weight reaches ``color_eps`` (another counter): only those get a
                     colour, added by
    trace_shade      rgb += sum_i w_i c_i over the ray's slots in order (deterministic: no atomics
                     on colours).

``trace_march`` with ``n_steps == 0`` primes a call: k moves to each ray's first occupied interval
and the rays that have one form the first live list.
"""

import warp as wp

from .composite import optical_depth
from .occupancy import march_next, march_next_contracted


@wp.func
def next_interval(
    o: wp.vec3,
    d: wp.vec3,
    t0: float,
    t1: float,
    k: int,
    contracted: int,
    bits: wp.array(dtype=wp.uint8),
    res: int,
    lo: wp.vec3,
    cell_size: wp.vec3,
    dt: float,
    a: float,
    cone: float,
):
    """The ray's first occupied lattice interval at index >= k on a bounded grid (t0: the
    lattice anchor) or a contracted one (t0: the lattice coordinate of near)."""
    if contracted != 0:
        return march_next_contracted(o, d, t0, t1, 0.0, k, bits, res, a, dt, cone)
    inv = wp.vec3(1.0 / cell_size[0], 1.0 / cell_size[1], 1.0 / cell_size[2])
    return march_next(o, d, t0, t1, 0.0, k, bits, res, lo, cell_size, inv, dt)


@wp.kernel(enable_backward=False)
def trace_march(
    live: wp.array(dtype=wp.int32),  # [>= n_live] ray ids of the live rays
    n_live: wp.array(dtype=wp.int32),  # [>= 1] the live count (element 0)
    n_steps: int,  # slots per live ray; 0: prime (see the module's docstring)
    origins: wp.array(dtype=wp.vec3),  # [n_rays]
    directions: wp.array(dtype=wp.vec3),  # [n_rays]
    t_lo: wp.array(dtype=float),  # [n_rays] lattice anchor (contracted: s(near))
    t_hi: wp.array(dtype=float),  # [n_rays] end (bounded: <= t_lo: no samples)
    contracted: int,
    bits: wp.array(dtype=wp.uint8),  # [res^3 / 8]
    res: int,
    lo: wp.vec3,
    cell_size: wp.vec3,
    dt: float,
    a: float,  # contracted: the inner cube's half-size
    cone: float,  # contracted: the step's growth
    k_state: wp.array(dtype=wp.int32),  # [n_rays] in/out: next lattice index, -1 = done
    positions: wp.array(dtype=wp.vec3),  # [n_live * n_steps] out: the samples' midpoints
    dirs: wp.array(dtype=wp.vec3),  # [n_live * n_steps] out: their rays' directions
    t_starts: wp.array(dtype=float),  # [n_live * n_steps] out
    t_ends: wp.array(dtype=float),  # [n_live * n_steps] out
    counts: wp.array(dtype=wp.int32),  # [n_live] out: samples in each live ray's slots
    counters: wp.array(dtype=wp.int32),  # [3] out: (prime: live rays), 2: samples marched
    next_live: wp.array(dtype=wp.int32),  # [n_rays] out (prime): the first live list
):
    i = wp.tid()
    if i >= n_live[0]:
        return
    r = live[i]
    o = origins[r]
    d = directions[r]
    t0 = t_lo[r]
    t1 = t_hi[r]
    k = int(k_state[r])
    if contracted == 0 and not (t1 > t0):
        k = -1
    base = i * n_steps
    n = int(0)
    while k >= 0 and n < n_steps:
        found, s, e = next_interval(o, d, t0, t1, k, contracted, bits, res, lo, cell_size, dt,
                                    a, cone)  # fmt: skip
        if found < 0:
            k = -1
        else:
            positions[base + n] = o + d * (0.5 * (s + e))
            dirs[base + n] = d
            t_starts[base + n] = s
            t_ends[base + n] = e
            n += 1
            k = found + 1
    if k >= 0:  # the next sample's index, or -1: a ray with none left leaves the list now
        found, s, e = next_interval(o, d, t0, t1, k, contracted, bits, res, lo, cell_size, dt,
                                    a, cone)  # fmt: skip
        k = found
    k_state[r] = k
    if n_steps == 0:
        if k >= 0:
            next_live[wp.atomic_add(counters, 0, 1)] = r
        return
    counts[i] = n
    if n > 0:
        wp.atomic_add(counters, 2, n)
    for jj in range(n, n_steps):  # unused slots: finite inputs no ray composites
        positions[base + jj] = o
        dirs[base + jj] = d
        t_starts[base + jj] = 0.0
        t_ends[base + jj] = 0.0


@wp.kernel(enable_backward=False)
def trace_composite(
    live: wp.array(dtype=wp.int32),  # [>= n_live]
    n_live: wp.array(dtype=wp.int32),  # [>= 1] the live count (element 0)
    n_steps: int,
    counts: wp.array(dtype=wp.int32),  # [n_live]
    t_starts: wp.array(dtype=float),  # [n_live * n_steps]
    t_ends: wp.array(dtype=float),  # [n_live * n_steps]
    sigmas: wp.array(dtype=float),  # [n_live * n_steps]
    rgbs: wp.array2d(dtype=float),  # [n_live * n_steps, 3], or [0, 3]: colours come later
    t_threshold: float,
    color_eps: float,
    k_state: wp.array(dtype=wp.int32),  # [n_rays]
    log_t: wp.array(dtype=float),  # [n_rays] in/out
    rgb: wp.array2d(dtype=float),  # [n_rays, 3] in/out
    depth: wp.array(dtype=float),  # [n_rays] in/out
    weights: wp.array(dtype=float),  # [n_live * n_steps] out (no rgbs): w_i, 0 below color_eps
    color_slots: wp.array(dtype=wp.int32),  # [n_live * n_steps] out (no rgbs): slots to colour
    counters: wp.array(dtype=wp.int32),  # [>= 2] out: 0 next live rays, 1 slots to colour
    next_live: wp.array(dtype=wp.int32),  # [n_rays] out: the next live list
):
    i = wp.tid()
    if i >= n_live[0]:
        return
    r = live[i]
    base = i * n_steps
    m = int(counts[i])
    colored = rgbs.shape[0] > 0
    lt = log_t[r]
    c0 = float(0.0)
    c1 = float(0.0)
    c2 = float(0.0)
    dep = float(0.0)
    stop = int(0)
    for j in range(m):
        slot = base + j
        t = wp.exp(lt)
        if stop != 0 or t < t_threshold:
            stop = 1
            if not colored:
                weights[slot] = 0.0
        else:
            tau, alpha, keep = optical_depth(0, sigmas[slot], t_ends[slot] - t_starts[slot])
            w = t * alpha
            if colored:
                c0 += w * rgbs[slot, 0]
                c1 += w * rgbs[slot, 1]
                c2 += w * rgbs[slot, 2]
            elif w >= color_eps or not wp.isfinite(w):  # (a NaN weight is coloured: it
                weights[slot] = w  # reaches the ray's colour on every device, as compositing's)
                color_slots[wp.atomic_add(counters, 1, 1)] = slot
            else:
                weights[slot] = 0.0
            dep += w * 0.5 * (t_starts[slot] + t_ends[slot])
            lt -= tau
    log_t[r] = lt
    depth[r] = depth[r] + dep
    if colored:
        rgb[r, 0] = rgb[r, 0] + c0
        rgb[r, 1] = rgb[r, 1] + c1
        rgb[r, 2] = rgb[r, 2] + c2
    if k_state[r] >= 0 and wp.exp(lt) >= t_threshold:
        next_live[wp.atomic_add(counters, 0, 1)] = r


@wp.kernel(enable_backward=False)
def trace_shade(
    live: wp.array(dtype=wp.int32),  # [>= n_live]
    n_live: wp.array(dtype=wp.int32),  # [>= 1] the live count (element 0)
    n_steps: int,
    counts: wp.array(dtype=wp.int32),  # [n_live]
    weights: wp.array(dtype=float),  # [n_live * n_steps] from trace_composite
    rgbs: wp.array2d(dtype=float),  # [n_live * n_steps, 3] set where weights > 0
    rgb: wp.array2d(dtype=float),  # [n_rays, 3] in/out
):
    i = wp.tid()
    if i >= n_live[0]:
        return
    r = live[i]
    base = i * n_steps
    c0 = float(0.0)
    c1 = float(0.0)
    c2 = float(0.0)
    for j in range(int(counts[i])):
        w = weights[base + j]
        if w > 0.0 or not wp.isfinite(w):
            c0 += w * rgbs[base + j, 0]
            c1 += w * rgbs[base + j, 1]
            c2 += w * rgbs[base + j, 2]
    rgb[r, 0] = rgb[r, 0] + c0
    rgb[r, 1] = rgb[r, 1] + c1
    rgb[r, 2] = rgb[r, 2] + c2
