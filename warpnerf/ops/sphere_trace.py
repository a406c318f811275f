"""Torch bridge for analytic SDF scenes and sphere tracing (kernels/sphere_trace.py). No
gradients: the outputs are geometry (hits, distances, normals), not differentiable renders."""

from __future__ import annotations

import torch

from ..sphere_tracing import Trace
from . import bridge

__all__ = ["scene_sdf", "sphere_trace"]


def _scene(scene, device):
    """The kernels' ``Scene`` struct of an SDFScene (warpnerf.fields), taken by its interface:
    ops import no fields."""
    from warpnerf.kernels import sphere_trace as K

    if not callable(getattr(scene, "arrays", None)):
        raise TypeError(f"scene must be an SDFScene, got {type(scene).__name__}")
    a = scene.arrays(device)
    wp = bridge.load_warp()
    s = K.Scene()
    s.kinds = wp.from_torch(a["kinds"])
    s.params = wp.from_torch(a["params"], wp.vec4)
    s.rots = wp.from_torch(a["rots"], wp.mat33)
    s.centers = wp.from_torch(a["centers"], wp.vec3)
    s.ops = wp.from_torch(a["ops"])
    s.ks = wp.from_torch(a["ks"])
    return s


def scene_sdf(points: torch.Tensor, scene):  # points [n, 3] float32
    """(sdf [n], ids [n] int32) of an :class:`~warpnerf.fields.SDFScene` at points."""
    from warpnerf.kernels import sphere_trace as K

    bridge.check_float("points", points, (None, 3), dtype=torch.float32)
    n, dev = points.shape[0], points.device
    sdf = torch.empty(n, device=dev, dtype=torch.float32)
    ids = torch.empty(n, device=dev, dtype=torch.int32)
    wp = bridge.load_warp()
    bridge.launch(
        K.scene_sdf_fwd,
        n,
        [bridge.arr(points, wp.vec3), _scene(scene, dev), bridge.arr(sdf), bridge.arr(ids)],
        dev,
    )
    return sdf, ids


def sphere_trace(
    origins: torch.Tensor,  # [n, 3] float32
    directions: torch.Tensor,  # [n, 3] float32, unit length
    scene,
    near=0.0,  # float or [n]
    far=100.0,  # float or [n]
    *,
    eps: float = 1e-4,
    omega: float = 1.0,
    max_iters: int = 256,
    normal_eps: float = 1e-4,
) -> Trace:
    """Sphere-traces an analytic scene, one Warp thread per ray.

    A ray marches ``t += omega * sdf`` from ``near`` until ``sdf < eps`` (HIT), ``t > far``
    (MISS) or ``max_iters`` evaluations (CAP, not a hit); a ray starting inside a solid is INSIDE,
    non-finite input INVALID. ``omega`` in [1, 2) over-relaxes with Keinert's fallback (see
    kernels/sphere_trace.py for the rules and failure modes). Returns a :class:`Trace`.
    """
    from warpnerf.kernels import sphere_trace as K

    bridge.check_float("origins", origins, (None, 3), dtype=torch.float32)
    n, dev = origins.shape[0], origins.device
    bridge.check_float("directions", directions, (n, 3), torch.float32, dev)
    max_iters = bridge.check_int("max_iters", max_iters, lo=1)
    if not (eps > 0 and normal_eps > 0 and 1.0 <= omega < 2.0):
        raise ValueError("need eps > 0, normal_eps > 0, 1 <= omega < 2 and max_iters >= 1")
    if n:
        norms = directions.norm(dim=-1)
        bad = torch.isfinite(norms) & ((norms - 1).abs() > 1e-3)
        if bool(bad.any()):  # a step of d(t) along a longer vector would tunnel through surfaces
            raise ValueError("directions must have unit length (sphere tracing steps by distance)")
    near = torch.as_tensor(near, device=dev, dtype=torch.float32).expand(n).contiguous()
    far = torch.as_tensor(far, device=dev, dtype=torch.float32).expand(n).contiguous()
    f32 = dict(device=dev, dtype=torch.float32)
    t = torch.empty(n, **f32)
    status = torch.empty(n, device=dev, dtype=torch.int32)
    iters = torch.empty(n, device=dev, dtype=torch.int32)
    points = torch.empty(n, 3, **f32)
    normals = torch.empty(n, 3, **f32)
    ids = torch.empty(n, device=dev, dtype=torch.int32)
    wp = bridge.load_warp()
    v3 = wp.vec3
    a = bridge.arr
    bridge.launch(
        K.sphere_trace_fwd,
        n,
        [
            a(origins, v3),
            a(directions, v3),
            a(near),
            a(far),
            _scene(scene, dev),
            float(eps),
            float(omega),
            int(max_iters),
            float(normal_eps),
            a(t),
            a(status),
            a(iters),
            a(points, v3),
            a(normals, v3),
            a(ids),
        ],
        dev,
    )
    return Trace(t, status, iters, points, normals, ids)
