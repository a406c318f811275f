"""PyTorch twins of the analytic-scene kernels: the scene's signed distance (same primitives and
fold as kernels/sphere_trace.py) and sphere tracing (the generic torch tracer on that twin)."""

from __future__ import annotations

import torch

from ..sphere_tracing import sphere_trace_fn

__all__ = ["scene_sdf", "sphere_trace"]


def _primitive(kind: int, prm: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    if kind == 0:  # sphere
        return q.norm(dim=-1) - prm[0]
    if kind == 1:  # box (half sizes, rounding)
        d = q.abs() - prm[:3] + prm[3]
        return d.clamp_min(0).norm(dim=-1) + d.amax(-1).clamp_max(0) - prm[3]
    if kind == 2:  # torus about local y
        ring = torch.sqrt(q[:, 0] ** 2 + q[:, 2] ** 2) - prm[0]
        return torch.sqrt(ring**2 + q[:, 1] ** 2) - prm[1]
    if kind == 3:  # capsule along local y
        y = q[:, 1] - q[:, 1].clamp(-prm[0], prm[0])
        return torch.sqrt(q[:, 0] ** 2 + y**2 + q[:, 2] ** 2) - prm[1]
    return q[:, 1]  # plane


def _combine(op: int, acc, d, k):
    if op == 0:
        return torch.minimum(acc, d)
    if op == 1:
        h = (0.5 + 0.5 * (d - acc) / k).clamp(0, 1)
        return d + (acc - d) * h - k * h * (1 - h)
    if op == 2:
        return torch.maximum(acc, d)
    return torch.maximum(acc, -d)


def scene_sdf(points: torch.Tensor, scene):
    """(sdf [n], ids [n]) of an SDFScene at points [n, 3], in the points' dtype."""
    a = scene.arrays("cpu")
    dt, dev = points.dtype, points.device
    acc = ids = None
    for i in range(len(scene)):
        rot = a["rots"][i].to(dev, dt)
        q = (points - a["centers"][i].to(dev, dt)) @ rot.T
        d = _primitive(int(a["kinds"][i]), a["params"][i].to(dev, dt), q)
        if i == 0:
            acc, ids = d, torch.zeros(points.shape[0], dtype=torch.int32, device=dev)
        else:
            op = int(a["ops"][i])
            takes = d > acc if op == 2 else (-d > acc if op == 3 else d < acc)
            ids = torch.where(takes, torch.full_like(ids, i), ids)
            acc = _combine(op, acc, d, float(a["ks"][i]))
    return acc, ids


def sphere_trace(origins, directions, scene, near=0.0, far=100.0, **kw):
    """Same signature and outputs as warpnerf.ops.sphere_trace, on the torch scene twin."""
    return sphere_trace_fn(lambda p: scene_sdf(p, scene), origins, directions, near, far, **kw)
