"""Sphere tracing of any signed distance callable in PyTorch (neural SDFs), with the same rules
and outputs as the Warp kernel for analytic scenes (kernels/sphere_trace.py): every step
evaluates the callable once, batched over the rays still marching.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

__all__ = ["Trace", "sphere_trace_fn", "shade", "MISS", "HIT", "CAP", "INSIDE", "INVALID"]

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


@torch.no_grad()
def sphere_trace_fn(
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
) -> Trace:
    """Sphere-traces ``sdf_fn(points [m, 3]) -> sdf [m]`` (or ``(sdf, ids)``) along rays.

    Same algorithm as :func:`warpnerf.ops.sphere_trace` (see kernels/sphere_trace.py for the
    statuses, the over-relaxation fallback and the failure modes); only the rays still marching
    are evaluated at each step, so the callable sees shrinking batches.
    """
    if not (eps > 0 and normal_eps > 0 and 1.0 <= omega < 2.0 and max_iters >= 1):
        raise ValueError("need eps > 0, normal_eps > 0, 1 <= omega < 2 and max_iters >= 1")
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
    om = torch.full((n,), float(omega), dtype=dt, device=dev)
    t_prev, d_prev, step = t.clone(), torch.zeros_like(t), torch.zeros_like(t)
    active = finite.clone()
    while True:
        active &= iters < max_iters
        past = active & (t > t_far)
        back = past & (om > 1) & (step > d_prev) & (t_prev + d_prev <= t_far)
        t[back], step[back], om[back] = t_prev[back] + d_prev[back], d_prev[back], 1.0
        left = past & ~back
        status[left], t[left] = MISS, t_far[left]
        active &= ~left
        idx = active.nonzero().squeeze(-1)
        if idx.numel() == 0:
            break
        out = sdf_fn(origins[idx] + t[idx, None] * directions[idx])
        dist, pid = out if isinstance(out, tuple) else (out, None)
        dist = dist.to(dt)
        if pid is not None:
            ids[idx] = pid.to(torch.int32)
        iters[idx] += 1
        first_inside = (iters[idx] == 1) & (dist < 0)
        fail = (om[idx] > 1) & (dist.abs() + d_prev[idx] < step[idx]) & ~first_inside
        hit = (dist < eps) & ~fail & ~first_inside
        go = ~(first_inside | fail | hit)
        status[idx[first_inside]] = INSIDE
        status[idx[hit]] = HIT
        active[idx[first_inside | hit]] = False
        f = idx[fail]  # back to the last safe point, no more relaxation
        t[f] = t_prev[f] + d_prev[f]
        step[f] = d_prev[f]
        om[f] = 1.0
        g = idx[go]
        t_prev[g], d_prev[g] = t[g], dist[go]
        step[g] = om[g] * dist[go]
        t[g] = t[g] + step[g]
    left = (status == CAP) & (t >= t_far) & (om <= 1)
    status[left], t[left] = MISS, t_far[left]
    points = origins + t.unsqueeze(-1) * directions
    normals = torch.zeros_like(points)
    hit = status == HIT
    if bool(hit.any()):
        normals[hit] = tetra_normals(sdf_fn, points[hit], normal_eps)
    ids[~hit] = -1
    return Trace(t, status, iters, points, normals, ids)


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
