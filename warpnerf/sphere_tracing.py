"""Sphere tracing of any signed distance callable in PyTorch (neural SDFs), with the same rules
and outputs as the Warp kernel for analytic scenes (kernels/sphere_trace.py): every step
evaluates the callable once, batched over the rays still marching.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

__all__ = [
    "Trace",
    "sphere_trace_fn",
    "sphere_trace_steps",
    "shade",
    "MISS",
    "HIT",
    "CAP",
    "INSIDE",
    "INVALID",
]

MISS, HIT, CAP, INSIDE, INVALID = 0, 1, 2, 3, 4
_TETRA = ((1.0, -1.0, -1.0), (-1.0, -1.0, 1.0), (-1.0, 1.0, -1.0), (1.0, 1.0, 1.0))


class Trace(NamedTuple):
    """Sphere-tracing results per ray: t [n], status [n] (MISS 0, HIT 1, CAP 2 = iteration cap,
    INSIDE 3 = started inside a solid, INVALID 4 = non-finite input), iters [n] (evaluations),
    points [n, 3], normals [n, 3] (unit at hits, zero elsewhere), ids [n] (primitive hit or -1)."""

    t: torch.Tensor
    status: torch.Tensor
    iters: torch.Tensor
    points: torch.Tensor
    normals: torch.Tensor
    ids: torch.Tensor

    @property
    def hit(self) -> torch.Tensor:
        return self.status == HIT


def tetra_normals(sdf_fn, p: torch.Tensor, h: float) -> torch.Tensor:
    """Unit gradient of sdf_fn at p [n, 3] by the tetrahedral central difference."""
    g = torch.zeros_like(p)
    for k in _TETRA:
        kv = torch.tensor(k, dtype=p.dtype, device=p.device)
        g = g + _dist(sdf_fn, p + h * kv).unsqueeze(-1) * kv
    return torch.nn.functional.normalize(g, dim=-1)


def _dist(sdf_fn, p):
    out = sdf_fn(p)
    return out[0] if isinstance(out, tuple) else out


def sphere_trace_fn(sdf_fn, origins, directions, near, far, **kw) -> Trace:
    """Sphere-traces ``sdf_fn(points [m, 3]) -> sdf [m]`` (or ``(sdf, ids)``) along rays
    ``origins`` [n, 3], ``directions`` [n, 3] (unit length) from ``near`` to ``far`` (floats or
    [n]); ``kw``: ``eps`` (1e-4), ``omega`` (1.0), ``max_iters`` (256), ``normal_eps`` (1e-4),
    as :func:`sphere_trace_steps` takes them.

    Same algorithm as :func:`warpnerf.ops.sphere_trace` (see kernels/sphere_trace.py for the
    statuses, the over-relaxation fallback and the failure modes); only the rays still marching
    are evaluated at each step, so the callable sees shrinking batches.
    """
    allowed = {"eps", "omega", "max_iters", "normal_eps"}
    if set(kw) - allowed:
        raise TypeError(f"sphere_trace_fn: unknown arguments {sorted(set(kw) - allowed)}")
    return sphere_trace_steps(sdf_fn, origins, directions, near, far, **kw)[0]


@torch.no_grad()
def sphere_trace_steps(
    sdf_fn,
    origins: torch.Tensor,  # [n, 3]
    directions: torch.Tensor,  # [n, 3] unit length
    near,  # float or [n]
    far,  # float or [n]
    *,
    eps: float = 1e-4,
    omega: float = 1.0,
    max_iters: int = 256,
    normal_eps: float = 1e-4,
    normals: bool = True,
    cone: float = 0.0,
):
    """:func:`sphere_trace_fn`, also returning the last step: (Trace, t_prev [n], d_prev [n]),
    the marching point before each ray's final t and sdf_fn there (a HIT's t_prev has d_prev >=
    eps: with the hit, a bracket of the surface when the last step overshot it; near and 0
    before the first step). ``normals=False`` skips the normals (zero everywhere), for callers
    that compute their own at a refined point. ``cone`` > 0 widens the hit test to
    sdf < eps + cone * t (a pixel's footprint: cone = its half-angle; 0 is the kernel's test).

    The marching rays are kept compacted: each step evaluates them, updates them with
    element-wise selects, and drops the finished ones in one gather (one host sync a step, so
    the loop costs a few dozen launches a step whatever the number of rays).
    """
    if not (eps > 0 and normal_eps > 0 and 1.0 <= omega < 2.0 and max_iters >= 1 and cone >= 0):
        raise ValueError("need eps > 0, normal_eps > 0, 1 <= omega < 2, max_iters >= 1 and "
                         "cone >= 0")  # fmt: skip
    n, dev, dt = origins.shape[0], origins.device, origins.dtype
    t = torch.as_tensor(near, device=dev, dtype=dt).expand(n).clone()
    t_far = torch.as_tensor(far, device=dev, dtype=dt).expand(n).clone()
    status = torch.full((n,), CAP, dtype=torch.int32, device=dev)
    iters = torch.zeros(n, dtype=torch.int32, device=dev)
    ids = torch.full((n,), -1, dtype=torch.int32, device=dev)
    finite = (
        torch.isfinite(origins).all(-1)
        & torch.isfinite(directions).all(-1)
        & torch.isfinite(t)
        & torch.isfinite(t_far)
    )
    status[~finite] = INVALID
    t[~finite] = float("nan")
    om_all = torch.full((n,), float(omega), dtype=dt, device=dev)
    t_prev, d_prev = t.clone(), torch.zeros_like(t)
    # the marching rays, compacted: idx into the n rays and their state
    idx = finite.nonzero().squeeze(-1)
    o_a, d_a, ta, fa = origins[idx], directions[idx], t[idx], t_far[idx]
    om = om_all[idx]
    tp, dp, st = ta.clone(), torch.zeros_like(ta), torch.zeros_like(ta)
    it, pid_a = torch.zeros_like(idx, dtype=torch.int32), None
    fin = torch.full_like(it, -1)  # status a ray finished with, -1 while it marches
    while True:
        # before a step: out of steps (CAP), past far (MISS, or back to the last safe point
        # when an over-relaxed step jumped there)
        fin = torch.where((fin < 0) & (it >= max_iters), CAP, fin)
        past = (fin < 0) & (ta > fa)
        back = past & (om > 1) & (st > dp) & (tp + dp <= fa)
        ta, st = torch.where(back, tp + dp, ta), torch.where(back, dp, st)
        om = torch.where(back, 1.0, om)
        left = past & ~back
        fin, ta = torch.where(left, MISS, fin), torch.where(left, fa, ta)
        keep = (fin < 0).nonzero().squeeze(-1)  # (the step's one host sync)
        if keep.numel() < idx.numel():  # write the state back, then drop the finished rays
            t[idx], iters[idx], om_all[idx] = ta, it, om
            status[idx] = torch.where(fin < 0, CAP, fin)
            t_prev[idx], d_prev[idx] = tp, dp
            if pid_a is not None:
                ids[idx] = pid_a
        if keep.numel() == 0:
            break
        if keep.numel() < idx.numel():
            idx, o_a, d_a, ta, fa, om = (x[keep] for x in (idx, o_a, d_a, ta, fa, om))
            tp, dp, st, it, fin = (x[keep] for x in (tp, dp, st, it, fin))
        out = sdf_fn(o_a + ta.unsqueeze(-1) * d_a)
        dist, pid = out if isinstance(out, tuple) else (out, None)
        dist = dist.to(dt)
        pid_a = None if pid is None else pid.to(torch.int32)
        it = it + 1
        first_inside = (it == 1) & (dist < 0)
        fail = (om > 1) & (dist.abs() + dp < st) & ~first_inside
        hit = (dist < (eps + cone * ta if cone else eps)) & ~fail & ~first_inside
        go = ~(first_inside | fail | hit)
        # fail: back to the last safe point, no more relaxation
        ta, st = torch.where(fail, tp + dp, ta), torch.where(fail, dp, st)
        om = torch.where(fail, 1.0, om)
        tp, dp = torch.where(go, ta, tp), torch.where(go, dist, dp)
        st = torch.where(go, om * dist, st)
        ta = torch.where(go, ta + st, ta)
        fin = torch.where(first_inside, INSIDE, torch.where(hit, HIT, -1)).to(torch.int32)
    left = (status == CAP) & (t >= t_far) & (om_all <= 1)
    status[left], t[left] = MISS, t_far[left]
    points = origins + t.unsqueeze(-1) * directions
    nrm = torch.zeros_like(points)
    hit = status == HIT
    if normals and bool(hit.any()):
        nrm[hit] = tetra_normals(sdf_fn, points[hit], normal_eps)
    ids[~hit] = -1
    return Trace(t, status, iters, points, nrm, ids), t_prev, d_prev


def shade(
    trace: Trace,
    directions: torch.Tensor,  # [n, 3]
    colors: torch.Tensor | None = None,  # [n_ids, 3] per primitive, or None: normal map
    light=(0.4, -0.5, 0.75),
    background=(1.0, 1.0, 1.0),
    ambient: float = 0.25,
) -> torch.Tensor:
    """Lambert + ambient shading of hits (albedo from ``colors[ids]``, or the normal map
    (n + 1) / 2 when ``colors`` is None), background elsewhere; ``light`` a direction towards the
    light, or None for a headlight. Returns rgb [n, 3] in [0, 1]."""
    n = trace.normals
    if light is None:  # headlight: lit from the camera, every visible surface is shaded
        light_dirs = -directions.to(n.dtype)
    else:
        lv = torch.tensor(light, dtype=n.dtype, device=n.device)
        light_dirs = torch.nn.functional.normalize(lv, dim=0).expand_as(n)
    if colors is None:
        albedo = (n + 1) * 0.5
    else:
        albedo = colors.to(n.device, n.dtype)[trace.ids.clamp_min(0).long()]
    facing = torch.where((n * directions).sum(-1, keepdim=True) > 0, -n, n)
    lam = (facing * light_dirs).sum(-1).clamp_min(0).unsqueeze(-1)
    rgb = albedo * (ambient + (1 - ambient) * lam)
    bg = torch.tensor(background, dtype=n.dtype, device=n.device).expand_as(rgb)
    return torch.where(trace.hit.unsqueeze(-1), rgb.clamp(0, 1), bg)
