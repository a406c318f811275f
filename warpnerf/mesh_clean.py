"""Cleaning a mesh: merging duplicate vertices, connected components and dropping the small
ones, culling the faces no training camera sees or no training ray weighs, the mesh a run
delivers (:func:`surface_mesh`) and decimation."""

from __future__ import annotations

import math

import numpy as np
import torch

__all__ = [
    "merge_vertices",
    "face_components",
    "face_areas",
    "clean_mesh",
    "seen_faces",
    "cull_unseen",
    "cull_unweighted",
    "surface_mesh",
    "DEFAULT_CLEAN",
    "decimate_mesh",
]


def _polydata(vertices, faces):
    """A triangle-only pyvista PolyData of (vertices [V, 3], faces [F, 3])."""
    import pyvista as pv

    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    return pv.PolyData.from_regular_faces(v, f)


def _arrays(mesh):
    """(vertices float32 [V, 3], faces int32 [F, 3]) of a PolyData's triangles (its lines and
    vertices, e.g. degenerate triangles that ``clean`` turned into lines, are dropped)."""
    if mesh.n_cells == 0 or mesh.n_faces == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32)
    v = np.asarray(mesh.points, dtype=np.float32)
    return v, np.asarray(mesh.regular_faces, dtype=np.int32)


def merge_vertices(vertices, faces):
    """The mesh with coincident vertices merged (marching cubes may emit a vertex per triangle:
    triangles meeting at a position then share its vertex), degenerate triangles and unused
    vertices dropped: (vertices float32 [V', 3], faces int64 [F', 3])."""
    v = np.asarray(vertices, dtype=np.float32).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(f) == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64)
    uniq, inv = np.unique(v, axis=0, return_inverse=True)
    f = inv.reshape(-1)[f]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    return _compact(uniq, f)


def _compact(v, f):
    """(v, f) without the vertices no face uses (faces renumbered)."""
    used = np.zeros(len(v), bool)
    used[f.ravel()] = True
    remap = np.cumsum(used) - 1
    return v[used], remap[f].astype(np.int64)


MAX_LABEL_ROUNDS = 10_000  # face_components: a bound that a correct run never nears


def face_components(faces, n_vertices: int) -> tuple:
    """The connected components of a triangle mesh (faces sharing a vertex are connected):
    (label per face int64 [F] in 0..k-1, k). Min-label propagation over the faces with pointer
    jumping, in torch (no VTK): each round every vertex, and the root its label points to, takes
    the least label of the faces it is on (hooking roots, as Shiloach-Vishkin's algorithm does,
    so the rounds grow with the logarithm of the mesh's size, not its length), then labels follow
    their own labels to a fixed point."""
    f = torch.as_tensor(np.asarray(faces, dtype=np.int64).reshape(-1, 3))
    if len(f) == 0:
        return np.zeros(0, np.int64), 0
    lab = torch.arange(int(n_vertices), dtype=torch.int64)
    for _ in range(MAX_LABEL_ROUNDS):
        m = lab[f].amin(1)
        new = lab.clone()
        for k in range(3):  # each face's least label to its vertices and to their labels' roots
            new.scatter_reduce_(0, f[:, k], m, reduce="amin")
            new.scatter_reduce_(0, lab[f[:, k]], m, reduce="amin")
        while True:  # pointer jumping: a label's label, to its root
            nxt = new[new]
            if torch.equal(nxt, new):
                break
            new = nxt
        if torch.equal(new, lab):
            break
        lab = new
    else:  # (hooking roots keeps the rounds logarithmic; a partition cut short would be wrong)
        raise RuntimeError(f"connected components did not settle in {MAX_LABEL_ROUNDS} rounds")
    uniq, per_face = torch.unique(lab[f[:, 0]], return_inverse=True)
    return per_face.numpy(), int(len(uniq))


def face_areas(vertices, faces) -> np.ndarray:
    """Area of each triangle [F] (float64)."""
    t = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64)]
    return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)


def clean_mesh(vertices: np.ndarray, faces: np.ndarray, min_fraction: float = 0.01):
    """Removes floating pieces: the connected components whose surface area is below
    ``min_fraction`` of the whole mesh's (the largest component is always kept).

    Coincident points are merged first (:func:`merge_vertices`), so that connectivity follows
    the surface; degenerate triangles and unused vertices go too. numpy and torch only
    (:func:`face_components`): it runs wherever training runs, without VTK.

    Args:
        vertices: [V, 3] positions.
        faces: [F, 3] vertex indices of triangles.
        min_fraction: in [0, 1); 0 keeps every component (only merging points).

    Returns:
        (vertices float32 [V', 3], faces int32 [F', 3], info) with info = {"faces_before",
        "faces_after", "components", "components_removed", "area_removed_fraction"}.
    """
    min_fraction = float(min_fraction)
    if not 0.0 <= min_fraction < 1.0:
        raise ValueError(f"min_fraction must be in [0, 1), got {min_fraction}")
    info = {"faces_before": int(len(faces)), "faces_after": 0, "components": 0,
            "components_removed": 0, "area_removed_fraction": 0.0}  # fmt: skip
    v, f = merge_vertices(vertices, faces)
    if len(f) == 0:
        return v, f.astype(np.int32), info
    region, k = face_components(f, len(v))
    area = np.bincount(region, weights=face_areas(v, f), minlength=k)
    keep = area >= min_fraction * area.sum()
    keep[np.argmax(area)] = True
    v, f = _compact(v, f[keep[region]])
    total = float(area.sum())
    removed = float(area[~keep].sum() / total) if total > 0 else 0.0
    info.update(faces_after=int(len(f)), components=int(k),
                components_removed=int((~keep).sum()), area_removed_fraction=removed)  # fmt: skip
    return v, f.astype(np.int32), info


CULL_MAX_SIDE = 512  # visibility z-buffers: the longest side, pixels (a camera's, scaled down)


CULL_TOLERANCE = 0.01  # a face is seen when no splat is nearer than (1 - this) x its depth


def seen_faces(vertices, faces, c2w, intrinsics, width: int, height: int, *,
               max_side: int = CULL_MAX_SIDE, tolerance: float = CULL_TOLERANCE,
               device="cpu") -> np.ndarray:  # fmt: skip
    """Which faces some camera sees: bool [F]. A face is seen by a camera when its centroid
    lies in front of it, inside its image, and is not hidden: each camera's depth buffer holds,
    per pixel, the nearest splatted point of the mesh (each face's centroid and vertices), at
    most ``max_side`` pixels on the longest side and no finer than the mesh's median edge at its
    median depth (so a surface's splats, vertices and centroids, leave no holes; a pixel none
    reached takes a neighbour's depth); a face counts as hidden where that buffer is nearer
    than its centroid by more than ``tolerance`` of its depth plus two pixels' width at that
    depth. Cameras:
    ``c2w`` [N, 4, 4] camera-to-world (OpenGL: x right, y up, looking down -z, the library's
    rays), ``intrinsics`` [N, 4] (fx, fy, cx, cy) of ``width`` x ``height`` images. A dense
    mesh (marching cubes) splats densely, so points behind a surface are hidden by it; what
    no training camera sees (the inside of an object, space under a floor) is not kept."""
    v = torch.as_tensor(np.asarray(vertices, dtype=np.float32), device=device)
    f = torch.as_tensor(np.asarray(faces, dtype=np.int64), device=device)
    c2w = torch.as_tensor(c2w, dtype=torch.float32, device=device).reshape(-1, 4, 4)
    k = torch.as_tensor(intrinsics, dtype=torch.float32, device=device).reshape(-1, 4)
    seen = torch.zeros(len(f), dtype=torch.bool, device=device)
    if len(f) == 0:
        return seen.cpu().numpy()
    tri = v[f]
    cent = tri.mean(1)
    pts = torch.cat([cent, v])  # what each camera's depth buffer is made of
    nc = len(cent)
    edge = (tri - tri.roll(1, 1)).norm(dim=-1).median().clamp_min(1e-9)  # the mesh's spacing
    for i in range(len(c2w)):
        r, t = c2w[i, :3, :3], c2w[i, :3, 3]
        q = (pts - t) @ r  # world -> camera (r orthonormal: r^T (p - t))
        z = -q[:, 2]  # depth along the viewing axis
        front = (z > 1e-6) & torch.isfinite(q).all(1)
        if not front[:nc].any():
            continue
        zs = z.clamp_min(1e-6)
        # the buffer's pixels no finer than the mesh's spacing at its median depth, so that the
        # splats of a surface leave no holes that would show what lies behind it
        zmed = z[:nc][front[:nc]].median()
        scale = min(1.0, max_side / max(int(width), int(height)), float(zmed / (k[i, 0] * edge)))
        w, h = max(1, math.ceil(width * scale)), max(1, math.ceil(height * scale))
        px = (k[i, 0] * q[:, 0] / zs + k[i, 2]) * (w / width)
        py = (k[i, 3] - k[i, 1] * q[:, 1] / zs) * (h / height)
        ok = front & (px >= 0) & (px < w) & (py >= 0) & (py < h)  # (False for NaN)
        ok &= torch.isfinite(z)
        pix = torch.where(ok, py.floor().clamp(0, h - 1) * w + px.floor().clamp(0, w - 1), 0)
        pix = pix.long()
        zbuf = torch.full((w * h,), float("inf"), device=device)
        zbuf.scatter_reduce_(0, pix[ok], z[ok], reduce="amin")
        # a pixel no splat reached takes its nearest neighbour's depth (holes between splats)
        grid = zbuf.reshape(1, 1, h, w)
        near = -torch.nn.functional.max_pool2d(-grid, 3, stride=1, padding=1)
        zbuf = torch.where(torch.isinf(grid), near, grid).reshape(-1)
        # hidden: something nearer by more than the tolerance and two pixels' width (a sloped
        # surface's own depth changes across a pixel)
        zc = z[:nc]
        allow = tolerance * zc + 2.0 * zc / (k[i, 0] * (w / width))
        seen |= ok[:nc] & (zbuf[pix[:nc]] >= zc - allow)
    return seen.cpu().numpy()


def cull_unseen(vertices, faces, c2w, intrinsics, width: int, height: int, **kw):
    """The mesh without the faces no camera sees (:func:`seen_faces`), unused vertices dropped:
    (vertices float32, faces int32, info) with info = {"faces_unseen", "area_unseen_fraction"}."""
    v, f = merge_vertices(vertices, faces)
    if len(f) == 0:
        return _keep_faces(v, f, np.zeros(0, bool), "unseen")
    return _keep_faces(v, f, seen_faces(v, f, c2w, intrinsics, width, height, **kw), "unseen")


def _keep_faces(v, f, keep, what: str):
    """(vertices float32, faces int32, info) of the faces ``keep`` [F] bool of a merged mesh,
    unused vertices dropped; info: the faces dropped (``faces_<what>``) and their fraction of
    the area (``area_<what>_fraction``)."""
    if len(f) == 0:  # (nothing to drop: the vertices as they are)
        return v, f.astype(np.int32), {f"faces_{what}": 0, f"area_{what}_fraction": 0.0}
    area = face_areas(v, f)
    total = float(area.sum())
    info = {
        f"faces_{what}": int((~keep).sum()),
        f"area_{what}_fraction": float(area[~keep].sum() / total) if total > 0 else 0.0,
    }
    v, f = _compact(v, f[keep])
    return v, f.astype(np.int32), info


def cull_unweighted(vertices, faces, grid, lower, upper):
    """The mesh without the faces whose centroid lies in an unmarked cell of ``grid`` (bool
    [Rx, Ry, Rz], numpy or torch, indexed x, y, z; its cells split the box [lower, upper] evenly,
    e.g. a run's visibility grid: the cells where its training rays put weight,
    :func:`warpnerf.train.visibility.training_weight_grid`); a centroid outside the box counts
    as unmarked. Coincident vertices are merged first (as :func:`cull_unseen` does) and unused
    ones dropped: (vertices float32, faces int32, info) with info = {"faces_unweighted",
    "area_unweighted_fraction"}."""
    g = torch.as_tensor(grid).to("cpu", torch.bool)
    if g.dim() != 3 or min(g.shape) < 1:
        raise ValueError(f"grid must be a 3-d bool array, got shape {tuple(g.shape)}")
    lo = np.asarray(lower, dtype=np.float64).reshape(3)
    hi = np.asarray(upper, dtype=np.float64).reshape(3)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all() and (hi > lo).all()):
        raise ValueError(f"need finite lower < upper, got {lo.tolist()} .. {hi.tolist()}")
    v, f = merge_vertices(vertices, faces)
    if len(f) == 0:
        return _keep_faces(v, f, np.zeros(0, bool), "unweighted")
    cent = v.astype(np.float64)[f].mean(1)
    res = np.asarray(g.shape)
    u = (cent - lo) / (hi - lo)  # [0, 1] inside the box
    inside = ((u >= 0) & (u <= 1)).all(1)  # (False for NaN)
    idx = np.clip(np.floor(np.where(inside[:, None], u, 0.0) * res), 0, res - 1).astype(np.int64)
    keep = inside & g.numpy()[idx[:, 0], idx[:, 1], idx[:, 2]]
    return _keep_faces(v, f, keep, "unweighted")


DEFAULT_CLEAN = 0.01  # a run's mesh: components under this fraction of the area are dropped


def surface_mesh(vertices, faces, cameras=None, min_fraction: float = DEFAULT_CLEAN, device="cpu",
                 weight_grid=None):  # fmt: skip
    """A run's mesh as `warpnerf mesh` delivers it by default: the faces where no training ray
    puts weight culled (:func:`cull_unweighted`; ``weight_grid``: an object with ``grid``,
    ``lower``, ``upper``, e.g. :func:`warpnerf.train.visibility.training_weight_grid`'s; None:
    not culled so), then of the rest the faces no camera of ``cameras`` sees
    (:func:`cull_unseen`; ``cameras`` with ``c2w``, ``intrinsics``, ``width``, ``height``, e.g.
    the training split; None: not culled so), then the components under ``min_fraction`` of
    the area dropped (:func:`clean_mesh`).

    Both culls apply, in this order: a face must lie where training rays put weight *and* be
    seen by a camera. The weight grid is the stricter rule (a surface a camera could see but
    that the rendering never stops at goes: level-set pieces behind haze the rays spend their
    transmittance on, surfaces no ray reaches), but its cells are coarser than the mesh (and
    dilated by one), so it keeps faces just behind a visible surface (inside a thin wall),
    which the cameras' depth buffers, at the mesh's own spacing, remove. Weights first: an
    unweighted piece in front then no longer hides what the rays do reach behind it.

    Returns (vertices, faces, info): ``culled_by_weights`` and, with a grid,
    ``faces_unweighted`` and ``area_unweighted_fraction``; ``culled_by_views`` and, with
    cameras, ``faces_unseen`` and ``area_unseen_fraction``; ``clean`` and
    :func:`clean_mesh`'s figures."""
    info = {"culled_by_weights": weight_grid is not None, "culled_by_views": cameras is not None}
    if weight_grid is not None:
        w = weight_grid
        vertices, faces, cull = cull_unweighted(vertices, faces, w.grid, w.lower, w.upper)
        info.update(cull)
    if cameras is not None:
        c = cameras
        vertices, faces, cull = cull_unseen(vertices, faces, c.c2w, c.intrinsics, c.width,
                                            c.height, device=device)  # fmt: skip
        info.update(cull)
    if len(faces) == 0:
        return vertices, faces, info
    vertices, faces, c = clean_mesh(vertices, faces, min_fraction)
    info.update(clean=min_fraction, components=c["components"],
                components_removed=c["components_removed"],
                area_removed_fraction=c["area_removed_fraction"])  # fmt: skip
    return vertices, faces, info


def decimate_mesh(vertices: np.ndarray, faces: np.ndarray, reduction: float):
    """Quadric-error decimation (pyvista's ``decimate``, VTK's vtkQuadricDecimation, with volume
    preservation) removing about ``reduction`` of the triangles; coincident points are merged
    first, so a closed manifold input stays closed and manifold.

    Args:
        vertices: [V, 3] positions.
        faces: [F, 3] vertex indices of triangles.
        reduction: target fraction of triangles removed, in (0, 1): 0.9 keeps ~10 %.

    Returns:
        (vertices float32 [V', 3], faces int32 [F', 3]).
    """
    reduction = float(reduction)
    if not 0.0 < reduction < 1.0:
        raise ValueError(f"reduction must be in (0, 1), got {reduction}")
    if len(faces) == 0:
        return _arrays(_polydata(vertices, faces))
    mesh = _polydata(*merge_vertices(vertices, faces)).decimate(reduction, volume_preservation=True)
    return _arrays(_polydata(*_arrays(mesh)).clean(tolerance=0.0))
