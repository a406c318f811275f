"""Torch bridge for the rendering tracer (kernels/tracer.py): rays marched through an occupancy
grid's bitfield and composited in rounds over a compacted list of live rays, the field evaluated
by callables once per round. No gradients (rendering). The readable twin is
``warpnerf.reference.tracer.trace_rays``."""

from __future__ import annotations

import torch

from . import bridge
from .occupancy import lattice_bounds, lattice_bounds_contracted, march_grid, raise_bad_rays

__all__ = ["trace_rays", "steps_per_round", "COLOR_WEIGHT_EPS", "MIN_STEPS", "MAX_STEPS"]

COLOR_WEIGHT_EPS = 1e-5  # colours of samples weighing less in the image are skipped
# Samples per live ray and round: at least MIN_STEPS (the first rounds', most rays live), at most
# MAX_STEPS (the last rounds', few rays left). instant-ngp's C++ uses 1 and 8; here every round
# costs Python launches and one host sync, so rounds are fewer and larger (a guess made on the
# CPU for correctness only: time them on the GPU, scripts/bench_frame.py --min-steps/--max-steps).
MIN_STEPS = 8
MAX_STEPS = 128


def steps_per_round(n_rays: int, n_alive: int, min_steps: int, max_steps: int) -> int:
    """Slots per live ray in a round (instant-ngp's rule): ``clamp(n_rays // n_alive, min,
    max)``, so a round holds about ``n_rays`` samples however many rays are left."""
    return max(min_steps, min(max_steps, n_rays // max(n_alive, 1)))


def _live_list(ids: torch.Tensor, counters: torch.Tensor):
    """The kernels' ``LiveList`` of ray ids [n_rays] int32 and their counters [3] int32."""
    from warpnerf.kernels import tracer as K

    wp = bridge.load_warp()
    lst = K.LiveList()
    lst.ids, lst.counters = wp.from_torch(ids), wp.from_torch(counters)
    return lst


def trace_rays(
    origins: torch.Tensor,  # [n_rays, 3] float32
    directions: torch.Tensor,  # [n_rays, 3] float32
    near,  # float or [n_rays]
    far,  # float or [n_rays]
    bits: torch.Tensor,  # [res^3 / 8] uint8
    res: int,
    aabb,  # [6] (a contracted grid: the cube [-2a, 2a]^3)
    dt: float,
    density_fn,
    color_fn,
    *,
    contract: float = 0.0,
    cone: float = 0.0,
    color_all: bool = False,
    background=1.0,
    t_threshold: float = 1e-4,
    color_eps: float = COLOR_WEIGHT_EPS,
    min_steps: int = MIN_STEPS,
    max_steps: int = MAX_STEPS,
) -> dict:
    """Renders rays through an occupancy grid in rounds (see kernels/tracer.py).

    The samples are the grid marchers' (:func:`warpnerf.ops.occupancy.march_rays`, or
    ``march_rays_contracted`` with ``contract`` > 0: no jitter); each round marches every live
    ray ``steps_per_round`` more occupied samples into fixed slots, calls ``density_fn(positions
    [m, 3], directions [m, 3]) -> (sigmas [m], ctx)`` once on all of the round's m slots (unused
    ones hold finite positions whose values are ignored), composites each ray's samples in order
    onto its transmittance, colour and depth, stopping at the first sample with T < t_threshold,
    and compacts the rays still live. Colours: ``color_fn(ctx, idx) -> rgbs [c, 3]`` of the
    slots ``idx`` [c] int64, called with ``idx=None`` for all slots before compositing when
    ``color_all``, else after it on the slots whose weight reaches ``color_eps`` only (the
    others count as black: an error below their summed weight).

    Host syncs: one after priming (the live count, and whether a ray was refused), then one per
    round (the next live count, with the number of slots to colour and of samples marched); the
    host needs the counts only to size the field's inputs. Nothing else leaves the device.

    Returns a dict of rgb [n_rays, 3] (``+ T * background``), depth (sum of w t), opacity
    (1 - T) [n_rays] float32, and ``n_marched``, ``n_rounds`` (ints). Raises ValueError as
    :func:`~warpnerf.ops.occupancy.march_rays` for refused rays (non-finite or zero directions,
    NaN near/far, too many lattice steps).
    """
    from warpnerf.kernels import tracer as K

    wp = bridge.load_warp()
    bridge.check_float("origins", origins, (None, 3), torch.float32)
    n_rays, dev = origins.shape[0], origins.device
    bridge.check_float("directions", directions, (n_rays, 3), torch.float32, dev)
    if bits.dtype != torch.uint8 or bits.shape != (res**3 // 8,) or bits.device != dev:
        raise ValueError(f"bits must be a uint8 tensor [{res**3 // 8}] on {dev}")
    min_steps = bridge.check_int("min_steps", min_steps, lo=1)
    max_steps = bridge.check_int("max_steps", max_steps, lo=min_steps)
    if n_rays > bridge.INT32_MAX // max_steps:
        raise ValueError(f"{n_rays} rays x {max_steps} steps exceed int32 slots: trace fewer")
    if isinstance(dt, torch.Tensor) or not (0 < dt < float("inf")):
        raise ValueError(f"need dt > 0 (a finite float), got {dt}")
    box = torch.as_tensor(aabb, dtype=torch.float32).reshape(-1).cpu()
    if contract:
        t_lo, t_hi, bad, near = lattice_bounds_contracted(origins, directions, near, far, dt,
                                                          cone)  # fmt: skip
        far = t_hi
        t_hi = torch.where(bad, torch.zeros_like(t_hi), t_hi)
        t_lo = torch.where(bad, torch.zeros_like(t_lo), t_lo)
    else:
        t_lo, t_hi, bad, near, far = lattice_bounds(origins, directions, near, far, box, dt)
        t_hi = torch.where(bad, t_lo, t_hi)
    f32 = dict(device=dev, dtype=torch.float32)
    i32 = dict(device=dev, dtype=torch.int32)
    # per-ray state, allocated once
    k_state = torch.zeros(n_rays, **i32)
    log_t = torch.zeros(n_rays, **f32)
    rgb = torch.zeros(n_rays, 3, **f32)
    depth = torch.zeros(n_rays, **f32)
    counters = torch.zeros(2, 3, **i32)  # per list: (live rays, slots to colour, samples marched)
    counters[0, 0] = n_rays
    ids = (torch.arange(n_rays, **i32), torch.empty(n_rays, **i32))
    lists = [_live_list(i, c) for i, c in zip(ids, counters)]  # the rounds read one, fill the other
    a = bridge.arr
    grid_args = [a(origins, wp.vec3), a(directions, wp.vec3), a(t_lo.contiguous()),
                 a(t_hi.contiguous()), march_grid(bits, res, box, dt, contract, cone),
                 a(k_state)]  # fmt: skip
    no_f, no_i = torch.empty(0, **f32), torch.empty(0, **i32)
    no_v = a(torch.empty(0, 3, **f32), wp.vec3)
    # priming: every ray moves to its first occupied interval; the first live list
    bridge.launch(K.trace_march, n_rays, [lists[0], 0, *grid_args, no_v, no_v, a(no_f), a(no_f),
                                          a(no_i), lists[1]], dev)  # fmt: skip
    # sync: the live count and whether a ray was refused
    n_alive, refused = torch.cat([counters[1, :1].long(), bad.any().reshape(1).long()]).tolist()
    if refused:
        raise_bad_rays(origins, directions, near, far, dt, contracted=bool(contract))
    cur, n_marched, n_rounds = 1, 0, 0
    bg = torch.as_tensor(background, **f32)
    while n_alive:
        n_steps = steps_per_round(n_rays, n_alive, min_steps, max_steps)
        m = n_alive * n_steps
        nxt = counters[1 - cur]
        nxt.zero_()
        positions = torch.empty(m, 3, **f32)
        dirs = torch.empty(m, 3, **f32)
        t_starts, t_ends = torch.empty(m, **f32), torch.empty(m, **f32)
        counts = torch.empty(n_alive, **i32)
        head = [lists[cur], n_steps]
        bridge.launch(K.trace_march, n_alive, [*head, *grid_args, a(positions, wp.vec3),
                                               a(dirs, wp.vec3), a(t_starts), a(t_ends),
                                               a(counts), lists[1 - cur]], dev)  # fmt: skip
        sigmas, ctx = density_fn(positions, dirs)
        sigmas = sigmas.detach().to(torch.float32).contiguous()
        if color_all:
            rgbs = color_fn(ctx, None).detach().to(torch.float32).contiguous()
            weights, slots = no_f, no_i
        else:
            rgbs = torch.empty(0, 3, **f32)
            weights, slots = torch.empty(m, **f32), torch.empty(m, **i32)
        comp = [*head, a(counts), a(t_starts), a(t_ends), a(sigmas), a(rgbs), float(t_threshold),
                float(color_eps), a(k_state), a(log_t), a(rgb), a(depth), a(weights), a(slots),
                lists[1 - cur]]  # fmt: skip
        bridge.launch(K.trace_composite, n_alive, comp, dev)
        # sync: the next live count, the slots to colour, the samples marched this round
        n_next, n_color, n_round = nxt.tolist()
        n_marched += n_round
        n_rounds += 1
        if n_color:
            idx = slots[:n_color].long()
            slot_rgbs = torch.empty(m, 3, **f32)
            slot_rgbs[idx] = color_fn(ctx, idx).detach().to(torch.float32)
            shade = [*head, a(counts), a(weights), a(slot_rgbs), a(rgb)]
            bridge.launch(K.trace_shade, n_alive, shade, dev)
        n_alive, cur = n_next, 1 - cur
    trans = torch.exp(log_t)
    rgb = rgb + trans.unsqueeze(-1) * (bg.expand(3) if bg.dim() == 0 else bg)
    return {"rgb": rgb, "depth": depth, "opacity": 1.0 - trans, "n_marched": n_marched,
            "n_rounds": n_rounds}  # fmt: skip
