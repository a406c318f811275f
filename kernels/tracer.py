"""The rendering tracer (instant-ngp's ``trace``): rays marched and composited in rounds over a
compacted list of live rays, with fixed sample slots per live ray (pure Warp, float32, no
gradients).

State per ray (allocated once per call): ``k`` the next lattice index (the occupancy marchers'
lattice, -1: the ray has no sample left), ``log_t`` the log transmittance, the accumulated
``rgb`` and ``depth``. A live list (``LiveList``) holds the ray ids still marching; its count
lives in a device counter, so kernels launched over an upper bound read it there. Two lists take
turns: a round reads the current one and appends the rays that go on to the next.

One round, live ray at list position i marching ``n_steps`` samples:

    trace_march      slots [i * n_steps, i * n_steps + n_i): the ray's next n_i <= n_steps
                     occupied lattice intervals (``next_occupied``: the marcher's own rule), their
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
from .occupancy import MarchGrid, next_occupied


@wp.struct
class LiveList:
    """Ray ids and the device counters of the round that fills them."""

    ids: wp.array(dtype=wp.int32)  # [n_rays] the list: ids[0 .. counters[0])
    counters: wp.array(dtype=wp.int32)  # [3] 0: the list's length, 1: slots to colour, 2: samples


@wp.func
def join(lst: LiveList, r: int):
    """Appends ray r to the list (an atomic add on its length: the order is not fixed)."""
    lst.ids[wp.atomic_add(lst.counters, 0, 1)] = r


@wp.kernel(enable_backward=False)
def trace_march(
    cur: LiveList,  # the live rays
    n_steps: int,  # slots per live ray; 0: prime (see the module's docstring)
    origins: wp.array(dtype=wp.vec3),  # [n_rays]
    directions: wp.array(dtype=wp.vec3),  # [n_rays]
    t_lo: wp.array(dtype=float),  # [n_rays] lattice anchor (contracted: s(near))
    t_hi: wp.array(dtype=float),  # [n_rays] end (bounded: <= t_lo: no samples)
    grid: MarchGrid,
    k_state: wp.array(dtype=wp.int32),  # [n_rays] in/out: next lattice index, -1 = done
    positions: wp.array(dtype=wp.vec3),  # [n_live * n_steps] out: the samples' midpoints
    dirs: wp.array(dtype=wp.vec3),  # [n_live * n_steps] out: their rays' directions
    t_starts: wp.array(dtype=float),  # [n_live * n_steps] out
    t_ends: wp.array(dtype=float),  # [n_live * n_steps] out
    counts: wp.array(dtype=wp.int32),  # [n_live] out: samples in each live ray's slots
    nxt: LiveList,  # out: samples marched (counter 2); prime: the first live list
):
    i = wp.tid()
    if i >= cur.counters[0]:
        return
    r = cur.ids[i]
    o = origins[r]
    d = directions[r]
    t0 = t_lo[r]
    t1 = t_hi[r]
    k = int(k_state[r])
    if grid.contracted == 0 and not (t1 > t0):
        k = -1
    base = i * n_steps
    n = int(0)
    while k >= 0 and n < n_steps:
        found, s, e = next_occupied(grid, o, d, t0, t1, 0.0, k)
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
        found, s, e = next_occupied(grid, o, d, t0, t1, 0.0, k)
        k = found
    k_state[r] = k
    if n_steps == 0:
        if k >= 0:
            join(nxt, r)
        return
    counts[i] = n
    if n > 0:
        wp.atomic_add(nxt.counters, 2, n)
    for jj in range(n, n_steps):  # unused slots: finite inputs no ray composites
        positions[base + jj] = o
        dirs[base + jj] = d
        t_starts[base + jj] = 0.0
        t_ends[base + jj] = 0.0


@wp.kernel(enable_backward=False)
def trace_composite(
    cur: LiveList,
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
    nxt: LiveList,  # out: the next live list, the slots to colour (counter 1)
):
    i = wp.tid()
    if i >= cur.counters[0]:
        return
    r = cur.ids[i]
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
                color_slots[wp.atomic_add(nxt.counters, 1, 1)] = slot
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
        join(nxt, r)


@wp.kernel(enable_backward=False)
def trace_shade(
    cur: LiveList,
    n_steps: int,
    counts: wp.array(dtype=wp.int32),  # [n_live]
    weights: wp.array(dtype=float),  # [n_live * n_steps] from trace_composite
    rgbs: wp.array2d(dtype=float),  # [n_live * n_steps, 3] set where weights > 0
    rgb: wp.array2d(dtype=float),  # [n_rays, 3] in/out
):
    i = wp.tid()
    if i >= cur.counters[0]:
        return
    r = cur.ids[i]
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
