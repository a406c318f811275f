"""Rendering pipelines: rays -> stratified samples -> field -> Warp compositing.

Renderers take a callable ``field_fn(positions [n, 3], directions [n, 3]) -> (values [n], rgbs
[n, 3])`` whose ``values`` are densities (``mode="sigma"``) or per-sample opacities
(``mode="alpha"``); they never own the model.
"""

from __future__ import annotations

import torch

from .ops import generate_rays, ray_aabb_intersect, render_packed, stratified_samples
from .ops._bridge import check_int

__all__ = [
    "render_rays",
    "render_image",
    "render_views",
    "render_nerf",
    "render_marched",
    "render_chunks",
]


SAMPLE_BUDGET = 1 << 23  # rendering: most samples the field sees in one call (memory bound)


def render_chunks(n_rays: int, chunk: int | None, render_fn):
    """The one chunked-rendering helper (used by the renderers, eval, render, video, the SDF
    geometry view and the training loop's validation): calls ``render_fn(sl)`` on consecutive
    slices ``sl`` of at most ``chunk`` of the ``n_rays`` rays (None: all at once) and joins the
    outputs, which may be a tensor, a tuple or a dict of them: tensors with one row per ray are
    concatenated, numbers (ints, floats, 0-d tensors: counters such as ``n_kept``) summed.
    Zero rays still make one call (with an empty slice), so the outputs keep their shapes."""
    chunk = max(n_rays, 1) if chunk is None else check_int("chunk", chunk, lo=1, hi=2**62)
    outs = [render_fn(slice(s, min(s + chunk, n_rays))) for s in range(0, max(n_rays, 1), chunk)]
    return _join(outs)


def _join(outs: list):
    first = outs[0]
    if isinstance(first, dict):
        return {k: _join([o[k] for o in outs]) for k in first}
    if isinstance(first, tuple):
        return tuple(_join(list(x)) for x in zip(*outs))
    if isinstance(first, torch.Tensor) and first.dim() > 0:
        return first if len(outs) == 1 else torch.cat(outs)
    return sum(outs[1:], first)


def render_rays(
    origins: torch.Tensor,  # [n_rays, 3]
    directions: torch.Tensor,  # [n_rays, 3]
    near,  # float or [n_rays]
    far,  # float or [n_rays]
    field_fn,
    *,
    n_samples: int = 64,
    mode: str = "sigma",
    background=None,
    perturb: bool = False,
    seed: int = 0,
    t_threshold: float = 0.0,
    chunk: int | None = None,
):
    """Volume-renders rays with packed stratified samples (rays with far <= near cost nothing).

    ``chunk`` bounds the rays processed at once (memory ~ chunk * n_samples); use it under
    ``torch.no_grad()`` for full images. Returns a dict of rgb [n_rays, 3], depth [n_rays]
    (expected, not normalised), opacity [n_rays].
    """
    if mode not in ("sigma", "alpha"):
        raise ValueError(f"mode must be 'sigma' or 'alpha', got {mode!r}")
    n_rays = origins.shape[0]
    dev, dt = origins.device, origins.dtype
    near = torch.as_tensor(near, device=dev, dtype=dt).expand(n_rays).contiguous()
    far = torch.as_tensor(far, device=dev, dtype=dt).expand(n_rays).contiguous()

    def chunk_fn(sl):
        smp = stratified_samples(
            near[sl], far[sl], n_samples, perturb=perturb, seed=seed + sl.start, packed=True
        )
        bg = background
        if isinstance(bg, torch.Tensor) and bg.dim() == 2:
            bg = bg[sl]
        return _shade(field_fn, origins[sl], directions[sl], smp, bg, t_threshold, False, mode)

    rgb, depth, opacity = render_chunks(n_rays, chunk, chunk_fn)
    return {"rgb": rgb, "depth": depth, "opacity": opacity}


@torch.no_grad()
def render_image(
    c2w, intrinsics, width: int, height: int, near, far, field_fn, *, chunk: int = 16384, **kw
):
    """One camera (c2w [4, 4], intrinsics [4]) to rgb [H, W, 3], depth and opacity [H, W]."""
    o, d = generate_rays(c2w, intrinsics, width, height)
    out = render_rays(o, d, near, far, field_fn, chunk=chunk, **kw)
    return {
        "rgb": out["rgb"].reshape(height, width, 3),
        "depth": out["depth"].reshape(height, width),
        "opacity": out["opacity"].reshape(height, width),
    }


@torch.no_grad()
def render_views(c2w, intrinsics, width: int, height: int, near, far, field_fn, **kw):
    """Cameras c2w [N, 4, 4], intrinsics [N, 4] to rgb [N, H, W, 3], depth, opacity [N, H, W]."""
    outs = [
        render_image(c2w[i], intrinsics[i], width, height, near, far, field_fn, **kw)
        for i in range(c2w.shape[0])
    ]
    return {k: torch.stack([o[k] for o in outs]) for k in ("rgb", "depth", "opacity")}


def render_nerf(
    coarse,
    origins: torch.Tensor,  # [n_rays, 3]
    directions: torch.Tensor,  # [n_rays, 3] unit length
    near: float,
    far: float,
    *,
    fine=None,
    n_coarse: int = 64,
    n_fine: int = 0,
    perturb: bool = False,
    seed: int = 0,
    background=1.0,
    t_threshold: float = 1e-4,
    chunk: int | None = None,
    aabb=None,
):
    """NeRF's hierarchical volume rendering through the Warp kernels.

    ``coarse(positions, directions) -> (sigmas, rgbs)`` is evaluated at ``n_coarse`` stratified
    samples per ray; with a ``fine`` callable and ``n_fine > 0``, ``n_fine`` more positions are
    drawn from the coarse weights (inverse CDF) and ``fine`` is evaluated on the union of coarse
    and fine intervals.
    When both are the same network, the coarse pass runs without gradients (it only places the
    fine samples). ``aabb`` [6] restricts samples to the box (rays that miss it get none).
    Returns rgb, depth, opacity [n_rays(, 3)] from the finest level and ``rgb_coarse``.
    """
    n_fine = check_int("n_fine", n_fine)
    dev, dt = origins.device, origins.dtype

    def chunk_fn(sl):
        o, d, s = origins[sl], directions[sl], sl.start
        m = o.shape[0]
        nr = torch.full((m,), float(near), device=dev, dtype=dt)
        fr = torch.full((m,), float(far), device=dev, dtype=dt)
        if aabb is not None:
            t0, t1, hit = ray_aabb_intersect(o, d, aabb)
            nr = torch.maximum(nr, t0)
            fr = torch.where(hit, torch.minimum(fr, t1), nr)
        smp = stratified_samples(nr, fr, n_coarse, perturb=perturb, seed=seed + s, packed=True)
        shared = fine is coarse and n_fine > 0
        with torch.set_grad_enabled(torch.is_grad_enabled() and not shared):
            res = _shade(coarse, o, d, smp, background, t_threshold, want_weights=True)
        out = {"rgb_coarse": res[0]}
        if fine is not None and n_fine > 0:
            from .ops.sampling import importance_samples

            smp_fine = importance_samples(
                smp, res[3].detach(), n_fine, perturb=perturb, seed=seed + s + 7919
            )
            res = _shade(fine, o, d, smp_fine, background, t_threshold, want_weights=False)
        out.update(rgb=res[0], depth=res[1], opacity=res[2])
        return out

    return render_chunks(origins.shape[0], chunk, chunk_fn)


def _shade(field, o, d, smp, background, t_threshold, want_weights, mode="sigma"):
    """Evaluates ``field`` at the packed samples' midpoints and composites them (the one place
    both renderers shade samples). mode: the field returns densities ("sigma") or opacities.
    ``smp`` comes from the library's own samplers: its packed_info is not re-checked (no sync)."""
    ri = smp.ray_indices
    positions = o[ri] + d[ri] * smp.midpoints().unsqueeze(-1)
    values, rgbs = field(positions, d[ri])
    kw = {"sigmas": None, "alphas": values} if mode == "alpha" else {"sigmas": values}
    return render_packed(
        smp.t_starts,
        smp.t_ends,
        ri,
        rgbs=rgbs,
        n_rays=o.shape[0],
        background=background,
        packed_info=smp.packed_info,
        t_threshold=t_threshold,
        return_weights=want_weights,
        check=False,
        **kw,
    )


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
):
    """Volume rendering with an occupancy grid: packed marching + early termination.

    ``grid`` (:class:`warpnerf.OccupancyGrid`) emits lattice samples of step ``grid.dt`` in
    occupied cells (the lattice shifted by a random fraction of a step per ray when ``perturb``,
    drawn from ``generator`` on the rays' device). ``field`` is a module with ``density(positions)
    -> (sigmas [n], features)`` and ``color(features, directions) -> rgbs [n, 3]``. Densities of
    all marched samples are computed first without gradients; each ray keeps its samples before
    transmittance drops below ``t_threshold`` (the compositing kernels' own rule, so forward and
    backward see the same samples); the field then runs again with gradients on the kept samples
    only.

    Without gradients (rendering) the field's density runs once on the marched samples, their
    weights are composited, and the colour MLP runs only on samples whose weight reaches
    ``COLOR_WEIGHT_EPS`` (1e-5; the others count as black, an error below their summed weight).
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
    ``n_marched`` / ``n_kept`` (ints).

    The packed samples are the grid's own: they are composited without re-checking their indices
    (``render_packed(check=False)``), so no host sync is added to the marching's own.
    """
    from .ops.occupancy import live_samples
    from .ops.sampling import Samples

    max_samples = check_int("max_samples", max_samples, lo=1)
    round_samples = check_int("round_samples", round_samples)
    sample_budget = check_int("sample_budget", sample_budget, lo=1, hi=2**62)
    if not torch.is_grad_enabled():
        return _render_rounds(
            grid, field, origins, directions, near, far, background, t_threshold,
            round_samples or max_samples, max_samples, half, sample_budget,
        )  # fmt: skip
    n_rays, dev = origins.shape[0], origins.device
    jitter = None
    if perturb:
        jitter = torch.rand(n_rays, device=dev, generator=generator)
    smp, _ = grid.march(origins, directions, near, far, jitter=jitter, max_samples=max_samples)
    ri = smp.ray_indices
    positions = origins[ri] + directions[ri] * smp.midpoints().unsqueeze(-1)
    with torch.no_grad():
        sigmas, _ = field.density(positions)
    keep, n_live = live_samples(smp, sigmas, t_threshold, check=False)
    idx = torch.nonzero(keep).squeeze(1)
    counts = n_live.to(torch.int64)
    info = torch.stack([torch.cumsum(counts, 0) - counts, counts], -1).to(torch.int32)
    kept = Samples(smp.t_starts[idx], smp.t_ends[idx], ri[idx], info)
    dirs = directions[kept.ray_indices]
    sigmas, feats = field.density(positions[idx])
    rgbs = field.color(feats, dirs)
    rgb, depth, opacity = render_packed(
        kept.t_starts,
        kept.t_ends,
        kept.ray_indices,
        sigmas,
        rgbs,
        n_rays,
        background=background,
        packed_info=kept.packed_info,
        t_threshold=t_threshold,
        check=False,
    )
    return {
        "rgb": rgb,
        "depth": depth,
        "opacity": opacity,
        "n_marched": int(smp.t_starts.shape[0]),
        "n_kept": int(idx.shape[0]),
    }


COLOR_WEIGHT_EPS = 1e-5  # rendering: colours of samples weighing less are skipped


def _render_rounds(
    grid, field, o, d, near, far, background, t_threshold, round_samples, cap, half=False,
    sample_budget=SAMPLE_BUDGET,
):  # fmt: skip
    n_rays, dev, dt = o.shape[0], o.device, o.dtype
    use_half = half and dev.type == "cuda"
    rgb = torch.zeros(n_rays, 3, device=dev, dtype=dt)
    depth = torch.zeros(n_rays, device=dev, dtype=dt)
    trans = torch.ones(n_rays, device=dev, dtype=dt)
    near = torch.as_tensor(near, device=dev, dtype=dt).expand(n_rays)
    far = torch.as_tensor(far, device=dev, dtype=dt).expand(n_rays)
    alive = torch.arange(n_rays, device=dev)
    k = torch.zeros(n_rays, device=dev, dtype=torch.int32)
    n_marched, budget = 0, round_samples * n_rays
    while alive.numel():
        per_ray = min(max(round_samples, budget // alive.numel()), cap)
        oa, da = o[alive], d[alive]
        smp, k_next = grid.march(
            oa, da, near[alive], far[alive], k_begin=k[alive], max_samples=per_ray
        )
        ri = smp.ray_indices
        n_marched += smp.t_starts.shape[0]
        pos = oa[ri] + da[ri] * smp.midpoints().unsqueeze(-1)
        n = pos.shape[0]
        with torch.autocast("cuda", dtype=torch.float16, enabled=use_half):
            if n <= sample_budget:  # one call; the colour head reuses its features
                sig, feats = field.density(pos)
            else:  # bounded memory: densities in slices, features recomputed where needed
                sig = torch.cat([field.density(pos[s : s + sample_budget])[0]
                                 for s in range(0, n, sample_budget)])  # fmt: skip
                feats = None
        sig = sig.to(dt)
        # Weights first (no colours): the colour MLP runs only where a sample's weight in the
        # image, T_ray * w, reaches COLOR_WEIGHT_EPS; the rest add at most their weight's sum.
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
        seen = torch.nonzero(w * t_a[ri] >= COLOR_WEIGHT_EPS).squeeze(1)
        rs = ri[seen]
        c = torch.zeros(alive.numel(), 3, device=dev, dtype=dt)
        with torch.autocast("cuda", dtype=torch.float16, enabled=use_half):
            if feats is not None:
                col = field.color(feats[seen], da[rs])
            else:
                col = torch.cat([
                    field.color(field.density(pos[sl])[1], da[ri[sl]])
                    for sl in seen.split(sample_budget)
                ])  # fmt: skip
        c.index_add_(0, rs, w[seen].unsqueeze(-1) * col.to(dt))
        rgb[alive] += t_a.unsqueeze(-1) * c
        depth[alive] += t_a * z
        t_a = t_a * (1.0 - op)
        trans[alive] = t_a
        k[alive] = k_next
        alive = alive[(k_next >= 0) & (t_a >= t_threshold)]
    bg = torch.as_tensor(background, device=dev, dtype=dt)
    bg = bg.expand(3) if bg.dim() == 0 else bg
    rgb = rgb + trans.unsqueeze(-1) * bg
    return {
        "rgb": rgb,
        "depth": depth,
        "opacity": 1.0 - trans,
        "n_marched": n_marched,
        "n_kept": n_marched,
    }
