"""Rendering pipelines: rays -> stratified samples -> field -> Warp compositing, and sphere
tracing of an SDF field's zero level set (:func:`render_sphere_traced`).

Renderers take a callable ``field_fn(positions [n, 3], directions [n, 3]) -> (values [n], rgbs
[n, 3])`` whose ``values`` are densities (``mode="sigma"``) or per-sample opacities
(``mode="alpha"``); they never own the model.
"""

from __future__ import annotations

import torch

from .ops import generate_rays, ray_aabb_intersect, render_packed, stratified_samples
from .ops.bridge import check_int
from .trace import CAP, HIT, INSIDE, INVALID, sphere_trace_steps

__all__ = [
    "render_rays",
    "render_image",
    "render_views",
    "render_nerf",
    "render_marched",
    "render_marched_fixed",
    "render_chunks",
    "render_sphere_traced",
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
            near[sl], far[sl], n_samples, perturb=perturb, seed=seed, packed=True,
            ray_offset=sl.start,
        )  # fmt: skip
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
    ray_offset: int = 0,
):
    """NeRF's hierarchical volume rendering through the Warp kernels.

    ``coarse(positions, directions) -> (sigmas, rgbs)`` is evaluated at ``n_coarse`` stratified
    samples per ray; with a ``fine`` callable and ``n_fine > 0``, ``n_fine`` more positions are
    drawn from the coarse weights (inverse CDF) and ``fine`` is evaluated on the union of coarse
    and fine intervals.
    When both are the same network, the coarse pass runs without gradients (it only places the
    fine samples). ``aabb`` [6] restricts samples to the box (rays that miss it get none).
    ``perturb`` jitter is keyed by ``seed`` and each ray's index plus ``ray_offset`` (these rays
    are a slice of a larger batch starting there: a data-parallel rank's share), so chunks and
    slices draw what the whole batch would.
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
        smp = stratified_samples(nr, fr, n_coarse, perturb=perturb, seed=seed, packed=True,
                                 ray_offset=ray_offset + s)  # fmt: skip
        shared = fine is coarse and n_fine > 0
        with torch.set_grad_enabled(torch.is_grad_enabled() and not shared):
            res = _shade(coarse, o, d, smp, background, t_threshold, want_weights=True)
        out = {"rgb_coarse": res[0]}
        if fine is not None and n_fine > 0:
            from .ops.sampling import importance_samples

            smp_fine = importance_samples(
                smp,
                res[3].detach(),
                n_fine,
                perturb=perturb,
                seed=seed + 7919,
                ray_offset=ray_offset + s,
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
    jitter: torch.Tensor | None = None,
    ray_images: torch.Tensor | None = None,
    distortion_s=None,
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
    ``n_marched`` / ``n_kept`` (ints); with gradients and ``distortion_s`` (a map of ray
    distances t to a normalised coordinate s, increasing) also ``distortion`` [n_rays], each
    ray's distortion loss (:func:`warpnerf.ops.distortion_loss`) of its kept samples' weights.

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
    if jitter is None and perturb:
        jitter = torch.rand(n_rays, device=dev, generator=generator)
    smp, _ = grid.march(origins, directions, near, far, jitter=jitter, max_samples=max_samples)
    ri = smp.ray_indices
    positions = origins[ri] + directions[ri] * smp.midpoints().unsqueeze(-1)
    with torch.no_grad():
        enc, sigmas = _first_pass(field, positions)
    keep, n_live = live_samples(smp, sigmas, t_threshold, check=False)
    idx = torch.nonzero(keep).squeeze(1)
    counts = n_live.to(torch.int64)
    info = torch.stack([torch.cumsum(counts, 0) - counts, counts], -1).to(torch.int32)
    kept = Samples(smp.t_starts[idx], smp.t_ends[idx], ri[idx], info)
    sigmas, feats = _second_pass(field, positions[idx], None if enc is None else enc[idx])
    out = _shade_kept(field, directions, kept, sigmas, feats, background, t_threshold,
                      ray_images, distortion_s)  # fmt: skip
    out.update(n_marched=int(smp.t_starts.shape[0]), n_kept=int(idx.shape[0]))
    return out


def _first_pass(field, positions):
    """(encoding or None, sigmas) of a marcher's first, gradient-free pass: a field that can
    hand over its encoding (``encode``) keeps it for the second pass."""
    if getattr(field, "encode", None) is None:
        return None, field.density(positions)[0]
    enc = field.encode(positions)
    return enc, field.density(positions, encoded=enc)[0]


def _second_pass(field, positions, enc):
    """(sigmas, features) of the kept samples, with gradients (the encoding reused)."""
    return field.density(positions) if enc is None else field.density(positions, encoded=enc)


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
    ``distortion_s``) and ``stats``, an int64 device tensor [5]: (samples marched, marched
    samples dropped, rays refused, live samples, live samples dropped).
    """
    from .ops.occupancy import live_samples_fixed

    smp, _, march_stats = grid.march(origins, directions, near, far, jitter=jitter,
                                     max_samples=max_samples, capacity=marched)  # fmt: skip
    ri = smp.ray_indices
    positions = origins[ri] + directions[ri] * smp.midpoints().unsqueeze(-1)
    with torch.no_grad():
        enc, sigmas = _first_pass(field, positions)
    live, src, live_stats = live_samples_fixed(smp, sigmas.float(), t_threshold, kept)
    sigmas, feats = _second_pass(field, positions[src], None if enc is None else enc[src])
    color_kw = None
    if getattr(field, "kind", "density") == "sdf":  # its eikonal term: the live slots only
        n_live = live_stats[0].clamp_max(kept)
        color_kw = {"valid": torch.arange(kept, device=directions.device) < n_live}
    out = _shade_kept(field, directions, live, sigmas, feats, background, t_threshold,
                      ray_images, distortion_s, color_kw)  # fmt: skip
    out["stats"] = torch.cat([march_stats, live_stats])
    return out


def _shade_kept(field, directions, kept, sigmas, feats, background, t_threshold, ray_images,
                distortion_s, color_kw=None) -> dict:  # fmt: skip
    """The marchers' last part: colours of the kept samples (with their densities and
    features from the field's second pass), compositing, and each ray's distortion loss when
    ``distortion_s`` is given. ``color_kw``: more keywords for the field's ``color``."""
    dirs = directions[kept.ray_indices]
    kw = dict(color_kw or {})
    if ray_images is not None:
        kw["image_ids"] = ray_images[kept.ray_indices]
    rgbs = field.color(feats, dirs, **kw)
    rgb, depth, opacity, *weights = render_packed(
        kept.t_starts, kept.t_ends, kept.ray_indices, sigmas, rgbs, directions.shape[0],
        background=background, packed_info=kept.packed_info, t_threshold=t_threshold,
        check=False, return_weights=distortion_s is not None,
    )  # fmt: skip
    out = {"rgb": rgb, "depth": depth, "opacity": opacity}
    if distortion_s is not None:
        from .ops.distortion import distortion_loss

        out["distortion"] = distortion_loss(
            distortion_s(kept.t_starts), distortion_s(kept.t_ends), kept.ray_indices, weights[0],
            directions.shape[0], packed_info=kept.packed_info, check=False,
        )  # fmt: skip
    return out


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


SPHERE_CHUNK = 1 << 18  # sphere tracing: rays at once (memory ~ rays, not rays x samples)


@torch.no_grad()
def render_sphere_traced(
    field,
    origins: torch.Tensor,  # [n_rays, 3]
    directions: torch.Tensor,  # [n_rays, 3] any length > 0
    near,  # float or [n_rays]
    far,  # float or [n_rays]
    *,
    aabb=None,
    background=1.0,
    eps: float = 1e-3,
    cone: float = 0.0,
    max_iters: int = 64,
    step_scale: float = 0.9,
    refine_steps: int = 2,
    cap_eps: float | None = None,
    normals: bool = True,
    chunk: int | None = SPHERE_CHUNK,
):
    """Renders an SDF field's zero level set by sphere tracing (:func:`warpnerf.trace.
    sphere_trace_fn`, one batched ``field.sdf`` call per step) and its colour head at the hit.

    ``field`` has ``sdf(x [m, 3]) -> [m]`` (world units), ``forward(x, d) -> (sigmas, rgbs)``
    (for hash_sdf: ``density`` then ``color(features, d)``, what the volume renderer composites
    at the surface) and, when ``normals``, ``normals(x) -> [m, 3]``. Rays are clipped to
    ``aabb`` [6] first (a hash SDF clamps positions to its box, so its values outside are no
    distances) and to near..far (in the units of t along ``directions``, as the volume
    renderers). Marching runs in unit-speed t with steps ``step_scale * sdf`` (< 1: a learned
    SDF is not exactly 1-Lipschitz), stops where sdf < ``eps`` + ``cone`` * t (world units; t
    from the ray's origin: cone = half a pixel's angle stops within a pixel's footprint), then
    ``refine_steps`` evaluations polish the hit (:func:`_refine`: false position with the
    Illinois rule on the bracket [last step, hit] when the step overshot the surface, secant
    steps when it stopped short), keeping the t of smallest |sdf|. A ray that starts inside the
    solid (sdf < 0 at its first point) hits there; one that reached ``max_iters`` (grazing) hits
    where |sdf| < ``cap_eps`` (default 10 * eps) after refinement, else misses. Rays with
    non-finite or zero origins/directions, or non-finite near/far, are status INVALID: depth NaN
    (as trace.py's t), background colour, opacity 0.

    Returns a dict of rgb [n_rays, 3] (the field's colour at the hit seen along the ray,
    background elsewhere), depth [n_rays] (t of the hit, 0 on a miss), opacity [n_rays] (1 on a
    hit, 0 otherwise), normals [n_rays, 3] (unit at hits, zero elsewhere; zero everywhere when
    ``normals`` is False), status [n_rays] (trace.py's MISS/HIT/CAP/INSIDE/INVALID), iters
    [n_rays] (marching steps) and the counters ``n_sdf`` (points the SDF saw while marching and
    refining) and ``n_hit``.
    """
    if not (eps > 0 and cone >= 0 and 0 < step_scale <= 1):
        raise ValueError(f"need eps > 0, cone >= 0 and 0 < step_scale <= 1, got {eps}, {cone}, "
                         f"{step_scale}")  # fmt: skip
    max_iters = check_int("max_iters", max_iters, lo=1)
    refine_steps = check_int("refine_steps", refine_steps)
    cap_eps = 10.0 * eps if cap_eps is None else float(cap_eps)
    n_rays, dev, dt = origins.shape[0], origins.device, origins.dtype
    near = torch.as_tensor(near, device=dev, dtype=dt).expand(n_rays)
    far = torch.as_tensor(far, device=dev, dtype=dt).expand(n_rays)
    bg = torch.as_tensor(background, device=dev, dtype=dt)
    bg = bg.expand(3) if bg.dim() == 0 else bg
    opts = (aabb, eps, cone, max_iters, step_scale, refine_steps, cap_eps, normals)

    def chunk_fn(sl):
        b = bg[sl] if bg.dim() == 2 else bg.expand(sl.stop - sl.start, 3)
        return _trace_chunk(field, origins[sl], directions[sl], near[sl], far[sl], b, *opts)

    return render_chunks(n_rays, chunk, chunk_fn)


def _trace_chunk(field, o, d, near, far, bg, aabb, eps, cone, max_iters, step_scale,
                 refine_steps, cap_eps, want_normals):  # fmt: skip
    n, dev, dt = o.shape[0], o.device, o.dtype
    length = d.norm(dim=-1)
    valid = (torch.isfinite(o).all(-1) & torch.isfinite(d).all(-1) & torch.isfinite(length)
             & (length > 0) & torch.isfinite(near) & torch.isfinite(far))  # fmt: skip
    o0 = torch.where(valid.unsqueeze(-1), o, 0.0)
    u = torch.where(valid.unsqueeze(-1), d / length.clamp_min(1e-30).unsqueeze(-1), 0.0)
    u[~valid, 2] = 1.0  # (any unit direction: these rays are not traced)
    scale = torch.where(valid, length, 1.0)  # metric t = t * |d|
    lo = torch.where(valid, near, 0.0) * scale
    hi = torch.where(valid, far, 0.0) * scale
    live = valid & (lo <= hi)
    if aabb is not None:
        t0, t1, inbox = ray_aabb_intersect(o0, u, aabb)
        lo, hi = torch.maximum(lo, t0), torch.minimum(hi, t1)
        live &= inbox & (lo <= hi)
    status = torch.zeros(n, dtype=torch.int32, device=dev)  # MISS
    status[~valid] = INVALID
    iters = torch.zeros(n, dtype=torch.int32, device=dev)
    rgb, depth = bg.clone(), torch.zeros(n, device=dev, dtype=dt)
    depth[~valid] = float("nan")
    opacity, nrm = torch.zeros_like(depth), torch.zeros(n, 3, device=dev, dtype=dt)
    idx = live.nonzero().squeeze(1)
    out = {"rgb": rgb, "depth": depth, "opacity": opacity, "normals": nrm, "status": status,
           "iters": iters, "n_sdf": 0, "n_hit": 0}  # fmt: skip
    if idx.numel() == 0:
        return out
    sdf = field.sdf
    oi, ui, lo, hi = o0[idx], u[idx], lo[idx], hi[idx]
    tr, t_prev, d_prev = sphere_trace_steps(lambda p: step_scale * sdf(p), oi, ui, lo, hi,
                                            eps=step_scale * eps, cone=step_scale * cone,
                                            max_iters=max_iters, normals=False)  # fmt: skip
    status[idx], iters[idx] = tr.status, tr.iters
    t, n_sdf = tr.t, int(tr.iters.sum())
    hit = tr.status == INSIDE  # surface at the first point (the box face or the near plane)
    cand = ((tr.status == HIT) | (tr.status == CAP)).nonzero().squeeze(1)
    if cand.numel() and (refine_steps or bool((tr.status[cand] == CAP).any())):
        tc, dc = _refine(sdf, oi[cand], ui[cand], t[cand], t_prev[cand],
                         d_prev[cand] / step_scale, lo[cand], hi[cand], refine_steps)  # fmt: skip
        t = t.clone()
        t[cand] = tc
        n_sdf += cand.numel() * (refine_steps + 1)
        hit[cand] = (tr.status[cand] == HIT) | (dc.abs() < cap_eps)
    else:
        hit[cand] = tr.status[cand] == HIT
    h = hit.nonzero().squeeze(1)
    if h.numel() == 0:
        return out
    p = oi[h] + t[h].unsqueeze(-1) * ui[h]
    gi = idx[h]
    rgb[gi] = field(p, d[gi])[1].to(dt)
    depth[gi] = t[h] / scale[gi]
    opacity[gi] = 1.0
    if want_normals:
        nrm[gi] = field.normals(p).to(dt)
    out.update(n_sdf=n_sdf, n_hit=int(h.numel()))
    return out


def _refine(sdf, o, u, t, t_prev, d_prev, lo, hi, steps):
    """Polishes sphere-tracing hits t [m] along unit rays o + t u, given the march's previous
    point t_prev (sdf d_prev >= 0 there). Each step is a secant step through the two latest
    points a, b: t = b - f(b) (b - a) / (f(b) - f(a)); while they bracket the root (an overshot
    hit: f < 0 at the hit) it is false position with the Illinois rule (halve the kept end's
    value when the same end is kept twice, so both ends converge), otherwise it extrapolates
    (a hit that stopped short, f in [0, eps)); a flat pair falls back to t + f(t). Clamped to
    lo..hi. Returns (t, sdf) of smallest |sdf| seen: (t, sdf(t)) for steps = 0."""

    def at(tt):
        return sdf(o + tt.unsqueeze(-1) * u).to(t.dtype)

    a, fa = t_prev, d_prev
    b, fb = t, at(t)
    best_t, best_d = b, fb
    for _ in range(steps):
        den = fb - fa
        ok = (den.abs() > 1e-12) & (a != b)
        c = torch.where(ok, b - fb * (b - a) / torch.where(ok, den, 1.0), b + fb)
        c = torch.minimum(torch.maximum(c, lo), hi)
        fc = at(c)
        bracket = (fa * fb < 0) & ok
        keep_a = bracket & (fc * fb > 0)  # c on b's side: a stays, Illinois halves f(a)
        a = torch.where(keep_a, a, b)
        fa = torch.where(keep_a, 0.5 * fa, fb)
        b, fb = c, fc
        better = fb.abs() < best_d.abs()
        best_t, best_d = torch.where(better, b, best_t), torch.where(better, fb, best_d)
    return best_t, best_d
