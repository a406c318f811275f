"""Readable twin of the occupancy grid's view culling (:func:`warpnerf.occupancy.seen_cells`,
same name and signature): one cell at a time, one camera at a time, in plain Python floats. Each
cell's hull is listed vertex by vertex (homogeneous: weight 1 a point, 0 a direction) and moved
into each camera's own frame, where the five sides of its frustum are the image's tangent bounds
and the depth; a cell is culled when every camera has a side that all of the hull lies beyond.
"""

from __future__ import annotations

import itertools

import torch

__all__ = ["seen_cells"]

NDC_NEAR = 1.0  # warpnerf.data.cameras.ndc_rays' near plane


def _hull(lo, hi, outer: bool, contract: float, ndc):
    """[(vertex (x, y, z), weight)] of the cell [lo, hi] (3 floats each) in world space, or None
    when its region cannot be bounded."""
    corners = [tuple(hi[k] if bit else lo[k] for k, bit in enumerate(b))
               for b in itertools.product((0, 1), repeat=3)]  # fmt: skip
    if ndc is not None:  # point (X, Y, Z) of NDC space is world (n X W/fx, n Y H/fy, -2n) / (1 - Z)
        fx, fy, w, h = (float(v) for v in ndc)
        n = NDC_NEAR
        return [((n * x * w / fx, n * y * h / fy, -2 * n), 1 - z) for x, y, z in corners]
    if not contract or max(max(abs(v) for v in c) for c in corners) <= contract:
        return [(c, 1.0) for c in corners]  # world space is the grid's own
    a = contract

    def world_norm(s):  # max-norm of the world point whose contraction has max-norm s
        return s if s <= a else a * a / (2 * a - s)

    norms = [max(abs(v) for v in c) for c in corners]
    s_min = max(max(lo[k], -hi[k], 0.0) for k in range(3))
    if s_min <= 0:
        return None
    dirs = [tuple(v / m for v in c) for c, m in zip(corners, norms)]
    centre = [0.5 * (lo[k] + hi[k]) for k in range(3)]
    axis = max(range(3), key=lambda k: abs(centre[k]))
    sign = 1.0 if centre[axis] > 0 else -1.0
    beta = min(sign * d[axis] for d in dirs)
    if beta <= 0:
        return None
    near = [(tuple(world_norm(s_min) * v for v in d), 1.0) for d in dirs]
    if outer:
        return near + [(d, 0.0) for d in dirs]
    big = world_norm(max(norms)) / beta
    return near + [(tuple(big * v for v in d), 1.0) for d in dirs]


def _camera_sees(hull, c2w, bounds) -> bool:
    r = [[float(c2w[i][j]) for j in range(3)] for i in range(3)]
    o = [float(c2w[i][3]) for i in range(3)]
    x_lo, x_hi, y_lo, y_hi = (float(v) for v in bounds)
    sides = [[] for _ in range(5)]  # (value, weight) of every vertex on each side
    for p, w in hull:
        q = [p[i] - w * o[i] for i in range(3)]
        x, y, z = (sum(r[i][j] * q[i] for i in range(3)) for j in range(3))  # R^T q
        depth = -z
        for side, v in zip(sides, (x - x_lo * depth, x_hi * depth - x, y - y_lo * depth,
                                   y_hi * depth - y, depth)):  # fmt: skip
            side.append((v, w))
    for side in sides:  # this side leaves the hull out: points below, directions not above
        if all((v < 0) if w > 0 else (v <= 0) for v, w in side):
            return False
    return True


def seen_cells(res, aabb, c2w, bounds, *, contract=0.0, ndc=None, chunk=None):
    """Twin of :func:`warpnerf.occupancy.seen_cells` (``chunk`` is ignored)."""
    box = [float(v) for v in torch.as_tensor(aabb, dtype=torch.float32).reshape(-1)]
    c2w = c2w.detach().double().cpu().tolist()
    bounds = bounds.detach().double().cpu().tolist()
    out = torch.zeros(res**3, dtype=torch.bool)
    for cell in range(res**3):
        ijk = (cell // (res * res), (cell // res) % res, cell % res)
        size = [box[k + 3] - box[k] for k in range(3)]
        lo = [box[k] + size[k] * (ijk[k] / res) for k in range(3)]
        hi = [
            box[k + 3] if ijk[k] + 1 == res else box[k] + size[k] * ((ijk[k] + 1) / res)
            for k in range(3)
        ]
        hull = _hull(lo, hi, any(v in (0, res - 1) for v in ijk), contract, ndc)
        out[cell] = hull is None or any(_camera_sees(hull, m, b) for m, b in zip(c2w, bounds))
    return out
