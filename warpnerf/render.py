"""Rendering pipelines: rays -> stratified samples -> field -> Warp compositing, and sphere
tracing of an SDF field's zero level set (:func:`render_sphere_traced`); marching an occupancy
grid: :mod:`warpnerf.render_marched` (re-exported here).

Renderers take a callable ``field_fn(positions [n, 3], directions [n, 3]) -> (values [n], rgbs
[n, 3])`` whose ``values`` are densities (``mode="sigma"``) or per-sample opacities
(``mode="alpha"``); they never own the model.
"""

from __future__ import annotations

import torch

from .ops import generate_rays, ray_aabb_intersect, render_packed, stratified_samples
from .ops.bridge import check_int
from .render_marched import (
    RENDER_COLOR_EPS,
    SAMPLE_BUDGET,
    render_marched,
    render_marched_fixed,
    weight_before,
    weight_median,
)
from .sphere_tracing import CAP, HIT, INSIDE, INVALID, sphere_trace_steps

__all__ = [
    "render_rays",
    "render_image",
    "render_views",
    "render_nerf",
    "render_marched",
    "render_marched_fixed",
    "weight_before",
    "weight_median",
    "render_chunks",
    "render_sphere_traced",
    "SAMPLE_BUDGET",
    "RENDER_COLOR_EPS",
]


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
    """Renders an SDF field's zero level set by sphere tracing (:func:`warpnerf.sphere_tracing.
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
    (as sphere_tracing.py's t), background colour, opacity 0.

    Returns a dict of rgb [n_rays, 3] (the field's colour at the hit seen along the ray,
    background elsewhere), depth [n_rays] (t of the hit, 0 on a miss), opacity [n_rays] (1 on a
    hit, 0 otherwise), normals [n_rays, 3] (unit at hits, zero elsewhere; zero everywhere when
    ``normals`` is False), status [n_rays] (sphere_tracing.py's MISS/HIT/CAP/INSIDE/INVALID), iters
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
