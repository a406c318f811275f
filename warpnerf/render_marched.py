"""Rendering with an occupancy grid (:func:`render_marched`): rays marched through the grid's
occupied cells, the field evaluated on the kept samples in rounds within a sample budget, and the
fixed-shape variant a captured CUDA graph replays (:func:`render_marched_fixed`). Part of the
rendering pipelines of :mod:`warpnerf.render`, which re-exports both."""

from __future__ import annotations

import torch

from .field_protocol import density as field_density
from .field_protocol import needs_directions
from .ops import render_packed
from .ops.bridge import check_int
from .ops.tracer import COLOR_WEIGHT_EPS
from .render_traced import SAMPLE_BUDGET, TRACE_COLORS, render_traced

__all__ = [
    "render_marched", "render_marched_fixed", "weight_before", "weight_median", "SAMPLE_BUDGET",
]  # fmt: skip


TRACERS = ("auto", "traced", "rounds")  # render_marched's rendering paths (without gradients)
COLOR_FILLS = ("black", "mean")  # the rounds path's colour of the samples it does not colour
# The rounds path colours the samples weighing at least this much in the image (or a 100th of
# their ray's heaviest sample, if less), the others taking the coloured ones' mean colour along
# their ray: on an H200 a lego hash_sdf frame 22.1 ms colouring from 1e-3 (the rest black)
# against 27.8 with every sample above 1e-5 coloured (-0.024 dB against the val images; on the
# CPU the mean gives +0.006 dB where black gives -0.015; docs/design/training.md "Issue 47,
# eighth round"). The tracer (render_traced) keeps COLOR_WEIGHT_EPS.
RENDER_COLOR_EPS = 1e-3
COLOR_RELATIVE = 1e-2  # (a ray whose heaviest sample weighs under 0.1 colours from a 100th of it)


def render_marched(
    grid,
    field,
    origins: torch.Tensor,  # [n_rays, 3] float32
    directions: torch.Tensor,  # [n_rays, 3] unit length
    near,  # float or [n_rays]
    far,  # float or [n_rays]
    *,
    perturb: bool = False,
    generator: torch.Generator | None = None,
    background=1.0,
    t_threshold: float = 1e-4,
    max_samples: int = 1024,
    round_samples: int = 0,
    half: bool = False,
    sample_budget: int = SAMPLE_BUDGET,
    jitter: torch.Tensor | None = None,
    ray_images: torch.Tensor | None = None,
    distortion_s=None,
    near_t=None,
    tracer: str = "auto",
    colors: str = "weighted",
    on_weights=None,
    color_eps: float = RENDER_COLOR_EPS,
    color_fill: str = "mean",
):
    """Volume rendering with an occupancy grid: packed marching + early termination.

    ``grid`` (:class:`warpnerf.OccupancyGrid`) emits lattice samples of step ``grid.dt`` in
    occupied cells (the lattice shifted by a random fraction of a step per ray when ``perturb``,
    drawn from ``generator`` on the rays' device, or given as ``jitter`` [n_rays] in [0, 1): a
    data-parallel rank passes its share of the global batch's draws; ``ray_images`` [n_rays]:
    each ray's training image, for a field with appearance codes). ``field`` is a module
    with ``density(positions) -> (sigmas [n], features)`` and ``color(features, directions) ->
    rgbs [n, 3]``. Densities of all marched samples are computed first without gradients; each
    ray keeps its samples before transmittance drops below ``t_threshold`` (the compositing
    kernels' own rule, so forward and backward see the same samples); the field then runs again
    with gradients on the kept samples only.

    Without gradients (rendering), ``tracer`` picks the path: ``"traced"``
    (:func:`warpnerf.render_traced.render_traced`, instant-ngp's tracer: per-ray state on the
    device, a compacted list of live rays, a few samples per live ray and round, compositing
    with early termination, one host sync per round; ``colors`` "weighted" or "all" is its
    colour rule), ``"rounds"`` (the path below), or ``"auto"`` (the default: the rounds path,
    which measured 2x faster than the tracer on an H200: 97 against 197 ms a lego frame in
    8,192-ray chunks, about 100 rounds a frame; 10.2 s against 1.4 s a beer frame;
    docs/design/rendering.md "Issue 47"; ``round_samples`` and ``max_samples`` are the rounds
    path's only). The rounds path: the field's
    density runs once on the marched samples, their
    weights are composited, and the colour MLP runs only on samples whose weight in the image
    reaches ``color_eps`` (default ``RENDER_COLOR_EPS``, 1e-3) or, if less, ``COLOR_RELATIVE``
    (1e-2) of their ray's heaviest sample in the round, and at least ``COLOR_WEIGHT_EPS`` (1e-5;
    ``color_eps`` if smaller, which then is the rule: 1e-5 is the rule before 2026-12-03);
    ``n_colored`` in the result counts them. ``color_fill`` says what the others count as:
    ``"mean"`` (the default: the weighted mean colour of the ray's coloured samples over all
    its rounds, exact where a ray's colour is uniform, an error below the skipped weight times
    the ray's colour spread, e.g. a thin fog before a surface takes the surface's colour; every
    ray weighing 1e-5 colours its heaviest sample) or ``"black"`` (an error below their summed
    weight, always darker; with ``color_eps=COLOR_WEIGHT_EPS`` the rule before 2026-12-03, and
    the tracer's).
    ``round_samples > 0`` marches in rounds of at most that many samples per live ray (more as
    rays finish), compositing each round onto the rays' running colour and transmittance and
    dropping rays once T < t_threshold, so samples behind opaque surfaces are never marched
    (a round is composited whole); 0 marches everything in one round (on the H100 one round
    was faster on lego: every round costs host syncs and launches). ``half`` (rendering on
    CUDA only) runs the field's MLPs under float16 autocast; densities, weights and compositing
    stay float32. ``sample_budget`` bounds the samples the field sees in one call while
    rendering (its activations are most of the memory, whatever the number of rays): a round
    that marched more samples evaluates densities in slices of that size, then recomputes the
    features of the samples whose colour is needed (the default, 2^23 = 8192 rays x 1024
    samples, is never reached by the default rendering chunk).

    Returns a dict of rgb [n_rays, 3], depth, opacity [n_rays], and the sample counts
    ``n_marched`` / ``n_kept`` (ints); with gradients and ``distortion_s`` (a map of ray
    distances t to a normalised coordinate s, increasing) also ``distortion`` [n_rays], each
    ray's distortion loss (:func:`warpnerf.ops.distortion_loss`) of its kept samples' weights;
    with gradients and ``near_t`` (a float or [n_rays]) also ``near_weight`` [n_rays], each
    ray's weight before that distance (:func:`weight_before`, differentiable).

    ``on_weights`` (rendering without gradients; it selects the rounds path): called once per
    round with ``(ray_indices [n], t_starts [n], t_ends [n], weights [n])`` of every sample the
    round composited, ``weights`` being each sample's share of its ray's pixel (its weight
    within the round times the ray's transmittance before the round), so that a ray's weights
    over all rounds sum to its opacity: what a caller measures per sample (where along each
    ray the weight lies) without rendering again.

    The packed samples are the grid's own: they are composited without re-checking their indices
    (``render_packed(check=False)``), so no host sync is added to the marching's own.
    """
    from .ops.occupancy import live_samples
    from .ops.sampling import Samples

    max_samples = check_int("max_samples", max_samples, lo=1)
    round_samples = check_int("round_samples", round_samples)
    sample_budget = check_int("sample_budget", sample_budget, lo=1, hi=2**62)
    if not 0.0 <= float(color_eps) < 1.0:  # (also refuses NaN)
        raise ValueError(f"color_eps must be in [0, 1), got {color_eps!r}")
    if color_fill not in COLOR_FILLS:
        raise ValueError(f"color_fill must be one of {COLOR_FILLS}, got {color_fill!r}")
    if tracer not in TRACERS:
        raise ValueError(f"tracer must be one of {TRACERS}, got {tracer!r}")
    if colors not in TRACE_COLORS:  # (the tracer's option, checked whatever the path)
        raise ValueError(f"colors must be one of {TRACE_COLORS}, got {colors!r}")
    traced = tracer == "traced" and on_weights is None  # ("auto": the rounds path, faster)
    if not torch.is_grad_enabled() and traced:
        return render_traced(grid, field, origins, directions, near, far, background=background,
                             t_threshold=t_threshold, half=half, sample_budget=sample_budget,
                             colors=colors)  # fmt: skip
    if not torch.is_grad_enabled():
        return _render_rounds(
            grid, field, origins, directions, near, far, background, t_threshold,
            round_samples or max_samples, max_samples, half, sample_budget, on_weights,
            float(color_eps), color_fill == "mean",
        )  # fmt: skip
    n_rays, dev = origins.shape[0], origins.device
    if jitter is None and perturb:
        jitter = torch.rand(n_rays, device=dev, generator=generator)
    smp, _ = grid.march(origins, directions, near, far, jitter=jitter, max_samples=max_samples)
    ri = smp.ray_indices
    positions = origins[ri] + directions[ri] * smp.midpoints().unsqueeze(-1)
    with torch.no_grad():
        enc, sigmas = _first_pass(field, positions, lambda: directions[ri])
    keep, n_live = live_samples(smp, sigmas, t_threshold, check=False)
    idx = torch.nonzero(keep).squeeze(1)
    counts = n_live.to(torch.int64)
    info = torch.stack([torch.cumsum(counts, 0) - counts, counts], -1).to(torch.int32)
    kept = Samples(smp.t_starts[idx], smp.t_ends[idx], ri[idx], info)
    sigmas, feats = _second_pass(field, positions[idx], None if enc is None else enc[idx],
                                 lambda: directions[kept.ray_indices])  # fmt: skip
    out = _shade_kept(field, directions, kept, sigmas, feats, background, t_threshold,
                      ray_images, distortion_s, near_t=near_t)  # fmt: skip
    out.update(n_marched=int(smp.t_starts.shape[0]), n_kept=int(idx.shape[0]))
    return out


def _first_pass(field, positions, directions):
    """(encoding or None, sigmas) of a marcher's first, gradient-free pass: a field that can
    hand over its encoding (``encode``) keeps it for the second pass. ``directions``: a callable
    giving the samples' directions, called only for a field whose density needs them."""
    if getattr(field, "encode", None) is None:
        return None, field_density(field, positions, directions)[0]
    enc = field.encode(positions)
    return enc, field_density(field, positions, directions, encoded=enc)[0]


def _second_pass(field, positions, enc, directions):
    """(sigmas, features) of the kept samples, with gradients (the encoding reused)."""
    kw = {} if enc is None else {"encoded": enc}
    return field_density(field, positions, directions, **kw)


def render_marched_fixed(
    grid,
    field,
    origins: torch.Tensor,  # [n_rays, 3] float32
    directions: torch.Tensor,  # [n_rays, 3] unit length
    near,  # float or [n_rays]
    far,  # float or [n_rays] (a ray with far <= near gets no samples: an unused slot)
    *,
    marched: int,
    kept: int,
    jitter: torch.Tensor | None = None,
    background=1.0,
    t_threshold: float = 1e-4,
    max_samples: int = 1024,
    ray_images: torch.Tensor | None = None,
    distortion_s=None,
    near_t=None,
):
    """:func:`render_marched` with static shapes and no host sync, for a training step captured
    in a CUDA graph (:mod:`warpnerf.train.graph_step`): the marched samples fill ``marched``
    slots, the live ones (before each ray's transmittance drops below ``t_threshold``) are
    compacted into ``kept`` slots, and the field runs on all slots of each (unused ones hold
    finite positions no ray composites, so their gradients are zero). Rays past a full buffer
    lose samples, deterministically by ray order (``stats`` counts them; the trainer sizes the
    buffers from the previous steps so that this stays rare). With enough capacity, every ray's
    samples, colour and gradients are :func:`render_marched`'s.

    Returns a dict of rgb [n_rays, 3], depth, opacity [n_rays] (and ``distortion`` [n_rays] with
    ``distortion_s``, ``near_weight`` [n_rays] with ``near_t``) and ``stats``, an int64 device
    tensor [5]: (samples marched, marched samples dropped, rays refused, live samples, live
    samples dropped).
    """
    from .ops.occupancy import live_samples_fixed, sample_points

    smp, _, march_stats = grid.march(origins, directions, near, far, jitter=jitter,
                                     max_samples=max_samples, capacity=marched)  # fmt: skip
    # the samples' points, and the live ones' points and directions, by the kernels (no torch
    # gathers), unless gradients must reach the rays (then torch's differentiable ops)
    rays_grad = origins.requires_grad or directions.requires_grad
    if rays_grad:
        ri = smp.ray_indices
        positions = origins[ri] + directions[ri] * smp.midpoints().unsqueeze(-1)
    else:
        positions = sample_points(smp, origins, directions)
    with torch.no_grad():
        enc, sigmas = _first_pass(field, positions, lambda: directions[smp.ray_indices])
    gather = {} if rays_grad else {"positions": positions, "directions": directions}
    live, src, live_stats, live_pos, dirs = live_samples_fixed(smp, sigmas.float(), t_threshold,
                                                               kept, **gather)  # fmt: skip
    if rays_grad:
        live_pos = positions[src]
    live_dirs = (lambda: directions[live.ray_indices]) if dirs is None else dirs
    sigmas, feats = _second_pass(field, live_pos, None if enc is None else enc[src], live_dirs)
    color_kw = None
    if getattr(field, "kind", "density") == "sdf":  # its eikonal term: the live slots only
        n_live = live_stats[0].clamp_max(kept)
        color_kw = {"valid": torch.arange(kept, device=directions.device) < n_live}
    out = _shade_kept(field, directions, live, sigmas, feats, background, t_threshold,
                      ray_images, distortion_s, color_kw, dirs, near_t)  # fmt: skip
    out["stats"] = torch.cat([march_stats, live_stats])
    return out


def _shade_kept(field, directions, kept, sigmas, feats, background, t_threshold, ray_images,
                distortion_s, color_kw=None, dirs=None, near_t=None) -> dict:  # fmt: skip
    """The marchers' last part: colours of the kept samples (with their densities and
    features from the field's second pass), compositing, and each ray's distortion loss when
    ``distortion_s`` is given, its weight before ``near_t`` when that is given. ``color_kw``:
    more keywords for the field's ``color``; ``dirs``: the kept samples' directions when
    already gathered."""
    if dirs is None:
        dirs = directions[kept.ray_indices]
    kw = dict(color_kw or {})
    if ray_images is not None:
        kw["image_ids"] = ray_images[kept.ray_indices]
    rgbs = field.color(feats, dirs, **kw)
    rgb, depth, opacity, *weights = render_packed(
        kept.t_starts, kept.t_ends, kept.ray_indices, sigmas, rgbs, directions.shape[0],
        background=background, packed_info=kept.packed_info, t_threshold=t_threshold,
        check=False, return_weights=distortion_s is not None or near_t is not None,
    )  # fmt: skip
    out = {"rgb": rgb, "depth": depth, "opacity": opacity}
    if near_t is not None:
        out["near_weight"] = weight_before(kept.t_starts, kept.t_ends, kept.ray_indices,
                                           weights[0], kept.packed_info, near_t)  # fmt: skip
    if distortion_s is not None:
        from .ops.distortion import distortion_loss

        out["distortion"] = distortion_loss(
            distortion_s(kept.t_starts), distortion_s(kept.t_ends), kept.ray_indices, weights[0],
            directions.shape[0], packed_info=kept.packed_info, check=False,
        )  # fmt: skip
    return out


def weight_before(
    t_starts: torch.Tensor,  # [n]
    t_ends: torch.Tensor,  # [n]
    ray_indices: torch.Tensor,  # [n] int
    weights: torch.Tensor,  # [n] compositing weights
    packed_info: torch.Tensor,  # [n_rays, 2] (start, count)
    t_cut,  # float or [n_rays]
) -> torch.Tensor:
    """Each ray's compositing weight at its samples whose midpoint lies before ``t_cut``,
    ``[n_rays]``: ``sum_i w_i [(t0_i + t1_i) / 2 < t_cut]`` (differentiable in ``weights``; the
    indicator is not). A slot outside its ray's range in ``packed_info`` (the fixed-shape
    step's unused slots, whose weights the compositing leaves unwritten) counts for nothing."""
    ri, w = ray_indices.long(), _in_range(ray_indices, packed_info, weights)
    cut = torch.as_tensor(t_cut, device=weights.device, dtype=weights.dtype)
    cut = cut[ri] if cut.dim() else cut
    w = torch.where(0.5 * (t_starts + t_ends) < cut, w, torch.zeros_like(w))
    return weights.new_zeros(packed_info.shape[0]).index_add(0, ri, w)


def weight_median(
    t_starts: torch.Tensor,  # [n] in increasing order within each ray's range
    t_ends: torch.Tensor,  # [n]
    ray_indices: torch.Tensor,  # [n] int
    weights: torch.Tensor,  # [n] compositing weights
    packed_info: torch.Tensor,  # [n_rays, 2] (start, count)
) -> torch.Tensor:
    """Each ray's weighted median distance ``[n_rays]``: the midpoint of its first sample at
    which the running sum of its weights reaches half their total (NaN for a ray without
    weight). Running sums in float64; slots outside their ray's range count for nothing."""
    ri, w = ray_indices.long(), _in_range(ray_indices, packed_info, weights).double()
    n_rays = packed_info.shape[0]
    total = w.new_zeros(n_rays).index_add(0, ri, w)
    run = torch.cumsum(w, 0)  # (each ray's running sum: minus the sum before its first slot)
    start = packed_info[:, 0].long().clamp(0, max(w.shape[0] - 1, 0))
    base = (run - w)[start] if w.shape[0] else total
    run = run - base[ri]
    half = 0.5 * total[ri]
    at = (run >= half) & (run - w < half) & (total[ri] > 0)
    mid = (0.5 * (t_starts + t_ends))[at]
    out = torch.full((n_rays,), float("nan"), device=weights.device, dtype=weights.dtype)
    return out.scatter_reduce(0, ri[at], mid.to(out.dtype), "amin", include_self=False)


def _in_range(ray_indices, packed_info, values):
    """``values`` [n] with zeros at the slots outside their ray's range in ``packed_info``."""
    ri = ray_indices.long()
    slot = torch.arange(values.shape[0], device=values.device)
    start, count = packed_info[ri, 0].long(), packed_info[ri, 1].long()
    mine = (slot >= start) & (slot < start + count)
    return torch.where(mine, values, torch.zeros_like(values))


def _render_rounds(
    grid, field, o, d, near, far, background, t_threshold, round_samples, cap, half=False,
    sample_budget=SAMPLE_BUDGET, on_weights=None, color_eps=RENDER_COLOR_EPS, fill_mean=True,
):  # fmt: skip
    n_rays, dev, dt = o.shape[0], o.device, o.dtype
    use_half = half and dev.type == "cuda"
    rgb = torch.zeros(n_rays, 3, device=dev, dtype=dt)
    depth = torch.zeros(n_rays, device=dev, dtype=dt)
    trans = torch.ones(n_rays, device=dev, dtype=dt)
    seen_w = torch.zeros(n_rays, device=dev, dtype=dt)  # (the mean fill's)
    near = torch.as_tensor(near, device=dev, dtype=dt).expand(n_rays)
    far = torch.as_tensor(far, device=dev, dtype=dt).expand(n_rays)
    alive = torch.arange(n_rays, device=dev)
    k = torch.zeros(n_rays, device=dev, dtype=torch.int32)
    n_marched, n_colored, budget = 0, 0, round_samples * n_rays
    while alive.numel():
        per_ray = min(max(round_samples, budget // alive.numel()), cap)
        oa, da = o[alive], d[alive]
        smp, k_next = grid.march(
            oa, da, near[alive], far[alive], k_begin=k[alive], max_samples=per_ray
        )
        ri = smp.ray_indices
        n_marched += smp.t_starts.shape[0]
        pos = oa[ri] + da[ri] * smp.midpoints().unsqueeze(-1)
        sd = da[ri] if needs_directions(field) else None  # (NeuS: the samples' directions)
        n = pos.shape[0]
        with torch.autocast("cuda", dtype=torch.float16, enabled=use_half):
            if n <= sample_budget:  # one call; the colour head reuses its features
                sig, feats = field_density(field, pos, sd)
            else:  # bounded memory: densities in slices, features recomputed where needed
                sig = torch.cat([field_density(field, pos[s : s + sample_budget],
                                               None if sd is None else sd[s : s + sample_budget])[0]
                                 for s in range(0, n, sample_budget)])  # fmt: skip
                feats = None
        sig = sig.to(dt)
        # Weights first (no colours): the colour MLP runs only where a sample's weight in the
        # image, T_ray * w, reaches color_eps; the rest add at most their weight's sum.
        _, z, op, w = render_packed(
            smp.t_starts,
            smp.t_ends,
            ri,
            sig,
            sig.new_zeros(1, 3).expand(sig.shape[0], 3),
            alive.numel(),
            packed_info=smp.packed_info,
            return_weights=True,
            check=False,
        )
        t_a = trans[alive]
        if on_weights is not None:  # each sample's share of its ray's pixel
            on_weights(alive[ri], smp.t_starts, smp.t_ends, w * t_a[ri])
        wt = w * t_a[ri]  # each sample's weight in the image
        # coloured: weighing color_eps, or COLOR_RELATIVE of its ray's heaviest sample in this
        # round if that is less (so that every ray with weight colours some, whatever the march
        # step: a fog of many light samples colours them all), and at least COLOR_WEIGHT_EPS
        # (the tracer's rule; color_eps if smaller, which then is the rule)
        thr = color_eps
        if color_eps > COLOR_WEIGHT_EPS:  # (at most 1e-5 the relative part cannot lower it)
            heaviest = torch.zeros_like(op).scatter_reduce_(0, ri.long(), wt, "amax")
            thr = torch.clamp(COLOR_RELATIVE * heaviest[ri], COLOR_WEIGHT_EPS, color_eps)
        seen = torch.nonzero(wt >= thr).squeeze(1)
        rs = ri[seen]
        n_colored += seen.shape[0]
        c = torch.zeros(alive.numel(), 3, device=dev, dtype=dt)
        with torch.autocast("cuda", dtype=torch.float16, enabled=use_half):
            if feats is not None:
                col = field.color(feats[seen], da[rs])
            else:
                col = torch.cat([
                    field.color(field_density(field, pos[sl], da[ri[sl]])[1], da[ri[sl]])
                    for sl in seen.split(sample_budget)
                ])  # fmt: skip
        c.index_add_(0, rs, w[seen].unsqueeze(-1) * col.to(dt))
        if fill_mean:  # each ray's coloured weight in the image, over all its rounds
            seen_w.index_add_(0, alive[rs], wt[seen])
        rgb[alive] += t_a.unsqueeze(-1) * c
        depth[alive] += t_a * z
        t_a = t_a * (1.0 - op)
        trans[alive] = t_a
        k[alive] = k_next
        alive = alive[(k_next >= 0) & (t_a >= t_threshold)]
    bg = torch.as_tensor(background, device=dev, dtype=dt)
    bg = bg.expand(3) if bg.dim() == 0 else bg
    if fill_mean:  # the skipped weight takes the ray's coloured samples' mean colour (over all
        # its rounds): rgb * opacity / coloured weight
        scale = torch.where(seen_w > 0, (1.0 - trans) / seen_w.clamp_min(1e-30), 0.0)
        rgb = rgb * scale.unsqueeze(-1)  # (<= opacity: the coloured part is <= seen_w)
    rgb = rgb + trans.unsqueeze(-1) * bg
    return {
        "rgb": rgb,
        "depth": depth,
        "opacity": 1.0 - trans,
        "n_marched": n_marched,
        "n_kept": n_marched,
        "n_colored": n_colored,
    }
