"""Live samples after marching: compaction of the samples a ray still needs (transmittance
above the threshold) and their positions, as Warp kernels (kernels/occupancy.py)."""

from __future__ import annotations

import torch

from . import bridge
from .sampling import Samples


def live_samples_fixed(samples: Samples, sigmas: torch.Tensor, t_threshold: float,
                       capacity: int, positions: torch.Tensor | None = None,
                       directions: torch.Tensor | None = None):  # fmt: skip
    """Static-shape :func:`live_samples` plus compaction, with no host sync (a training step
    captured in a CUDA graph): each ray's samples before its transmittance drops below
    ``t_threshold``, packed into ``capacity`` slots in ray order (rays past a full buffer keep
    fewer, deterministically).

    ``samples`` must be packed by the library's own marcher (``march_rays(capacity=...)``): its
    packed_info is trusted, slots no ray references are ignored. ``positions`` [n, 3] (the
    samples' points) and ``directions`` [n_rays, 3] (the rays'), both float32 or both None:
    gathered into the kept slots by the same kernel. Returns ``(kept, src, stats, kept_positions,
    kept_directions)``: ``kept`` Samples of ``capacity`` slots (unused ones repeat slot 0 of
    ``samples``, referenced by no ray), ``src`` [capacity] int64: the index in ``samples`` of
    each kept slot, ``stats`` int64 [2] on the device: (live samples, samples dropped for want of
    capacity), then the kept slots' positions [capacity, 3] and their rays' directions
    [capacity, 3] (None without ``positions``)."""
    from warpnerf.kernels import occupancy as K

    wp = bridge.load_warp()
    capacity = bridge.check_int("capacity", capacity, lo=1)
    ts, te, info = samples.t_starts, samples.t_ends, samples.packed_info
    bridge.check_float("sigmas", sigmas, (ts.shape[0],), torch.float32, ts.device)
    n, n_rays, dev = ts.shape[0], info.shape[0], ts.device
    if n == 0:
        raise ValueError("live_samples_fixed needs at least one marched slot")
    gather = positions is not None
    if gather:
        bridge.check_float("positions", positions, (n, 3), torch.float32, dev)
        bridge.check_float("directions", directions, (n_rays, 3), torch.float32, dev)
    n_live = torch.empty(n_rays, device=dev, dtype=torch.int32)
    a = bridge.arr
    inputs = [a(info), a(ts), a(te), a(sigmas.detach()), float(t_threshold), a(n_live)]
    bridge.launch(K.live_counts, n_rays, inputs, dev)
    live = n_live.long()
    csum = torch.cumsum(live, 0)
    first = csum - live  # each ray's first kept slot
    kept_n = torch.minimum((capacity - first).clamp_min(0), live)
    src = torch.empty(capacity, device=dev, dtype=torch.int64)
    k_ts, k_te = (torch.empty_like(src, dtype=torch.float32) for _ in range(2))
    k_ri = torch.empty_like(src, dtype=torch.int32)
    k_pos = torch.empty(capacity if gather else 0, 3, device=dev, dtype=torch.float32)
    k_dir = torch.empty_like(k_pos)
    none = torch.empty(0, 3, device=dev, dtype=torch.float32)
    v3 = wp.vec3
    bridge.launch(K.live_compact, capacity, [
        a(info), a(csum), a(n_live), a(ts), a(te), a(samples.ray_indices),
        a(positions if gather else none, v3), a(directions if gather else none, v3),
        a(src), a(k_ts), a(k_te), a(k_ri), a(k_pos, v3), a(k_dir, v3),
    ], dev)  # fmt: skip
    total = csum[-1] if n_rays else torch.zeros((), device=dev, dtype=torch.int64)
    stats = torch.stack([total, (total - capacity).clamp_min(0)])
    packed = torch.stack([first.clamp_max(capacity), kept_n], -1).to(torch.int32)
    kept = Samples(k_ts, k_te, k_ri, packed)
    return kept, src, stats, (k_pos if gather else None), (k_dir if gather else None)


def sample_points(samples: Samples, origins: torch.Tensor, directions: torch.Tensor):
    """Points [n, 3] of packed ``samples`` at their intervals' midpoints, ``o + d (t0 + t1) / 2``
    of each sample's ray (one kernel instead of gathers and elementwise ops). The samples'
    ray indices are trusted (the library's own marcher made them)."""
    from warpnerf.kernels import occupancy as K

    wp = bridge.load_warp()
    bridge.check_float("origins", origins, (None, 3), torch.float32)
    bridge.check_float("directions", directions, (origins.shape[0], 3), torch.float32,
                       origins.device)  # fmt: skip
    ts, te, ri = samples.t_starts, samples.t_ends, samples.ray_indices
    bridge.check_float("samples.t_starts", ts, (None,), torch.float32, origins.device)
    bridge.check_float("samples.t_ends", te, (ts.shape[0],), torch.float32, origins.device)
    bridge.check_index("samples.ray_indices", ri, (ts.shape[0],), origins.device)
    out = torch.empty(ts.shape[0], 3, device=ts.device, dtype=torch.float32)
    a = bridge.arr
    bridge.launch(K.sample_points, ts.shape[0], [
        a(origins, wp.vec3), a(directions, wp.vec3), a(ts), a(te), a(ri.to(torch.int32)),
        a(out, wp.vec3),
    ], ts.device)  # fmt: skip
    return out


def live_samples(samples: Samples, sigmas: torch.Tensor, t_threshold: float, *, check=True):
    """Early termination on densities alone: (keep [n] bool, n_live [n_rays] int32).

    keep marks each ray's samples before the first one with transmittance below ``t_threshold``
    (the rule of the compositing kernels); n_live counts them per ray. ``samples`` is packed
    (as :func:`march_rays` gives); its ``packed_info`` [n_rays, 2] and ``ray_indices`` [n] must
    describe its samples exactly (ValueError otherwise; one pass and one host sync on CUDA, which
    ``check=False`` skips for samples the caller marched itself).
    """
    from warpnerf.kernels import occupancy as K

    from .composite import check_packed_info

    if not isinstance(samples, Samples) or samples.packed_info is None:
        raise ValueError("samples must be packed Samples (with packed_info and ray_indices)")
    ts, te, info = samples.t_starts, samples.t_ends, samples.packed_info
    bridge.check_float("samples.t_starts", ts, (None,), torch.float32)
    n, dev = ts.shape[0], ts.device
    bridge.check_float("samples.t_ends", te, (n,), torch.float32, dev)
    bridge.check_float("sigmas", sigmas, (n,), torch.float32, dev)
    bridge.check_index("samples.packed_info", info, (None, 2), dev)
    bridge.check_index("samples.ray_indices", samples.ray_indices, (n,), dev)
    n_rays = info.shape[0]
    if check:
        check_packed_info(info, samples.ray_indices, n, n_rays)
    info = info.to(torch.int32).contiguous()
    n_live = torch.empty(n_rays, device=dev, dtype=torch.int32)
    a = bridge.arr
    inputs = [a(info), a(ts), a(te), a(sigmas.detach()), float(t_threshold), a(n_live)]
    bridge.launch(K.live_counts, n_rays, inputs, dev)
    ri = samples.ray_indices.long()
    pos = torch.arange(n, device=dev) - info[:, 0].long()[ri]
    return pos < n_live.long()[ri], n_live
