"""Mesh extraction (Warp's marching cubes, CPU and CUDA), PLY output and pyvista screenshots.

``extract_mesh(field_fn, lower, upper, resolution, level)`` samples ``field_fn(points [m, 3]) ->
values [m]`` on a regular grid of ``resolution^3`` nodes spanning [lower, upper] (world
coordinates), in chunks, and runs marching cubes at ``level``: 0 for signed distances, a density
threshold for NeRFs (by default chosen from the grid by :func:`density_level`). Vertices come
back in world coordinates.
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
import warnings
from pathlib import Path

import numpy as np
import torch

from .io import atomic_path

__all__ = [
    "extract_mesh",
    "density_level",
    "level_hint",
    "write_ply",
    "read_ply",
    "vertex_colors",
    "screenshot",
    "sample_surface",
    "clean_mesh",
    "merge_vertices",
    "face_components",
    "face_areas",
    "seen_faces",
    "cull_unseen",
    "cull_unweighted",
    "surface_mesh",
    "DEFAULT_CLEAN",
    "decimate_mesh",
]


@torch.no_grad()
def extract_mesh(field_fn, lower, upper, resolution: int, level: float = 0.0, device="cpu",
                 chunk: int = 1 << 18, return_values: bool = False):  # fmt: skip
    """(vertices [V, 3] float32 numpy, faces [F, 3] int32 numpy) of the level set; with
    ``return_values`` also the field's values on the grid (float32 tensor [resolution^3] on
    ``device``), e.g. for :func:`level_hint` when there is no surface. ``level``: a number, or
    a callable given those values that returns the level to march (chosen from the grid, e.g.
    with :func:`density_level`)."""
    import warp as wp

    from .ops.bridge import load_warp

    if resolution < 2:
        raise ValueError(f"resolution must be >= 2, got {resolution}")
    lo = torch.as_tensor(lower, dtype=torch.float32).reshape(3)
    hi = torch.as_tensor(upper, dtype=torch.float32).reshape(3)
    if not bool((hi > lo).all()):
        raise ValueError("upper must exceed lower on every axis")
    dev = torch.device(device)
    axes = [torch.linspace(float(lo[i]), float(hi[i]), resolution, device=dev) for i in range(3)]
    n = resolution**3
    vals = torch.empty(n, device=dev)
    for s in range(0, n, chunk):  # grid points made per chunk: memory ~ chunk, not resolution^3
        idx = torch.arange(s, min(s + chunk, n), device=dev)
        ix, iy, iz = (
            idx // (resolution * resolution),
            (idx // resolution) % resolution,
            idx % resolution,
        )
        pts = torch.stack([axes[0][ix], axes[1][iy], axes[2][iz]], -1)
        vals[s : s + len(idx)] = field_fn(pts).float().reshape(-1)
    if not bool(torch.isfinite(vals).all()):
        raise ValueError("the field has NaN/Inf values on the grid")
    if callable(level):
        level = level(vals)
    field = vals.reshape(resolution, resolution, resolution).contiguous()
    load_warp()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        verts, tris = wp.MarchingCubes.extract(
            wp.from_torch(field, dtype=wp.float32),
            float(level),
            lower=wp.vec3(*lo.tolist()),
            upper=wp.vec3(*hi.tolist()),
        )
    v = verts.numpy().reshape(-1, 3).astype(np.float32)
    f = tris.numpy().reshape(-1, 3).astype(np.int32)
    return (v, f, vals) if return_values else (v, f)


LEVEL_OPACITY = 0.5  # density_level: where a ray is this opaque (its median depth)
LEVEL_REACHED = 0.9  # density_level: the share of the opaque rays whose peak density it keeps
LEVEL_DIRECTIONS = 32  # density_level: directions of the parallel rays (a Fibonacci sphere)
LEVEL_RAYS = 32  # density_level: rays per side of each direction's square bundle
LEVEL_SAMPLES = 256  # density_level: samples per ray, over the box's diagonal


def _quantile(x: torch.Tensor, q: float) -> float:
    """The ``q`` quantile of a 1-D tensor, the lower of two values (kthvalue: no size limit)."""
    return float(x.kthvalue(max(1, math.ceil(q * len(x))))[0])


def _fibonacci_directions(n: int) -> torch.Tensor:
    """[n, 3] unit vectors spread evenly over the sphere (none along an axis for n > 2)."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = (1.0 - z * z).clamp_min(0).sqrt()
    th = math.pi * (3.0 - math.sqrt(5.0)) * i
    return torch.stack([r * th.cos(), r * th.sin(), z], -1).float()


@torch.no_grad()
def density_level(densities, resolution: int, lower, upper) -> tuple:
    """The density level that meshes a NeRF where it renders its surface, without holes where
    it renders opaque: (level, why), ``why`` a phrase saying how it was found.

    The grid's densities are composited along parallel rays through the box, as a renderer
    does: :data:`LEVEL_DIRECTIONS` directions spread over the sphere (not along the grid's axes,
    whose rays would graze the faces of axis-aligned objects), a square bundle of
    :data:`LEVEL_RAYS` x :data:`LEVEL_RAYS` rays each, :data:`LEVEL_SAMPLES` samples over the
    box's diagonal read by trilinear interpolation (no new evaluation of the field), optical
    depth by the trapezoidal rule. Of the rays that reach opacity :data:`LEVEL_OPACITY`
    (optical depth ln 2, the ray's median depth: where rendering puts the surface it sees), two
    figures: ``a``, the median density where they reach it (interpolated between samples), and
    ``b``, the largest density that :data:`LEVEL_REACHED` (90 %) of them reach somewhere (the
    10th percentile of their peaks). The level is min(a, b): the depth the run renders, lowered
    where that would let more than a tenth of the rays it finds opaque through the mesh
    (holes). No ray that opaque (a faint field): half the largest density.

    Measured on the built-in scene (the mesh culled and cleaned as `warpnerf mesh` delivers it;
    Chamfer: the mean of the mean |true SDF| at the vertices and the mean distance from the
    analytic surface to the mesh; 128^3 grid): the `--preset cpu` hash run (densities peak at
    22, 7.6 median on the true surface) at levels 4 .. 7 had Chamfer 0.042 .. 0.047 and the
    95th percentile of the surface's distance to the mesh 0.06 at 4, 0.11 at 5, 0.17 at 6, 0.27
    at the former fixed 10 (Chamfer 0.063: a holed sphere, the box in pieces); the mlp run
    (peak 5): Chamfer 0.048 and 0.07 at 2.45, 0.13 at 2.62, 0.56 at 3, no surface at 10. This
    rule gives a = 6.9, b = 4.8 (hash; 7.0 and 4.9 on the default 256^3 grid, whose mesh has
    mean |SDF| 0.048, completeness 0.036, 95th percentile 0.087, 2 pieces) and a = 2.67,
    b = 2.50 (mlp); on the scene's own density (Laplace, beta 0.02: 25 on the surface; 64^3)
    a = 20.5, b = 12.4, mean |SDF| 0.017 at the vertices. Rejected: ln 2 / march step (opacity
    0.5 over one step: 51 for the hash run, no surface), half the largest density (11: holes),
    and rays along the grid's axes (b = 5.0 on the scene's own density: rays grazing the box's
    faces).

    Args:
        densities: the densities on the grid, [resolution^3] (x slowest, as
            :func:`extract_mesh` samples them), any device.
        resolution: grid nodes per axis.
        lower, upper: the grid's corners.
    """
    import torch.nn.functional as F

    r = int(resolution)
    d = torch.as_tensor(densities).detach().reshape(r, r, r).float()
    dev = d.device
    lo = torch.as_tensor(lower, dtype=torch.float32).reshape(3).to(dev)
    hi = torch.as_tensor(upper, dtype=torch.float32).reshape(3).to(dev)
    center, size = (lo + hi) / 2, hi - lo
    diag = float(size.norm())
    ts = torch.linspace(-diag / 2, diag / 2, LEVEL_SAMPLES, device=dev)
    h = diag / (LEVEL_SAMPLES - 1)
    side = torch.linspace(-diag / 2, diag / 2, LEVEL_RAYS, device=dev)
    across = torch.stack(torch.meshgrid(side, side, indexing="ij"), -1).reshape(-1, 2)
    grid = d[None, None]  # grid_sample's [N, C, D, H, W]: D = x, H = y, W = z
    target = -math.log(1.0 - LEVEL_OPACITY)
    at, peak = [], []  # per opaque ray: the density where it reaches the opacity, its peak
    for v in _fibonacci_directions(LEVEL_DIRECTIONS).to(dev):
        helper = torch.tensor([1.0, 0.0, 0.0] if abs(float(v[0])) < 0.9 else [0.0, 1.0, 0.0],
                              device=dev)  # fmt: skip
        u = F.normalize(torch.linalg.cross(v, helper), dim=0)
        w = torch.linalg.cross(v, u)
        o = center + across[:, :1] * u + across[:, 1:] * w  # [R, 3]
        p = o[:, None, :] + ts[None, :, None] * v  # [R, S, 3]
        q = 2.0 * (p - lo) / size - 1.0  # [-1, 1] over the box
        sig = F.grid_sample(grid, q.flip(-1)[None, None], align_corners=True)[0, 0, 0]  # [R, S]
        c = torch.cumsum(sig, -1)
        tau = h * (c - 0.5 * (sig[:, :1] + sig))  # trapezoid from the first sample
        hit = tau[:, -1] >= target
        if not bool(hit.any()):
            continue
        sig, tau = sig[hit], tau[hit]
        i = (tau >= target).int().argmax(-1, keepdim=True).clamp_min(1)
        t0, t1 = tau.gather(1, i - 1), tau.gather(1, i)
        s0, s1 = sig.gather(1, i - 1), sig.gather(1, i)
        f = ((target - t0) / (t1 - t0).clamp_min(1e-30)).clamp(0, 1)
        at.append((s0 + f * (s1 - s0)).reshape(-1))
        peak.append(sig.amax(-1))
    if at:
        a = _quantile(torch.cat(at), 0.5)
        b = _quantile(torch.cat(peak), 1.0 - LEVEL_REACHED)
        n = sum(len(x) for x in at)
        if min(a, b) > 0:
            why = (f"min({a:.4g}, {b:.4g}): the median density where rays through the grid "
                   f"reach opacity {LEVEL_OPACITY:g} (the depth the run renders), and the peak "
                   f"density {LEVEL_REACHED:.0%} of those {n} rays reach (no holes)")  # fmt: skip
            return min(a, b), why
    top = float(d.max())
    return top / 2, (f"half the largest density (no ray through the grid reaches opacity "
                     f"{LEVEL_OPACITY:g})")  # fmt: skip


def level_hint(values, density: bool = False) -> str:
    """Why a level set is empty, for an error line: the range of the grid's ``values`` (the
    densities themselves when ``density``) and, for a density, a level to try.

    The suggested density level is half the largest density on the grid: a VolSDF-style density
    (the built-in scene's, sigma = Psi_beta(-sdf) / beta) is half its interior value on the
    surface. Measured on built-in-scene runs trained with ``--preset cpu`` (peak densities 5.0
    (mlp) and 20 (hash); 64^3 grid), the mean |true SDF| at the vertices was 0.051 and 0.037,
    the best or within 0.001 of the best of the rules compared (99th and 95th percentiles, a
    quarter of the peak, geometric means of the peak and the minimum or median: 0.036 to 0.22).
    When half the peak is not above the smallest density (a field nearly constant inside the
    box), the middle of the range is suggested instead.

    Args:
        values: the field on the grid (any shape), as returned by ``extract_mesh(...,
            return_values=True)``.
        density: ``values`` are densities (a NeRF): suggest a level.
    """
    v = torch.as_tensor(values).detach().reshape(-1).float().cpu().numpy()
    lo, hi = float(v.min()), float(v.max())
    p50, p99 = (float(x) for x in np.percentile(v, [50, 99]))
    what = "densities" if density else "values"
    msg = f"the {what} on the grid range from {lo:.4g} to {hi:.4g} (median {p50:.4g}, 99th "
    msg += f"percentile {p99:.4g})"
    if not density:
        return msg
    if hi <= lo:
        return msg + "; the density is constant inside the box: try a larger --bounds"
    half = hi / 2
    if half > lo:
        return msg + f"; try --level {half:.3g} (half the largest density)"
    return msg + f"; try --level {(lo + hi) / 2:.3g} (the middle of the range)"


def write_ply(path, vertices: np.ndarray, faces: np.ndarray, replace_foreign: bool = False,
              colors=None, normals=None) -> None:  # fmt: skip
    """Binary little-endian PLY (float32 xyz, optional float32 nx/ny/nz and uchar red/green/blue
    per vertex, int32 triangle indices; no faces for a point cloud), written atomically with
    plyfile."""
    import plyfile

    v = np.asarray(vertices, dtype="<f4").reshape(-1, 3)
    f = np.asarray(faces, dtype="<i4").reshape(-1, 3)
    row = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if normals is not None:
        nr = np.asarray(normals)
        if nr.shape != (len(v), 3):
            raise ValueError(f"normals must be [{len(v)}, 3], got {nr.shape}")
        row += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if colors is not None:
        c = np.asarray(colors)
        if c.shape != (len(v), 3) or c.dtype != np.uint8:
            raise ValueError(f"colors must be uint8 [{len(v)}, 3], got {c.dtype} {c.shape}")
        row += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    rows = np.empty(len(v), dtype=row)
    rows["x"], rows["y"], rows["z"] = v.T
    if normals is not None:
        rows["nx"], rows["ny"], rows["nz"] = np.asarray(nr, dtype="<f4").T
    if colors is not None:
        rows["red"], rows["green"], rows["blue"] = c.T
    tris = np.empty(len(f), dtype=[("vertex_indices", "<i4", (3,))])
    tris["vertex_indices"] = f
    data = plyfile.PlyData([
        plyfile.PlyElement.describe(rows, "vertex"),
        plyfile.PlyElement.describe(tris, "face", len_types={"vertex_indices": "u1"}),
    ], byte_order="<")  # fmt: skip
    with atomic_path(path, replace_foreign) as tmp, open(tmp, "wb") as fh:
        data.write(fh)


MAX_PLY_BYTES = 1 << 32  # 4 GiB: larger mesh files are refused before reading


def read_ply(path, colors: bool = False, normals: bool = False):
    """(vertices [V, 3] float32, faces [F, 3] int32) of a PLY mesh or point cloud (plyfile:
    ascii or binary; faces must be triangles), plus the vertex colours uint8 [V, 3] when
    ``colors`` and the normals [V, 3] when ``normals`` (None when the file has none).

    The file may be untrusted (a run folder's mesh): the header's counts are checked against the
    file's size before plyfile allocates anything, and an unreadable file, non-triangle faces,
    face indices outside the vertices or non-finite coordinates are a
    :class:`~warpnerf.errors.UserError` naming the file."""
    import plyfile

    from .errors import UserError

    path = Path(path)

    def bad(msg):
        return UserError(f"{path}: unreadable PLY file ({msg})")

    try:
        size = path.stat().st_size
        if size > MAX_PLY_BYTES:
            raise bad(f"{size} bytes, more than the {MAX_PLY_BYTES} accepted")
        with open(path, "rb") as fh:
            head = fh.read(_PLY_MAX_HEADER + 64)
    except OSError as e:
        raise bad(f"cannot read: {e.strerror or e}") from None
    fmt, elements, start = _ply_header(head, bad)
    counts = {name: n for name, n, _ in elements}
    # the fewest bytes the promised rows take: binary xyz floats and 1 + 3 x 4-byte triangles;
    # ascii "0 0 0\n" and "3 0 0 0\n"; any other element at least a byte a row
    per = (6, 8) if fmt == "ascii" else (12, 13)
    least = per[0] * counts.get("vertex", 0) + per[1] * counts.get("face", 0)
    least += sum(n for name, n, _ in elements if name not in ("vertex", "face"))
    if size - start < least:
        raise bad(f"the header promises more elements than its {size} bytes hold")
    try:
        with open(path, "rb") as fh:
            ply = plyfile.PlyData.read(fh, known_list_len={"face": {"vertex_indices": 3}})
        vert = ply["vertex"].data
        names = vert.dtype.names or ()
        pts = np.stack([vert[k] for k in ("x", "y", "z")], -1).astype(np.float32)
        if "face" in ply and len(ply["face"].data):
            lists = ply["face"].data[ply["face"].data.dtype.names[0]]
            tri = np.stack([np.asarray(t) for t in lists]).astype(np.int64)
        else:
            tri = np.zeros((0, 3), np.int64)
    except UserError:
        raise
    except (plyfile.PlyParseError, KeyError, ValueError, IndexError, TypeError, OSError,
            MemoryError) as e:  # fmt: skip
        raise bad(str(e)[:200] or type(e).__name__) from None
    if tri.ndim != 2 or tri.shape[1] != 3:
        raise bad("faces must be triangles")
    if len(tri) and (tri.min() < 0 or tri.max() >= len(pts)):
        raise bad(f"face indices outside the {len(pts)} vertices")
    if not np.isfinite(pts).all():
        raise bad("non-finite vertex coordinates")
    out = (pts, tri.astype(np.int32))
    if colors:
        rgb = {"red", "green", "blue"} <= set(names)
        out += (np.stack([vert[k] for k in ("red", "green", "blue")], -1).astype(np.uint8)
                if rgb else None,)  # fmt: skip
    if normals:
        nrm = {"nx", "ny", "nz"} <= set(names)
        out += (np.stack([vert[k] for k in ("nx", "ny", "nz")], -1).astype(np.float32)
                if nrm else None,)  # fmt: skip
    return out


def vertex_colors(
    field, fn, vertices: np.ndarray, device, chunk: int = 1 << 16, h: float = 1e-3
) -> np.ndarray:
    """Bakes a radiance field's colour into mesh vertices, uint8 [V, 3]: at each vertex x the
    outward normal n is the normalised central-difference gradient of the level-set function
    ``fn`` (an SDF, or minus a density: both grow outwards), and the colour is the field's
    ``forward(x, -n)`` colour, i.e. seen by a camera looking straight at the surface."""
    import torch

    out = []
    e = torch.eye(3, device=device)
    with torch.no_grad():
        for s in range(0, len(vertices), chunk):
            x = torch.as_tensor(vertices[s : s + chunk], dtype=torch.float32, device=device)
            pts = torch.cat([x + h * e[i] for i in range(3)] + [x - h * e[i] for i in range(3)])
            d = fn(pts).float().reshape(6, -1)
            g = ((d[:3] - d[3:]) / (2 * h)).T
            n = torch.nn.functional.normalize(torch.nan_to_num(g), dim=-1)
            n = torch.where(
                n.norm(dim=-1, keepdim=True) > 0, n, torch.tensor([0.0, 0.0, 1.0], device=device)
            )
            _, rgb = field(x, -n)
            out.append((rgb.float().clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu())
    return torch.cat(out).numpy() if out else np.zeros((0, 3), np.uint8)


def sample_surface(vertices, faces, n: int, seed: int = 0) -> np.ndarray:
    """n points uniformly on the triangle mesh (area-weighted), [n, 3]."""
    rng = np.random.default_rng(seed)
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    idx = rng.choice(len(faces), n, p=area / area.sum())
    u, w = rng.random(n), rng.random(n)
    flip = u + w > 1
    u[flip], w[flip] = 1 - u[flip], 1 - w[flip]
    t = tri[idx]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + w[:, None] * (t[:, 2] - t[:, 0])


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
        return v, f.astype(np.int32), {"faces_unseen": 0, "area_unseen_fraction": 0.0}
    seen = seen_faces(v, f, c2w, intrinsics, width, height, **kw)
    area = face_areas(v, f)
    total = float(area.sum())
    info = {
        "faces_unseen": int((~seen).sum()),
        "area_unseen_fraction": float(area[~seen].sum() / total) if total > 0 else 0.0,
    }
    v, f = _compact(v, f[seen])
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
        return v, f.astype(np.int32), {"faces_unweighted": 0, "area_unweighted_fraction": 0.0}
    cent = v.astype(np.float64)[f].mean(1)
    res = np.asarray(g.shape)
    u = (cent - lo) / (hi - lo)  # [0, 1] inside the box
    inside = ((u >= 0) & (u <= 1)).all(1)  # (False for NaN)
    idx = np.clip(np.floor(np.where(inside[:, None], u, 0.0) * res), 0, res - 1).astype(np.int64)
    keep = inside & g.numpy()[idx[:, 0], idx[:, 1], idx[:, 2]]
    area = face_areas(v, f)
    total = float(area.sum())
    info = {
        "faces_unweighted": int((~keep).sum()),
        "area_unweighted_fraction": float(area[~keep].sum() / total) if total > 0 else 0.0,
    }
    v, f = _compact(v, f[keep])
    return v, f.astype(np.int32), info


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


def screenshot(path, vertices, faces, size=(640, 480), color="#d8b25a", colors=None) -> None:
    """Offscreen pyvista render of the mesh (no window), written atomically; ``colors`` (uint8
    [V, 3]) paints the vertices instead of the flat ``color``."""
    import pyvista as pv

    pv.OFF_SCREEN = True
    cells = np.hstack([np.full((len(faces), 1), 3), faces]).astype(np.int64).ravel()
    mesh = pv.PolyData(np.asarray(vertices, dtype=np.float64), cells)
    with _headless_vtk():
        plotter = pv.Plotter(off_screen=True, window_size=list(size))
        if colors is not None:
            mesh.point_data["rgb"] = np.asarray(colors, dtype=np.uint8)
            plotter.add_mesh(mesh, scalars="rgb", rgb=True, smooth_shading=True)
        else:
            plotter.add_mesh(mesh, color=color, smooth_shading=True)
        plotter.set_background("white")
        plotter.camera_position = "iso"
        try:
            with atomic_path(path) as tmp:  # the temporary name keeps the .png suffix
                plotter.screenshot(str(tmp))
        finally:
            plotter.close()


@contextlib.contextmanager
def _headless_vtk():
    """On Linux without an X display, VTK's render window asks for EGL directly.

    VTK (9.4+) picks its OpenGL window at run time: X first, then EGL, then OSMesa, and it logs
    why it fell back ("vtkXOpenGLRenderWindow ... WARN| bad X server connection. DISPLAY=", with
    raw ANSI colour codes) to stderr on every headless screenshot. Without ``DISPLAY`` the X try
    cannot succeed, so ``VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow`` skips it; VTK still falls
    back to OSMesa (with its own messages) when EGL fails. A value the user set wins, and the
    variable is restored afterwards (VTK reads it when the render window is made)."""
    key = "VTK_DEFAULT_OPENGL_WINDOW"
    if not sys.platform.startswith("linux") or os.environ.get("DISPLAY") or key in os.environ:
        yield
        return
    os.environ[key] = "vtkEGLRenderWindow"
    try:
        yield
    finally:
        os.environ.pop(key, None)


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2",
              "int16": "i2", "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4",
              "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4", "double": "f8",
              "float64": "f8"}  # fmt: skip
_PLY_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
_PLY_MAX_HEADER = 1 << 20


def _ply_header(data: bytes, bad):
    """(format, elements [(name, count, [(prop, type or None for lists)])], body offset)."""
    if not (data.startswith(b"ply\n") or data.startswith(b"ply\r\n")):
        raise bad("it does not start with 'ply'")
    end = data.find(b"end_header", 0, _PLY_MAX_HEADER)
    nl = data.find(b"\n", end) if end >= 0 else -1
    if nl < 0 or data[end + len(b"end_header") : nl].strip():
        raise bad(f"no 'end_header' line in the first {_PLY_MAX_HEADER} bytes")
    try:
        head = data[:end].decode("ascii").splitlines()[1:]
    except UnicodeDecodeError:
        raise bad("the header is not ASCII text") from None
    fmt, elements = None, []
    for lineno, line in enumerate(head, 2):
        w = line.split()
        if not w or w[0] in ("comment", "obj_info"):
            continue
        if w[0] == "format" and len(w) == 3 and w[1] in _PLY_FORMATS and fmt is None:
            fmt = w[1]
        elif w[0] == "element" and len(w) == 3:
            if not (w[2].isdigit() and len(w[2]) < 19):
                raise bad(f"header line {lineno}: element count {w[2]!r} is not a count")
            elements.append((w[1], int(w[2]), []))
        elif w[0] == "property" and elements and len(w) == 3 and w[1] in _PLY_TYPES:
            elements[-1][2].append((w[2], _PLY_TYPES[w[1]]))
        elif (w[0] == "property" and elements and len(w) == 5 and w[1] == "list"
              and w[2] in _PLY_TYPES and w[3] in _PLY_TYPES):  # fmt: skip
            elements[-1][2].append((w[4], None))
        else:
            raise bad(f"header line {lineno} not understood: {line[:60]!r}")
    if fmt is None:
        raise bad("no 'format ascii|binary_little_endian|binary_big_endian 1.0' line")
    return fmt, elements, nl + 1


def read_ply_points(path):
    """(points [N, 3] float64, normals [N, 3] or None) of a PLY file's vertices (ascii, binary
    little- or big-endian; properties ``x, y, z`` and optionally ``nx, ny, nz``).

    The file is untrusted: a malformed header (no ``ply`` magic, unknown format, type or line,
    non-numeric or negative counts), a vertex count larger than the file holds (checked against
    its size before anything is allocated), list properties in the vertex element (or, in a
    binary file, before it), unparsable ASCII rows and non-finite coordinates or normals are a
    :class:`~warpnerf.errors.UserError` naming the file."""
    from pathlib import Path

    from .errors import UserError

    path = Path(path)

    def bad(msg):
        return UserError(f"{path}: unreadable PLY file ({msg})")

    try:
        with open(path, "rb") as fh:
            data = fh.read()
    except OSError as e:
        raise bad(f"cannot read: {e.strerror or e}") from None
    fmt, elements, start = _ply_header(data, bad)
    vi = next((i for i, e in enumerate(elements) if e[0] == "vertex"), None)
    if vi is None:
        raise bad("no 'element vertex' in the header")
    _, n, props = elements[vi]
    names = [p for p, _ in props]
    if not {"x", "y", "z"} <= set(names) or len(set(names)) != len(names):
        raise bad("the vertex element needs x, y, z properties, each once")
    if any(t is None for _, t in props):
        raise bad("list properties in the vertex element are not supported")
    if fmt == "ascii":
        lines = [ln for ln in data[start:].split(b"\n") if ln.strip()]
        skip = sum(c for _, c, _ in elements[:vi])  # one line per row of the earlier elements
        if skip + n > len(lines):
            raise bad(f"{n} vertices declared, but the file has {max(len(lines) - skip, 0)} rows")
        rows = lines[skip : skip + n]
        tokens = []
        for i, row in enumerate(rows):
            vals = row.split()
            if len(vals) != len(names):
                raise bad(f"vertex {i} has {len(vals)} values, expected {len(names)}")
            tokens += vals
        try:
            arr = np.array([float(t) for t in tokens], dtype=np.float64)
        except ValueError:
            raise bad("a vertex value is not a number") from None
        arr = arr.reshape(n, len(names))  # 0 vertices: [0, k], not [0]
        col = {k: arr[:, i] for i, k in enumerate(names)}
    else:
        order = _PLY_FORMATS[fmt]
        offset = start
        for name, count, eprops in elements[:vi]:
            if any(t is None for _, t in eprops):
                raise bad(f"element {name!r} with list properties before the vertices")
            offset += count * sum(np.dtype(t).itemsize for _, t in eprops)
        dt = np.dtype([(k, order + t) for k, t in props])
        if offset + n * dt.itemsize > len(data):
            raise bad(
                f"{n} vertices of {dt.itemsize} bytes declared, but the file has "
                f"{max(len(data) - offset, 0)} bytes for them (truncated?)"
            )
        rec = np.frombuffer(data, dt, n, offset) if n else np.zeros(0, dt)
        col = {k: rec[k].astype(np.float64) for k in names}
    pts = np.stack([col["x"], col["y"], col["z"]], 1)
    has_n = {"nx", "ny", "nz"} <= set(col)
    nrm = np.stack([col["nx"], col["ny"], col["nz"]], 1) if has_n else None
    for what, a in (("coordinates", pts), ("normals", nrm)):
        if a is not None and not np.isfinite(a).all():
            i = int(np.argmin(np.isfinite(a).all(axis=1)))
            raise bad(f"vertex {i} has non-finite {what} {a[i].tolist()}")
    return pts, nrm
